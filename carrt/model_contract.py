"""What an ONNX policy must look like for carrt to drive with it.

export/ writes models to this contract and carrt checks it at load time, before the car can be
armed: a model with the wrong inputs, the wrong horizon or no metadata is refused with one
line that says what is wrong, instead of producing nonsense commands at the first tick.

Graph:
  inputs   image  uint8   [N, 96, 96, 3]  raw RGB, exactly as recorded (normalisation inside)
           speed  float32 [N, 1]          metres per second
  outputs  mu     float32 [N, H, 2]       mean (steering, throttle) for the next H steps
           sigma  float32 [N, H, 2]       standard deviation, > 0
Metadata (ONNX metadata_props, all strings): the keys in REQUIRED_KEYS.
"""

from __future__ import annotations

from collections.abc import Mapping

SCHEMA = "carrt.policy/1"

INPUT_IMAGE = "image"
INPUT_SPEED = "speed"
OUTPUT_MU = "mu"
OUTPUT_SIGMA = "sigma"

IMAGE_SHAPE = (96, 96, 3)
ACTION_NAMES = ("steering", "throttle")
ACTION_LOW = (-1.0, 0.0)
ACTION_HIGH = (1.0, 1.0)

REQUIRED_KEYS = {
    "carrt.schema": "contract version, must be " + SCHEMA,
    "carrt.horizon": "H, the number of future steps in mu and sigma",
    "carrt.control_period_s": "seconds between steps (0.1 at 10 Hz)",
    "carrt.image_shape": "H,W,C of the image input: 96,96,3",
    "carrt.action_names": "steering,throttle",
    "carrt.action_low": "lower bound per action, comma separated",
    "carrt.action_high": "upper bound per action, comma separated",
    "carrt.speed_units": "m/s",
    "carrt.training_data_digest": "sha256 over the episodes the policy was trained on",
    "carrt.iteration": "DIRL iteration that produced it (0 = imitation only)",
    "carrt.code_version": "carrt version that exported it",
}


class ContractError(ValueError):
    """The model does not meet the contract; the message names what is wrong."""


def _floats(text: str, key: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError as exc:
        raise ContractError(f"metadata {key}={text!r} is not a list of numbers") from exc


def validate_metadata(meta: Mapping[str, str], control_period_s: float | None = None) -> int:
    """Check the metadata; return the horizon H. Raises ContractError."""
    missing = [k for k in REQUIRED_KEYS if k not in meta]
    if missing:
        raise ContractError(
            "metadata missing " + ", ".join(missing) + " (was it exported with `python -m export`?)"
        )
    if meta["carrt.schema"] != SCHEMA:
        raise ContractError(
            f"metadata carrt.schema is {meta['carrt.schema']!r}, expected {SCHEMA!r}"
        )
    try:
        horizon = int(meta["carrt.horizon"])
    except ValueError as exc:
        raise ContractError(
            f"metadata carrt.horizon={meta['carrt.horizon']!r} is not an integer"
        ) from exc
    if not 1 <= horizon <= 100:
        raise ContractError(f"metadata carrt.horizon={horizon} is outside 1..100")
    period = _floats(meta["carrt.control_period_s"], "carrt.control_period_s")[0]
    if control_period_s is not None and abs(period - control_period_s) > 1e-6:
        raise ContractError(
            f"model was trained at a {period} s control period, "
            f"but the car runs at {control_period_s} s"
        )
    shape = tuple(int(x) for x in _floats(meta["carrt.image_shape"], "carrt.image_shape"))
    if shape != IMAGE_SHAPE:
        raise ContractError(f"metadata carrt.image_shape={shape}, expected {IMAGE_SHAPE}")
    if tuple(meta["carrt.action_names"].split(",")) != ACTION_NAMES:
        raise ContractError(
            f"metadata carrt.action_names={meta['carrt.action_names']!r}, "
            "expected steering,throttle"
        )
    low = _floats(meta["carrt.action_low"], "carrt.action_low")
    high = _floats(meta["carrt.action_high"], "carrt.action_high")
    if len(low) != 2 or len(high) != 2 or any(lo >= hi for lo, hi in zip(low, high, strict=True)):
        raise ContractError(f"metadata action bounds {low}..{high} are not two valid ranges")
    if meta["carrt.speed_units"] != "m/s":
        raise ContractError(
            f"metadata carrt.speed_units={meta['carrt.speed_units']!r}, expected m/s"
        )
    return horizon


def action_bounds(meta: Mapping[str, str]) -> tuple[tuple[float, ...], tuple[float, ...]]:
    return _floats(meta["carrt.action_low"], "carrt.action_low"), _floats(
        meta["carrt.action_high"], "carrt.action_high"
    )
