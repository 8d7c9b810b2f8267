"""The world-model and refinement stages on the simulator's episodes (tiny profile, a few dozen
steps each).

The world model's loss must fall on all its parts and it must respond to the actions (the
evaluation's action response and AUROC are checked here too); refinement must improve its
objective and leave the world model bit-identical (parameters AND BatchNorm statistics) while
the policy moves, and each of its safeguards (anchor, imitation term, centred gradient, throttle
only, the class weight divided out of the imagined risk) must do what it says. Imitation is in
test_train_imitation.py, the stage runner and its checkpoints in test_train_trainer.py.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from train_stage_rig import first_last, models, stage_data, tiny  # noqa: E402

from training import checkpoint as ck  # noqa: E402
from training.data import take  # noqa: E402
from training.imitation import imitation_loss, train_imitation  # noqa: E402
from training.refine import (  # noqa: E402
    anchor_penalty,
    held_out_objective,
    imagined_objective,
    train_refine,
)
from training.report_metrics import action_response, auroc, spearman  # noqa: E402
from training.trainer import param_digest  # noqa: E402
from training.world_model_stage import train_world_model  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def data(sim_episodes):
    return stage_data(sim_episodes)


@pytest.fixture(scope="module")
def trained_world_model(data):
    """A world model after 25 steps, and their history: refinement needs one that reacts to
    its actions (an untrained one barely does, so the objective would hardly move)."""
    _, norm, windows, _ = data
    with torch.random.fork_rng():
        torch.set_num_threads(1)
        _, world_model = models(norm)
        cfg = tiny(world_model_steps=60, world_model_batch_size=8, world_model_lr=2e-3)
        result = train_world_model(cfg, world_model, windows, norm, collision_weight=5.0)
    return world_model, result


def test_world_model_loss_falls_on_all_its_parts(trained_world_model):
    _, result = trained_world_model
    assert result.steps == 60
    for key in ("loss", "image", "speed", "collision"):
        first, last = first_last(result.history, key)
        assert last < 0.9 * first, (key, first, last)


def test_refinement_improves_the_objective_and_leaves_the_world_model_untouched(
    data, trained_world_model
):
    _, norm, windows, _ = data
    policy, _ = models(norm)
    world_model = copy.deepcopy(trained_world_model[0])
    world_model.train()  # refinement itself must freeze it
    frozen = param_digest(world_model)
    policy_before = param_digest(policy)
    # the paper's form (no anchor): the objective itself must move
    cfg = tiny(refine_steps=40, refine_batch_size=8, refine_lr=3e-4, refine_w_anchor=0.0,
               refine_center_gradient=False)  # fmt: skip
    world_model.eval()
    before = held_out_objective(cfg, policy, world_model, windows, "cpu", limit=64)
    world_model.train()
    result = train_refine(cfg, policy, world_model, windows, norm)
    after = held_out_objective(cfg, policy, world_model, windows, "cpu", limit=64)
    assert result.steps == 40
    assert after["loss"] < before["loss"] - 0.1, (before, after)
    # Each training step draws new start frames and new ε, so its loss is noisy; the fixed
    # ε = 0 objective above is the fair before/after comparison.
    assert len(result.history) == 40 and all(np.isfinite(h["loss"]) for h in result.history)
    now = param_digest(world_model)
    assert frozen.keys() == now.keys()
    assert any("running_mean" in k for k in now)  # BatchNorm statistics are compared too
    for k in frozen:
        assert torch.equal(frozen[k], now[k]), k
    assert not world_model.training
    assert all(not p.requires_grad for p in world_model.parameters())
    changed = [k for k, v in param_digest(policy).items() if not torch.equal(v, policy_before[k])]
    assert any("head" in k for k in changed) and any("backbone" in k for k in changed)


def test_the_anchor_keeps_refinement_near_the_policy_it_started_from(data, trained_world_model):
    """refine_w_anchor (our safeguard, off in the paper's form): same seed, same steps; the
    anchored run's plans move less from the starting policy's, and it logs the penalty."""
    _, norm, windows, _ = data
    batch = take(windows, range(16))
    moved, logged = {}, {}
    for weight in (0.0, 100.0):
        torch.manual_seed(0)
        policy, _ = models(norm)
        policy.eval()
        with torch.no_grad():
            start = policy(batch["image"], batch["speed"])[0]
        world_model = copy.deepcopy(trained_world_model[0])
        cfg = tiny(refine_steps=30, refine_batch_size=8, refine_lr=1e-3, refine_w_anchor=weight)
        result = train_refine(cfg, policy, world_model, windows, norm)
        with torch.no_grad():
            moved[weight] = float(anchor_penalty(policy(batch["image"], batch["speed"])[0], start))
        logged[weight] = "anchor" in result.history[-1]
    assert moved[100.0] < 0.5 * moved[0.0], moved
    assert logged == {0.0: False, 100.0: True}


def test_the_imitation_term_keeps_refinement_near_the_demonstrations(data, trained_world_model):
    """refine_w_imitation (our second safeguard, off in the paper's form): from the same
    imitation-trained policy, same seed and steps, no anchor; without the term refinement moves
    the policy away from the person's a* on the demonstrations, with it the policy drifts less
    than half as far, and the run logs the term."""
    _, norm, windows, free = data
    batch = take(free, range(min(len(free), 64)))
    torch.manual_seed(0)
    imitated, _ = models(norm)
    train_imitation(tiny(imitation_steps=60, imitation_batch_size=16, imitation_lr=3e-3),
                    imitated, free)  # fmt: skip
    imitated.eval()
    with torch.no_grad():
        start = float(imitation_loss(imitated, batch)[0])
    drift, logged = {}, {}
    for weight in (0.0, 100.0):
        torch.manual_seed(0)
        policy = copy.deepcopy(imitated)
        world_model = copy.deepcopy(trained_world_model[0])
        cfg = tiny(refine_steps=30, refine_batch_size=16, refine_lr=3e-3, refine_w_anchor=0.0,
                   refine_w_imitation=weight)  # fmt: skip
        result = train_refine(cfg, policy, world_model, windows, norm, demonstrations=free)
        with torch.no_grad():
            drift[weight] = float(imitation_loss(policy, batch)[0]) - start
        logged[weight] = "imitation_l1" in result.history[-1]
    assert drift[0.0] > 0.02, drift  # refinement alone does pull away from the demonstrations
    assert drift[100.0] < 0.5 * drift[0.0], drift
    assert logged == {0.0: False, 100.0: True}


def test_a_centred_gradient_changes_plans_per_start_not_all_alike(data, trained_world_model):
    """refine_center_gradient (our third safeguard, off in the paper's form): the same run with
    and without it. Uncentred, the world model's average preference moves every plan alike;
    centred, the batch-mean plan moves far less while the plans still change start by start."""
    _, norm, windows, _ = data
    batch = take(windows, range(0, len(windows), max(1, len(windows) // 64)))
    common, individual = {}, {}
    for flag in (False, True):
        torch.manual_seed(0)
        policy, _ = models(norm)
        policy.eval()
        with torch.no_grad():
            start = policy(batch["image"], batch["speed"])[0]
        # a small step: at 1e-3 Adam's per-parameter normalisation turns any residual
        # correlation into a full step and both runs saturate
        cfg = tiny(refine_steps=30, refine_batch_size=8, refine_lr=1e-4, refine_w_anchor=0.0,
                   refine_center_gradient=flag)  # fmt: skip
        train_refine(cfg, policy, copy.deepcopy(trained_world_model[0]), windows, norm)
        with torch.no_grad():
            moved = policy(batch["image"], batch["speed"])[0] - start
        shift = moved.mean(dim=0)  # (H, 2): what every plan did alike
        common[flag] = float(shift.abs().mean())
        individual[flag] = float((moved - shift).abs().mean())
    # the ratio was under 0.3 on the AMD EPYC VM it was written on and 0.32 on an Intel Xeon one,
    # same packages (the float kernels differ by CPU): what is asserted is "far less"
    assert common[True] < 0.5 * common[False], common
    assert individual[True] > 0.1 * individual[False], individual


def test_without_refine_steering_the_world_model_gradient_reaches_only_the_throttle(
    data, trained_world_model
):
    """refine_steering False (our fifth safeguard, True in the paper's form): the gradient the
    imagined objective leaves on the sampled actions has a zero steering channel and the same
    throttle channel as the paper's form; centred or not."""
    _, _, windows, _ = data
    world_model = copy.deepcopy(trained_world_model[0])
    world_model.freeze()
    batch = take(windows, range(8))
    grads = {}
    for steering in (True, False):
        for centred in (False, True):
            actions = batch["actions"].clone().requires_grad_(True)
            cfg = tiny(refine_steering=steering, refine_center_gradient=centred)
            loss, _ = imagined_objective(cfg, world_model, batch, actions, (1.0, 10.0, 1.0))
            loss.backward()
            grads[steering, centred] = actions.grad.clone()
    for centred in (False, True):
        assert grads[True, centred][..., 0].abs().sum() > 0  # the paper's form steers
        assert torch.equal(
            grads[False, centred][..., 0], torch.zeros_like(grads[True, centred][..., 0])
        )
        assert torch.allclose(grads[False, centred][..., 1], grads[True, centred][..., 1])
        assert grads[False, centred][..., 1].abs().sum() > 0


def test_refinement_gradient_reaches_the_actions_through_the_frozen_world_model(data):
    _, norm, windows, _ = data
    _, world_model = models(norm)
    world_model.freeze()
    batch = torch.utils.data.default_collate([windows[i] for i in range(4)])
    actions = batch["actions"].clone().requires_grad_(True)
    imagined = world_model.imagine(batch["image"], batch["speed"], actions, 10.0)
    sum(v.sum() for v in imagined.values()).backward()
    assert actions.grad is not None and actions.grad.abs().sum() > 0
    assert all(p.grad is None for p in world_model.parameters())


def test_imagined_risk_has_the_training_class_weight_divided_out(data, trained_world_model):
    """The world-model stage records the collision class weight it trained with (5 here);
    imagine() divides it back out of the odds, p / (p + w(1 − p)), unless told not to (the
    paper's form); the correction keeps the gradient to the actions."""
    _, _, windows, _ = data
    world_model = copy.deepcopy(trained_world_model[0])
    world_model.freeze()
    assert float(world_model.collision_class_weight) == 5.0
    batch = torch.utils.data.default_collate([windows[i] for i in range(4)])
    actions = batch["actions"].clone().requires_grad_(True)
    raw = world_model.imagine(batch["image"], batch["speed"], actions, 10.0, False)
    corrected = world_model.imagine(batch["image"], batch["speed"], actions, 10.0)
    p = raw["p_collision"].detach()
    assert torch.allclose(corrected["p_collision"].detach(), p / (p + 5.0 * (1 - p)))
    assert (corrected["p_collision"] < raw["p_collision"]).all()
    for key in ("speed", "u_image", "u_speed", "u_collision"):
        assert torch.equal(corrected[key], raw[key])
    corrected["p_collision"].sum().backward()
    assert actions.grad is not None and actions.grad.abs().sum() > 0
    with torch.no_grad():  # weight 1: nothing to divide out
        world_model.collision_class_weight.fill_(1.0)
        same = world_model.imagine(batch["image"], batch["speed"], actions, 10.0)
    assert torch.allclose(same["p_collision"], p)


def test_the_collision_class_weight_survives_a_checkpoint(data, trained_world_model, tmp_path):
    """Saved with the weights; a checkpoint from before the weight was recorded loads with 1."""
    _, norm, _, _ = data
    policy, _ = models(norm)
    world_model = trained_world_model[0]
    fields = {
        "config": {}, "profile": "tiny", "stage": "world_model", "step": 60,
        "policy": policy.state_dict(), "world_model": world_model.state_dict(),
        "optimizer": None, "normalisation": norm.to_dict(), "data_digest": "d", "iteration": 0,
        "code_version": ck.code_version(), "episodes": ["e1"],
    }  # fmt: skip
    ck.save_checkpoint(tmp_path / "wm.pt", **fields)
    loaded, _ = ck.load_world_model(tmp_path / "wm.pt")
    assert float(loaded.collision_class_weight) == 5.0
    old = {k: v for k, v in world_model.state_dict().items() if k != "collision_class_weight"}
    ck.save_checkpoint(tmp_path / "old.pt", **{**fields, "world_model": old})
    loaded, _ = ck.load_world_model(tmp_path / "old.pt")
    assert float(loaded.collision_class_weight) == 1.0


def test_no_uncertainty_removes_the_uncertainty_term(data):
    _, norm, windows, _ = data
    policy, world_model = models(norm)
    world_model.freeze()
    with_u = held_out_objective(tiny(), policy, world_model, windows, "cpu", limit=16)
    no_u = held_out_objective(
        tiny(no_uncertainty=True), policy, world_model, windows, "cpu", limit=16
    )
    u = with_u["u_image"] + with_u["u_speed"] + with_u["u_collision"]
    assert no_u["loss"] == pytest.approx(with_u["loss"] - 10 * u, rel=1e-4)


def test_the_action_response_is_zero_for_a_world_model_blind_to_the_actions(
    data, trained_world_model
):
    """With the action input cut (its layer's weights and bias zero) every shifted sequence is
    imagined alike: 0 on each response; the trained one responds to both channels."""
    _, _, windows, _ = data
    world_model, _ = trained_world_model
    seen = action_response(world_model, windows, "cpu", limit=32)
    assert seen["response_steering_image"] > 0 and seen["response_throttle_speed"] > 0
    assert seen["response_image_error"] > 0
    blind = copy.deepcopy(world_model)
    with torch.no_grad():
        for p in blind.action_net.parameters():
            p.zero_()
    cut = action_response(blind, windows, "cpu", limit=32)
    for key in ("response_steering_risk", "response_steering_image", "response_throttle_speed"):
        assert cut[key] == pytest.approx(0.0, abs=1e-6), key
    assert cut["response_image_error"] > 0  # it still predicts, just not from the actions


def test_auroc_matches_the_pairwise_definition():
    rng = np.random.default_rng(0)
    scores = rng.integers(0, 6, 200).astype(float)  # many ties
    labels = rng.random(200) < 0.2
    pos, neg = scores[labels], scores[~labels]
    pairwise = ((pos[:, None] > neg[None]) + 0.5 * (pos[:, None] == neg[None])).mean()
    assert auroc(scores, labels) == pytest.approx(pairwise)
    assert auroc([0.1, 0.9], [0, 1]) == 1.0 and auroc([0.9, 0.1], [0, 1]) == 0.0
    assert np.isnan(auroc([0.1, 0.2], [0, 0]))
    assert spearman([1, 2, 3, 4], [10, 20, 30, 40]) == pytest.approx(1.0)
