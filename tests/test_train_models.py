"""Shapes, bounds, the ResNet18 layout, gradient paths and freezing of the training models."""

import dataclasses

import pytest
import torch

from carrt.errors import UserError
from training.backbone import ResNet18Backbone
from training.data import Normalisation
from training.models import NIG, PolicyNet, WorldModel, WorldPrediction
from training.profiles import PROFILES, get_profile

TINY = get_profile("tiny")


def batch(n, profile, seed=0):
    g = torch.Generator().manual_seed(seed)
    image = torch.randint(0, 256, (n, 96, 96, 3), dtype=torch.uint8, generator=g)
    speed = torch.rand(n, 1, generator=g) * 2.5
    actions = torch.rand(n, profile.horizon, 2, generator=g) * torch.tensor([2.0, 1.0])
    return image, speed, actions - torch.tensor([1.0, 0.0])


def test_get_profile_names_the_choices():
    assert set(PROFILES) == {"tiny", "cpu", "paper"}
    assert get_profile("paper").width == 64
    with pytest.raises(ValueError, match="tiny, cpu, paper"):
        get_profile("huge")


def check_nig(p: NIG, shape):
    for t in (p.gamma, p.nu, p.alpha, p.beta):
        assert t.shape == shape and t.dtype == torch.float32
        assert torch.isfinite(t).all()
    assert (p.nu > 0).all() and (p.alpha > 1).all() and (p.beta > 0).all()


@pytest.mark.parametrize("name, n", [("tiny", 4), ("cpu", 2), ("paper", 1)])
def test_output_shapes_and_ranges(name, n):
    torch.manual_seed(0)
    profile = get_profile(name)
    h, size = profile.horizon, profile.predict_size
    image, speed, actions = batch(n, profile)
    policy, world = PolicyNet(profile).eval(), WorldModel(profile).eval()
    with torch.no_grad():
        mu, sigma = policy(image, speed)
        pred = world(image, speed, actions)
        eps = torch.randn(n, h, 2) * 10
        sampled = policy.sample(image, speed, eps)
        u = world.uncertainties(pred)
    assert mu.shape == sigma.shape == sampled.shape == (n, h, 2)
    for a in (mu, sampled):
        assert (a[..., 0] >= -1).all() and (a[..., 0] <= 1).all()
        assert (a[..., 1] >= -1).all() and (a[..., 1] <= 1).all()  # throttle < 0 brakes
    assert (sigma >= profile.min_sigma).all()
    assert isinstance(pred, WorldPrediction)
    check_nig(pred.image, (n, h, 3, size, size))
    check_nig(pred.speed, (n, h, 1))
    assert pred.collision.shape == (n, h, 2) and (pred.collision >= 0).all()
    for x in u:
        assert x.shape == (n, h) and torch.isfinite(x).all() and (x > 0).all()


def test_sample_is_mu_plus_sigma_eps_and_differentiable():
    torch.manual_seed(0)
    policy = PolicyNet(TINY)
    image, speed, _ = batch(3, TINY)
    mu, sigma = policy(image, speed)
    assert torch.allclose(policy.sample(image, speed, torch.zeros(3, 10, 2)), mu)
    eps = torch.full((3, 10, 2), 0.1)
    assert torch.allclose(policy.sample(image, speed, eps), mu + 0.1 * sigma)
    policy.sample(image, speed, eps).sum().backward()
    assert policy.head[-1].weight.grad.abs().sum() > 0


# torchvision resnet18's state_dict, a few entries (fc removed): name → shape
RESNET18 = {
    "conv1.weight": (64, 3, 7, 7),
    "bn1.weight": (64,),
    "bn1.running_mean": (64,),
    "layer1.0.conv1.weight": (64, 64, 3, 3),
    "layer1.1.bn2.bias": (64,),
    "layer2.0.conv1.weight": (128, 64, 3, 3),
    "layer2.0.downsample.0.weight": (128, 64, 1, 1),
    "layer2.0.downsample.1.weight": (128,),
    "layer2.0.downsample.1.running_var": (128,),
    "layer3.0.downsample.0.weight": (256, 128, 1, 1),
    "layer3.1.conv2.weight": (256, 256, 3, 3),
    "layer4.0.conv1.weight": (512, 256, 3, 3),
    "layer4.1.bn2.num_batches_tracked": (),
    "layer4.1.bn2.bias": (512,),
}


def test_backbone_at_width_64_is_torchvision_resnet18():
    net = ResNet18Backbone(64)
    state = net.state_dict()
    for name, shape in RESNET18.items():
        assert tuple(state[name].shape) == shape, name
    assert len(state) == 120  # torchvision's 122 keys minus fc.weight, fc.bias
    assert not any(k.startswith("fc.") for k in state)
    assert sum(p.numel() for p in net.parameters()) == 11_176_512
    assert net.out_features == 512
    assert "layer1.0.downsample.0.weight" not in state  # torchvision has none in layer1


def test_load_pretrained_round_trips_a_torchvision_state_dict(tmp_path):
    torch.manual_seed(1)
    src = ResNet18Backbone(64)
    state = dict(src.state_dict())
    state["fc.weight"], state["fc.bias"] = torch.randn(1000, 512), torch.randn(1000)
    path = tmp_path / "resnet18.pth"
    torch.save(state, path)
    torch.manual_seed(2)
    dst = ResNet18Backbone(64)
    dst.load_pretrained(path)
    for k, v in src.state_dict().items():
        assert torch.equal(dst.state_dict()[k], v), k
    with pytest.raises(ValueError, match="width 64"):
        ResNet18Backbone(8).load_pretrained(path)


def test_gradients_reach_the_actions_through_the_world_model():
    torch.manual_seed(0)
    world = WorldModel(TINY)
    image, speed, actions = batch(2, TINY)
    for frozen in (False, True):
        if frozen:
            world.freeze()
        a = actions.clone().requires_grad_(True)
        pred = world(image, speed, a)
        (grad,) = torch.autograd.grad(pred.speed.gamma.sum(), a)
        assert torch.isfinite(grad).all() and grad.abs().sum() > 0
        # later actions cannot change earlier predictions (the GRU is causal)
        (g0,) = torch.autograd.grad(world(image, speed, a).speed.gamma[:, 0].sum(), a)
        assert g0[:, 1:].abs().sum() == 0 and g0[:, 0].abs().sum() > 0


def cudnn_during_gru(world, image, speed, actions, grad: bool) -> bool:
    """Whether cuDNN was enabled while the world model's GRUs ran."""
    seen = []
    hook = world.gru[0].register_forward_pre_hook(
        lambda *_: seen.append(torch.backends.cudnn.enabled)
    )
    with torch.set_grad_enabled(grad):
        world(image, speed, actions)
    hook.remove()
    return seen[0]


def test_a_frozen_world_model_differentiated_runs_its_grus_without_cudnn():
    # cuDNN has no RNN backward in eval mode (the first GPU run's refinement failed on it)
    world = WorldModel(TINY)
    image, speed, actions = batch(2, TINY)
    assert torch.backends.cudnn.enabled
    assert cudnn_during_gru(world, image, speed, actions, grad=True)  # training: cuDNN's
    world.freeze()
    assert cudnn_during_gru(world, image, speed, actions, grad=False)  # imagining: cuDNN's
    assert not cudnn_during_gru(world, image, speed, actions, grad=True)  # refining: not
    assert torch.backends.cudnn.enabled  # and back afterwards


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (cuDNN)")
def test_refinement_backward_through_a_frozen_world_model_on_cuda():
    world, policy = WorldModel(TINY).cuda(), PolicyNet(TINY).cuda()
    world.freeze()
    image, speed, _ = batch(4, TINY)
    image, speed = image.cuda(), speed.cuda()
    actions = policy.sample(image, speed, torch.randn(4, TINY.horizon, 2, device="cuda"))
    world(image, speed, actions).speed.gamma.mean().backward()
    assert policy.head[-1].weight.grad is not None
    assert torch.isfinite(policy.head[-1].weight.grad).all()


def snapshot(module):
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def refinement_style_step(world, policy, n=4, seed=0):
    """What a refinement loop does: train() everything, imagine, backprop, step."""
    world.train()
    policy.train()
    image, speed, _ = batch(n, TINY, seed)
    actions = policy.sample(image, speed, torch.randn(n, TINY.horizon, 2))
    pred = world(image, speed, actions)
    loss = -pred.speed.gamma.mean() + sum(u.mean() for u in world.uncertainties(pred))
    loss.backward()
    with torch.no_grad():  # an SGD step (torch.optim's first use costs seconds of imports)
        for p in [*world.parameters(), *policy.parameters()]:
            if p.requires_grad and p.grad is not None:
                p -= 0.01 * p.grad


def test_freeze_keeps_parameters_and_batchnorm_statistics():
    torch.manual_seed(0)
    world, policy = WorldModel(TINY), PolicyNet(TINY)
    # control: unfrozen, the same step changes the BatchNorm statistics (the test can fail)
    before = snapshot(world)
    refinement_style_step(world, policy)
    assert not torch.equal(before["backbone.bn1.running_mean"],
                           world.state_dict()["backbone.bn1.running_mean"])  # fmt: skip
    world.freeze()
    world.zero_grad(set_to_none=True)
    policy.zero_grad(set_to_none=True)
    before = snapshot(world)
    for seed in range(2):
        refinement_style_step(world, policy, seed=seed)
    after = world.state_dict()
    for k, v in before.items():
        assert torch.equal(v, after[k]), k
    assert not world.training
    assert not any(p.requires_grad or p.grad is not None for p in world.parameters())
    assert policy.head[-1].weight.grad is not None  # the policy still learns through it


def test_normalisation_lives_in_state_dict():
    norm = Normalisation((0.4, 0.45, 0.5), (0.2, 0.21, 0.22), speed_mean=1.1, speed_std=0.6)
    torch.manual_seed(0)
    for cls in (PolicyNet, WorldModel):
        net = cls(TINY)
        net.set_normalisation(norm)
        state = net.state_dict()
        for key in ("image_mean", "image_std", "speed_mean", "speed_std"):
            assert key in state
        fresh = cls(TINY)
        fresh.load_state_dict(state)
        got = fresh.normalisation()
        assert got.image_mean == pytest.approx(norm.image_mean)
        assert got.image_std == pytest.approx(norm.image_std)
        assert got.speed_mean == pytest.approx(1.1) and got.speed_std == pytest.approx(0.6)


def test_policy_normalises_inside_forward():
    torch.manual_seed(0)
    policy = PolicyNet(TINY).eval()
    image, speed, _ = batch(2, TINY)
    with torch.no_grad():
        a = policy(image, speed)[0]
        policy.set_normalisation(Normalisation((0.1, 0.2, 0.3), (0.5, 0.5, 0.5), 2.0, 0.5))
        b = policy(image, speed)[0]
        # same result from float input holding the same 0..255 values
        c = policy(image.float(), speed)[0]
    assert not torch.allclose(a, b)
    assert torch.allclose(b, c)


def test_world_model_normalises_targets_like_its_inputs():
    world = WorldModel(TINY)
    world.set_normalisation(Normalisation((0.5, 0.4, 0.3), (0.25, 0.2, 0.1), 1.0, 0.5))
    future = torch.zeros(2, TINY.horizon, 16, 16, 3, dtype=torch.uint8)
    future[1, 3, 5, 7] = torch.tensor([255, 0, 51], dtype=torch.uint8)
    x = world.normalise_image(future)
    assert x.shape == (2, TINY.horizon, 3, 16, 16)
    assert x[1, 3, :, 5, 7].tolist() == pytest.approx([2.0, -2.0, -1.0], abs=1e-5)
    assert world.normalise_speed(torch.tensor([2.0])).item() == pytest.approx(2.0)
    assert world.denormalise_speed(torch.tensor([2.0])).item() == pytest.approx(2.0)


def test_world_model_encodes_a_frame_once_for_its_sequences():
    """K sequences per frame (the search, the counterfactual check) give what K copies of the
    frame give, and the encoder runs on the N frames only."""
    torch.manual_seed(0)
    world = WorldModel(TINY).eval()
    image, speed, _ = batch(2, TINY)
    actions = torch.rand(2 * 3, TINY.horizon, 2) * 2 - 1
    calls = []
    world.backbone.register_forward_hook(lambda m, i, o: calls.append(i[0].shape[0]))
    with torch.no_grad():
        shared = world.imagine(image, speed, actions, 5.0)
        copies = world.imagine(image.repeat_interleave(3, 0), speed.repeat_interleave(3, 0),
                               actions, 5.0)  # fmt: skip
    assert calls == [2, 6]
    for name, value in shared.items():
        assert value.shape == (6, TINY.horizon)
        torch.testing.assert_close(value, copies[name], rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="5 sequences, 2 frames"):
        world(image, speed, actions[:5])


# ---------------------------------------------------------- where the actions enter (issue 59)
ALL = dataclasses.replace(TINY, world_action_inputs="all")


def paper_forward(world, image, speed, actions):
    """Reveries-net's forward as it was before `world_action_inputs` existed (actions into the
    first GRU layer only), written out on the module's own parts."""
    context = world._encode(image, speed)
    x, states = world.action_net(actions.to(torch.float32)), []
    for init, gru in zip(world.init_state, world.gru, strict=True):
        x, _ = gru(x, torch.tanh(init(context)).unsqueeze(0))
        states.append(x)
    n, h = x.shape[:2]
    img = world.image_head(states[0].reshape(n * h, -1)).view(n, h, 4, 3, 16, 16)
    return (
        img,
        world.speed_head(states[1]),
        torch.nn.functional.softplus(world.collision_head(states[-1])),
    )


def test_first_is_the_paper_forward_bit_for_bit_with_the_same_weights():
    assert TINY.world_action_inputs == "first"
    torch.manual_seed(0)
    world = WorldModel(TINY).eval()
    again = WorldModel(ALL)
    # the paper's layout: layers 2, 3 read the hidden state alone, the heads the state alone
    shapes = {k: tuple(v.shape) for k, v in world.state_dict().items()}
    hidden = TINY.gru_hidden
    assert shapes["gru.1.weight_ih_l0"] == (3 * hidden, hidden)
    assert shapes["collision_head.0.weight"] == (hidden, hidden)
    assert shapes["image_head.fc.weight"][1] == hidden
    assert again.state_dict()["gru.1.weight_ih_l0"].shape == (3 * hidden, hidden + 8)
    image, speed, actions = batch(3, TINY)
    with torch.no_grad():
        pred = world(image, speed, actions)
        img, spd, coll = paper_forward(world, image, speed, actions)
    assert torch.equal(pred.collision, coll)
    assert torch.equal(pred.speed.gamma[..., 0], spd[..., 0])
    assert torch.equal(pred.image.gamma, img[:, :, 0])


def test_all_has_the_same_output_shapes():
    torch.manual_seed(0)
    world = WorldModel(ALL).eval()
    image, speed, actions = batch(4, ALL)
    with torch.no_grad():
        pred = world(image, speed, actions)
        out = world.imagine(image, speed, actions, 5.0)
    check_nig(pred.image, (4, ALL.horizon, 3, 16, 16))
    check_nig(pred.speed, (4, ALL.horizon, 1))
    assert pred.collision.shape == (4, ALL.horizon, 2) and (pred.collision >= 0).all()
    assert all(v.shape == (4, ALL.horizon) for v in out.values())


def action_entries(world) -> dict[str, tuple[torch.Tensor, slice]]:
    """Each place the action features enter: (weight, its columns that read them)."""
    hidden = world.profile.gru_hidden
    entries = {"gru0": (world.gru[0].weight_ih_l0, slice(None))}
    if world.action_inputs == "all":
        for i in range(1, len(world.gru)):
            entries[f"gru{i}"] = (world.gru[i].weight_ih_l0, slice(hidden, None))
        entries["collision_head"] = (world.collision_head[0].weight, slice(hidden, None))
    return entries


def collision_gradient(world, only: str | None) -> float:
    """|d collision evidence / d actions| with every action entry but `only` cut (zeroed)."""
    image, speed, actions = batch(2, world.profile)
    with torch.no_grad():
        for name, (weight, cols) in action_entries(world).items():
            if name != only:
                weight[:, cols] = 0.0
    a = actions.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(world(image, speed, a).collision.sum(), a)
    return float(grad.abs().sum())


@pytest.mark.parametrize("entry", ["gru0", "gru1", "gru2", "collision_head"])
def test_with_all_the_collision_head_hears_the_action_at_every_entry(entry):
    torch.manual_seed(0)
    assert collision_gradient(WorldModel(ALL), entry) > 0
    torch.manual_seed(0)
    assert collision_gradient(WorldModel(ALL), "none") == 0  # every entry cut: deaf


def test_with_first_cutting_the_first_layer_makes_it_deaf():
    torch.manual_seed(0)
    assert collision_gradient(WorldModel(TINY), "gru0") > 0
    torch.manual_seed(0)
    assert collision_gradient(WorldModel(TINY), None) == 0


def test_action_inputs_travel_with_the_checkpoint_and_old_ones_load_as_first(tmp_path):
    from training import checkpoint as ck
    from training.config import TrainingConfig, UsageError, apply_set

    cfg = apply_set(TrainingConfig(profile="tiny"), ["world_action_inputs=all"])
    assert cfg.profile_obj == ALL
    with pytest.raises(UsageError, match="world_action_inputs must be one of first, all"):
        apply_set(TrainingConfig(), ["world_action_inputs=every"]).validate()
    fields = dataclasses.asdict(cfg.profile_obj)
    assert ck.profile_of({"profile_fields": fields}).world_action_inputs == "all"
    old = {k: v for k, v in dataclasses.asdict(TINY).items() if k != "world_action_inputs"}
    assert ck.profile_of({"profile_fields": old}) == TINY  # saved before the field: first
    assert ck.profile_of({"profile": "tiny"}) == TINY
    with pytest.raises(UserError, match="world_action_inputs=all, this model is first"):
        WorldModel(TINY).load_state_dict(WorldModel(ALL).state_dict())
    with pytest.raises(UserError, match="world_action_inputs=first, this model is all"):
        WorldModel(ALL).load_state_dict(WorldModel(TINY).state_dict())
