"""Model sizes by name, so a run, its checkpoint and its export agree on one architecture.

`paper` is the paper's network (ResNet18, GRU 512, full-resolution image prediction) for a GPU;
`cpu` trains ~1000 imitation samples/s on two laptop cores; `tiny` exists for tests, where a
forward and backward pass must take milliseconds. A checkpoint stores only the profile's name,
so changing a profile's numbers makes old checkpoints unloadable: add a profile instead.
"""

from __future__ import annotations

from dataclasses import dataclass

from carrt.model_contract import HORIZON

# Where the world model's actions enter (WorldModel): "first", the paper's Reveries-net (the
# first GRU layer only); "all", every GRU layer and every head, so a head can read the action
# directly instead of through states the image set.
WORLD_ACTION_INPUTS = ("first", "all")


@dataclass(frozen=True)
class Profile:
    name: str
    width: int  # backbone base channels: 64 is exactly torchvision's resnet18
    speed_features: int  # dense speed features f_s
    action_features: int  # per-step action features fed to the GRU
    gru_hidden: int
    gru_layers: int = 3  # layer 1 → images, layer 2 → speed, last → collision
    predict_size: int = 96  # side of the predicted future images (pixels)
    policy_hidden: int = 256
    horizon: int = HORIZON  # H, the paper's 1 s at 10 Hz
    min_sigma: float = 0.05  # floor on the policy's σ (evidential σ must not collapse)
    input_size: int = 96  # side the 96×96 frame is resized to inside the model (backbone input)
    # WORLD_ACTION_INPUTS; set per run (TrainingConfig.world_action_inputs), saved in the
    # checkpoint's profile_fields; a checkpoint from before the field loads as "first"
    world_action_inputs: str = "first"

    def __post_init__(self) -> None:
        sizes = ("width", "speed_features", "action_features", "gru_hidden", "gru_layers")
        sizes += ("predict_size", "policy_hidden", "horizon", "input_size")
        bad = [f"{k}={getattr(self, k)}" for k in sizes if int(getattr(self, k)) < 1]
        if not self.min_sigma > 0:
            bad.append(f"min_sigma={self.min_sigma}")
        if self.world_action_inputs not in WORLD_ACTION_INPUTS:
            bad.append(f"world_action_inputs={self.world_action_inputs!r} (one of first, all)")
        if bad:
            raise ValueError(f"profile {self.name!r}: out of range: {', '.join(bad)}")

    @property
    def image_features(self) -> int:
        """f_i: the backbone's pooled output (512 for the paper)."""
        return 8 * self.width


_PROFILES = (
    Profile("tiny", 8, speed_features=16, action_features=8, gru_hidden=32,
            predict_size=16, policy_hidden=32),
    # cpu: width 16 and a 64×64 backbone input (resized inside the graph; the ONNX input stays
    # the contract's 96×96) cost 1/4.4 of width 24 at 96×96 per backbone pass on 2 cores;
    # predicting 16×16 futures instead of 32×32 cuts the world model's step (decoder + pixel
    # NLL, most of it) by ~40 % (measured 221 → 354 samples/s at batch 32).
    Profile("cpu", 16, speed_features=64, action_features=32, gru_hidden=128,
            predict_size=16, policy_hidden=128, input_size=64),
    Profile("paper", 64, speed_features=128, action_features=64, gru_hidden=512,
            predict_size=96, policy_hidden=256),
)  # fmt: skip
PROFILES: dict[str, Profile] = {p.name: p for p in _PROFILES}


def get_profile(name: str | Profile) -> Profile:
    """The profile called `name` (a Profile is passed through)."""
    if isinstance(name, Profile):
        return name
    try:
        return PROFILES[name]
    except KeyError:
        raise ValueError(f"unknown profile {name!r}; choose one of {', '.join(PROFILES)}") from None
