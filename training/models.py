"""The policy and the world model ("Reveries-net"), with the paper's structure (the DIRL paper).

Both take the raw uint8 frame and the speed in m/s, exactly as carrt records and feeds them:
the normalisation lives in buffers inside the modules, so it is saved with the weights and
exported into the ONNX graph, and no caller can normalise twice or forget to.
"""

from __future__ import annotations

import contextlib
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from carrt.errors import UserError
from carrt.model_contract import ACTION_HIGH, ACTION_LOW
from training.backbone import ResNet18Backbone
from training.losses import NIG, dirichlet_probability, dirichlet_uncertainty, nig_uncertainty
from training.profiles import Profile

if TYPE_CHECKING:
    from training.data import Normalisation


# ------------------------------------------------------------------------------ shared parts
class _Normalised(nn.Module):
    """Holds the normalisation as buffers: saved in state_dict, traced into the ONNX graph."""

    def _init_normalisation(self) -> None:
        self.register_buffer("image_mean", torch.full((1, 3, 1, 1), 0.5))
        self.register_buffer("image_std", torch.full((1, 3, 1, 1), 0.25))
        self.register_buffer("speed_mean", torch.zeros(1))
        self.register_buffer("speed_std", torch.ones(1))

    def set_normalisation(self, norm: Normalisation) -> None:
        self.image_mean.copy_(torch.tensor(norm.image_mean).view(1, 3, 1, 1))
        self.image_std.copy_(torch.tensor(norm.image_std).view(1, 3, 1, 1))
        self.speed_mean.fill_(float(norm.speed_mean))
        self.speed_std.fill_(float(norm.speed_std))

    def normalisation(self) -> Normalisation:
        from training.data import Normalisation

        return Normalisation(
            image_mean=tuple(self.image_mean.flatten().tolist()),
            image_std=tuple(self.image_std.flatten().tolist()),
            speed_mean=float(self.speed_mean),
            speed_std=float(self.speed_std),
        )

    def normalise_image(self, image: Tensor) -> Tensor:
        """uint8 (..., h, w, 3) NHWC, 0..255 → float (..., 3, h, w) in normalised units."""
        nd = image.dim()  # explicit non-negative perm: movedim(-1, -3) exports a bad Transpose
        perm = [*range(nd - 3), nd - 1, nd - 3, nd - 2]
        x = image.to(torch.float32).permute(*perm) / 255.0
        return (x - self.image_mean.squeeze(0)) / self.image_std.squeeze(0)

    def normalise_speed(self, speed: Tensor) -> Tensor:
        """m/s → normalised units (any shape)."""
        return (speed.to(torch.float32) - self.speed_mean) / self.speed_std

    def denormalise_speed(self, speed: Tensor) -> Tensor:
        """Normalised units → m/s (any shape)."""
        return speed * self.speed_std + self.speed_mean

    def _encode(self, image: Tensor, speed: Tensor) -> Tensor:
        """(N,96,96,3) uint8 and (N,1) m/s → concat(f_i, f_s) (N, 8·width + speed_features)."""
        if speed.dim() == 1:
            speed = speed.unsqueeze(-1)
        x = self.normalise_image(image)
        size = self.profile.input_size
        if x.shape[-1] != size or x.shape[-2] != size:
            # Bilinear (an ONNX Resize at opset 17); a smaller backbone input is the cheapest
            # speed-up on a CPU, and the graph's input stays the contract's 96×96 frame.
            x = F.interpolate(x, size=(size, size), mode="bilinear", align_corners=False)
        f_i = self.backbone(x)
        f_s = self.speed_net(self.normalise_speed(speed))
        return torch.cat([f_i, f_s], dim=-1)


def _speed_net(features: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(1, features), nn.ReLU(), nn.Linear(features, features), nn.ReLU()
    )


def clamp_actions(actions: Tensor) -> Tensor:
    """Steering and throttle into carrt.model_contract's bounds, both [-1, 1] (throttle < 0
    brakes/reverses, as the demonstrator does)."""
    lo = actions.new_tensor(ACTION_LOW)
    hi = actions.new_tensor(ACTION_HIGH)
    return torch.maximum(torch.minimum(actions, hi), lo)


def sample_actions(mu: Tensor, sigma: Tensor, eps: Tensor) -> Tensor:
    """a = μ + σ·ε (reparameterised: differentiable in μ and σ), clamped to the bounds."""
    return clamp_actions(mu + sigma * eps)


# ------------------------------------------------------------------------------------ policy
class PolicyNet(_Normalised):
    """ResNet18 image features + dense speed features → Gaussian over the next H actions."""

    def __init__(self, profile: Profile) -> None:
        super().__init__()
        self.profile = profile
        self.horizon = profile.horizon
        self.min_sigma = profile.min_sigma
        self._init_normalisation()
        self.backbone = ResNet18Backbone(profile.width)
        self.speed_net = _speed_net(profile.speed_features)
        hidden = profile.policy_hidden
        self.head = nn.Sequential(
            nn.Linear(profile.image_features + profile.speed_features, hidden),
            nn.ReLU(),
            nn.Linear(hidden, hidden),
            nn.ReLU(),
            nn.Linear(hidden, profile.horizon * 4),
        )
        out = self.head[-1]
        with torch.no_grad():  # start near μ = (0, 0.5), σ = min_sigma + 0.2
            out.weight.mul_(0.1)
            bias = out.bias.view(profile.horizon, 4)
            bias.zero_()
            bias[:, 1].fill_(math.atanh(0.5))
            bias[:, 2:].fill_(float(torch.log(torch.expm1(torch.tensor(0.2)))))

    def forward(self, image: Tensor, speed: Tensor) -> tuple[Tensor, Tensor]:
        out = self.head(self._encode(image, speed)).view(-1, self.horizon, 4)
        # tanh on both: throttle spans [-1, 1] because the demonstrator brakes (~7 % of a*
        # are negative); a sigmoid could never imitate, or refine towards, a brake.
        mu = torch.tanh(out[..., :2])
        sigma = self.min_sigma + F.softplus(out[..., 2:])
        return mu, sigma

    def sample(self, image: Tensor, speed: Tensor, eps: Tensor) -> Tensor:
        mu, sigma = self(image, speed)
        return sample_actions(mu, sigma, eps)


# ------------------------------------------------------------------------------- world model
@dataclass
class WorldPrediction:
    image: NIG  # each (N, H, 3, P, P), normalised image units
    speed: NIG  # each (N, H, 1), normalised speed units
    collision: Tensor  # (N, H, 2) evidence ≥ 0, class 1 = collision


def _decoder_plan(size: int) -> tuple[int, int]:
    """(start side, doublings): 96 → 3·2⁵, 32 → 4·2³, 16 → 4·2², 20 → 5·2², 15 → 15·2⁰."""
    side, ups = size, 0
    while side % 2 == 0 and side // 2 >= 3:
        side, ups = side // 2, ups + 1
    return side, ups


class ImageDecoder(nn.Module):
    """GRU state → NIG parameters per pixel and channel: linear to a small map, ×2 upsampling
    convolutions up to predict_size, then a 3×3 conv to 4·3 channels.

    The ×2 upsampling is learned (4×4 transposed conv, stride 2) instead of nearest-neighbour
    upsampling followed by a 3×3 conv: 2.3× faster on a CPU for the N·H small maps decoded per
    batch; the final 3×3 conv smooths the transposed convs' checkerboard pattern.
    """

    def __init__(self, hidden: int, width: int, size: int) -> None:
        super().__init__()
        self.side, ups = _decoder_plan(size)
        floor = max(8, width // 4)
        chans = [max(2 * width >> i, floor) for i in range(ups + 1)]
        self.chans0 = chans[0]
        self.fc = nn.Linear(hidden, chans[0] * self.side * self.side)
        layers: list[nn.Module] = []
        for cin, cout in itertools.pairwise(chans):
            layers += [nn.ConvTranspose2d(cin, cout, 4, 2, 1), nn.ReLU()]
        layers.append(nn.Conv2d(chans[-1], 4 * 3, 3, 1, 1))
        self.convs = nn.Sequential(*layers)

    def forward(self, h: Tensor) -> Tensor:
        """(B, hidden) → (B, 4, 3, P, P)."""
        x = F.relu(self.fc(h)).view(-1, self.chans0, self.side, self.side)
        x = self.convs(x)
        return x.view(x.shape[0], 4, 3, x.shape[-2], x.shape[-1])


def _mlp(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(cin, cin), nn.ReLU(), nn.Linear(cin, cout))


def _rnn_backward_outside_training(training: bool):
    """cuDNN has no RNN backward outside training mode, and refinement differentiates the
    frozen world model (eval mode: its BatchNorm statistics must not move) with respect to the
    actions; there the GRUs run on PyTorch's own kernels (cuDNN refuses: "cudnn RNN backward
    can only be called in training mode"). Elsewhere: unchanged."""
    if training or not torch.is_grad_enabled():
        return contextlib.nullcontext()
    return torch.backends.cudnn.flags(enabled=False)


class WorldModel(_Normalised):
    """Reveries-net: (image_t, speed_t, a_t..a_{t+H−1}) → images, speeds, collisions at
    t+1..t+H, each with evidential uncertainty.

    concat(f_i, f_s) initialises every GRU layer. The paper gives f_i 512 + f_s 128 = 640 and a
    GRU of hidden 512, sizes that do not line up; we project the concatenation to the hidden
    size with one linear layer (+ tanh, the GRU's state range) per GRU layer. The GRU is three
    single-layer nn.GRU modules stacked by hand, so each layer's state sequence is available:
    layer 1's drives the image decoder, layer 2's the speed head, the last layer's the
    collision head (the paper's assignment).

    `profile.world_action_inputs` says where the actions enter. "first" is the paper's: the
    first GRU layer only, so every later state and every head sees an action only through
    states the image initialised, and a model fitted to drives where the action is a function
    of the image can ignore it. "all" (the study's variant) also feeds the step's action features to
    every later GRU layer (concatenated with the layer below's state) and to every head
    (concatenated with the state it reads): the collision head can read the action directly.
    "first" builds exactly the modules, parameters and forward it always did.
    """

    def __init__(self, profile: Profile) -> None:
        super().__init__()
        self.profile = profile
        self.horizon = profile.horizon
        self._frozen = False
        self._init_normalisation()
        hidden = profile.gru_hidden
        self.backbone = ResNet18Backbone(profile.width)
        self.speed_net = _speed_net(profile.speed_features)
        context = profile.image_features + profile.speed_features
        self.init_state = nn.ModuleList(
            nn.Linear(context, hidden) for _ in range(profile.gru_layers)
        )
        self.action_net = nn.Sequential(nn.Linear(2, profile.action_features), nn.ReLU())
        self.action_inputs = profile.world_action_inputs
        # "all": each later layer and each head also gets the step's action features
        extra = profile.action_features if self.action_inputs == "all" else 0
        self.gru = nn.ModuleList(
            nn.GRU(profile.action_features if i == 0 else hidden + extra, hidden, batch_first=True)
            for i in range(profile.gru_layers)
        )
        self.image_head = ImageDecoder(hidden + extra, profile.width, profile.predict_size)
        self.speed_head = _mlp(hidden + extra, 4)
        self.collision_head = _mlp(hidden + extra, 2)
        # The weight of the collision class in the loss this model was trained with (set by
        # the world-model stage): imagine() divides it back out of the odds. Saved with the
        # weights, so a loaded model imagines what it imagined in the run that made it.
        self.register_buffer("collision_class_weight", torch.ones(1))

    def forward(self, image: Tensor, speed: Tensor, actions: Tensor) -> WorldPrediction:
        """N frames, N·K action sequences (start i's are rows i·K…i·K+K−1): a frame is encoded
        once for its K sequences (the search and the check imagine K alternatives per start)."""
        context = self._encode(image, speed)
        k, rest = divmod(actions.shape[0], context.shape[0])
        if rest or k < 1:
            raise ValueError(f"world model: {actions.shape[0]} sequences, {len(context)} frames")
        context = context.repeat_interleave(k, dim=0) if k > 1 else context
        a = self.action_net(actions.to(torch.float32))
        every = self.action_inputs == "all"
        x, states = a, []
        with _rnn_backward_outside_training(self.training):
            for i, (init, gru) in enumerate(zip(self.init_state, self.gru, strict=True)):
                h0 = torch.tanh(init(context)).unsqueeze(0)
                x, _ = gru(torch.cat([x, a], dim=-1) if every and i else x, h0)
                states.append(torch.cat([x, a], dim=-1) if every else x)  # what the heads read
        n, h = x.shape[0], x.shape[1]
        img = self.image_head(states[0].reshape(n * h, -1))
        img = img.view(n, h, *img.shape[1:])  # (N, H, 4, 3, P, P)
        spd = self.speed_head(states[min(1, len(states) - 1)])  # (N, H, 4)
        return WorldPrediction(
            image=NIG.from_raw(img, dim=2),
            speed=NIG.from_raw(spd.unsqueeze(-1), dim=2),
            collision=F.softplus(self.collision_head(states[-1])),
        )

    def uncertainties(
        self, pred: WorldPrediction, clip: float | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """(u_image, u_speed, u_collision), each (N, H); u_image averages over the pixels.
        `clip` caps the regression uncertainties, which explode as α → 1."""
        u_image = nig_uncertainty(pred.image)
        u_speed = nig_uncertainty(pred.speed)
        if clip is not None:
            u_image, u_speed = u_image.clamp(max=clip), u_speed.clamp(max=clip)
        return (
            u_image.flatten(2).mean(-1),
            u_speed.squeeze(-1),
            dirichlet_uncertainty(pred.collision),
        )

    def imagine(
        self,
        image: Tensor,
        speed: Tensor,
        actions: Tensor,
        uncertainty_clip: float,
        prior_correction: bool = True,
    ) -> dict[str, Tensor]:
        """What this world model expects an action sequence to do, as refinement scores it:
        (N·K, H) speed in m/s, p(collision) and the three uncertainties, each capped at
        `uncertainty_clip` (u explodes as α → 1; the cap is per pixel before the mean, so one
        exploding pixel cannot dominate). Gradients flow to `actions` (DreamerV3: the world
        model owns imagination; refinement and the counterfactual check only call it).

        `prior_correction` (our safeguard; False is the paper's form): the collision class is
        weighted w = n_safe/n_collision (23-65 in the study) in training, which multiplies the
        head's odds by about w, so its raw p̂ averages ~0.4 per step where ~0.04 collide.
        The objective adds p̂ to metres per second as an expected cost, so an inflated p̂ gives
        the collision term ~10× its weight and its noise. p / (p + w·(1 − p)) divides w back
        out of the odds (the standard correction for a class-weighted classifier)."""
        pred = self(image, speed, actions)
        clip = float(uncertainty_clip)
        u_image, u_speed, u_coll = self.uncertainties(pred, clip=clip)
        p_collision = dirichlet_probability(pred.collision)[..., 1]
        if prior_correction:
            weight = self.collision_class_weight
            p_collision = p_collision / (p_collision + weight * (1.0 - p_collision))
        return {
            "speed": self.denormalise_speed(pred.speed.gamma[..., 0]),
            "p_collision": p_collision,
            "u_image": u_image.clamp(max=clip),
            "u_speed": u_speed.clamp(max=clip),
            "u_collision": u_coll.clamp(max=clip),
        }

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """A checkpoint saved before `collision_class_weight` existed loads with weight 1 (no
        correction): the weight it was trained with was not recorded. Weights of the other
        `world_action_inputs` form are refused in one line naming the form they need."""
        if "collision_class_weight" not in state_dict:
            state_dict = {**state_dict, "collision_class_weight": torch.ones(1)}
        head = state_dict.get("collision_head.0.weight")
        if head is not None and head.shape != self.collision_head[0].weight.shape:
            form = "first" if head.shape[1] == self.profile.gru_hidden else "all"
            raise UserError(
                f"world model weights of world_action_inputs={form}, this model is "
                f"{self.action_inputs}: --set world_action_inputs={form}"
            )
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    def freeze(self) -> None:
        """For refinement: eval() (BatchNorm statistics frozen), no parameter gradients, and
        train() becomes a no-op, so a later policy.train()-style call cannot unfreeze BatchNorm;
        gradients still flow through to the actions."""
        self.eval()
        self.requires_grad_(False)
        self._frozen = True

    def unfreeze(self) -> None:
        self._frozen = False
        self.requires_grad_(True)
        self.train()

    def train(self, mode: bool = True) -> WorldModel:
        return super().train(mode and not getattr(self, "_frozen", False))


def count_parameters(module: nn.Module, names: Sequence[str] | None = None) -> int:
    """Trainable-or-not parameter count (of the named children only, if given)."""
    mods = [module] if names is None else [getattr(module, n) for n in names]
    return sum(p.numel() for m in mods for p in m.parameters())
