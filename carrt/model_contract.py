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

import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from carrt.errors import UserError

SCHEMA = "carrt.policy/1"

INPUT_IMAGE = "image"
INPUT_SPEED = "speed"
OUTPUT_MU = "mu"
OUTPUT_SIGMA = "sigma"

IMAGE_SHAPE = (96, 96, 3)
# H, the plan's steps when nothing else says: the paper's 1 s at 10 Hz. A model states its own
# (carrt.horizon) and an episode records the one it was driven with; this is the default of both.
HORIZON = 10
ACTION_NAMES = ("steering", "throttle")
# Throttle < 0 brakes (and, held at rest, reverses): the demonstrator brakes, so the policy's
# range must include it. Models exported when the contract had throttle ≥ 0 (action_low
# "-1.0,0.0") still load: carrt clips to each model's own bounds, so they simply never brake.
ACTION_LOW = (-1.0, -1.0)
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


class ContractError(UserError, ValueError):
    """The model does not meet the contract; the message names what is wrong (a UserError:
    one line, exit 2)."""


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
            "metadata missing " + ", ".join(missing) + " (was it exported with `carrt-export`?)"
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
    # Narrower than the contract is fine (an old model without braking has throttle ≥ 0);
    # wider is not: the car has no command beyond full lock and full throttle.
    for name, lo, hi, c_lo, c_hi in zip(
        ACTION_NAMES, low, high, ACTION_LOW, ACTION_HIGH, strict=True
    ):
        if lo < c_lo or hi > c_hi:
            raise ContractError(
                f"metadata {name} bounds {lo}..{hi} exceed the contract's {c_lo}..{c_hi}"
            )
    if meta["carrt.speed_units"] != "m/s":
        raise ContractError(
            f"metadata carrt.speed_units={meta['carrt.speed_units']!r}, expected m/s"
        )
    return horizon


def action_bounds(meta: Mapping[str, str]) -> tuple[tuple[float, ...], tuple[float, ...]]:
    return _floats(meta["carrt.action_low"], "carrt.action_low"), _floats(
        meta["carrt.action_high"], "carrt.action_high"
    )


# ----------------------------------------------------------------------------- graph inputs/outputs
@dataclass(frozen=True)
class TensorSpec:
    """One graph input or output as a runtime reports it, independent of onnx/onnxruntime.

    dtype is a numpy name ("uint8", "float32"); each dim is an int, or a str/None when the
    graph leaves it dynamic. export/ and carrt both check graphs through validate_io, so a
    model the exporter accepts is one the car accepts.
    """

    name: str
    dtype: str
    shape: tuple[int | str | None, ...]

    def render(self) -> str:
        return f"{self.name} {self.dtype} {format_shape(self.shape)}"


def format_shape(shape: Sequence[int | str | None]) -> str:
    return "[" + ", ".join("?" if d is None else str(d) for d in shape) + "]"


def expected_io(horizon: int) -> tuple[tuple[TensorSpec, ...], tuple[TensorSpec, ...]]:
    """The contract's inputs and outputs for a horizon H ("N" is the free batch dim)."""
    inputs = (
        TensorSpec(INPUT_IMAGE, "uint8", ("N", *IMAGE_SHAPE)),
        TensorSpec(INPUT_SPEED, "float32", ("N", 1)),
    )
    outputs = (
        TensorSpec(OUTPUT_MU, "float32", ("N", horizon, 2)),
        TensorSpec(OUTPUT_SIGMA, "float32", ("N", horizon, 2)),
    )
    return inputs, outputs


_WHY_DTYPE = {
    INPUT_IMAGE: " (raw RGB as recorded; normalisation belongs inside the graph)",
    INPUT_SPEED: " (m/s)",
}


def _check_tensor(kind: str, actual: TensorSpec, expected: TensorSpec, horizon: int) -> None:
    if actual.dtype != expected.dtype:
        raise ContractError(
            f"{kind} {actual.name} is {actual.dtype}, expected {expected.dtype}"
            + _WHY_DTYPE.get(actual.name, "")
        )
    wanted = format_shape(expected.shape)
    if len(actual.shape) != len(expected.shape):
        raise ContractError(
            f"{kind} {actual.name} has shape {format_shape(actual.shape)}, expected {wanted}"
        )
    batch, *rest = actual.shape
    # carrt runs one frame at a time: the batch dim may be dynamic or 1, nothing else.
    if isinstance(batch, int) and batch != 1:
        raise ContractError(
            f"{kind} {actual.name} has a fixed batch of {batch} in {format_shape(actual.shape)}, "
            f"expected a dynamic batch: {wanted}"
        )
    for axis, (dim, want) in enumerate(zip(rest, expected.shape[1:], strict=True), start=1):
        # A dynamic dim is accepted here; the run-time output shape is checked at warm-up.
        if isinstance(dim, int) and dim != want:
            extra = ""
            if kind == "output" and axis == 1:
                extra = f" (metadata carrt.horizon is {horizon})"
            raise ContractError(
                f"{kind} {actual.name} has shape {format_shape(actual.shape)}, "
                f"expected {wanted}{extra}"
            )


def validate_io(inputs: Sequence[TensorSpec], outputs: Sequence[TensorSpec], horizon: int) -> None:
    """Check a graph's inputs and outputs against the contract. Raises ContractError.

    Inputs must be exactly image and speed (carrt feeds nothing else); outputs must include
    mu and sigma (further outputs, e.g. diagnostics, are ignored).
    """
    want_in, want_out = expected_io(horizon)
    names = [t.name for t in inputs]
    for spec in want_in:
        if spec.name not in names:
            raise ContractError(
                f"input {spec.name!r} missing (the graph's inputs are {', '.join(names) or 'none'}"
                f"; expected {INPUT_IMAGE}, {INPUT_SPEED})"
            )
    extra = [n for n in names if n not in (INPUT_IMAGE, INPUT_SPEED)]
    if extra:
        raise ContractError(
            f"unexpected input {extra[0]!r} (the contract has only {INPUT_IMAGE}, {INPUT_SPEED})"
        )
    out_names = [t.name for t in outputs]
    for spec in want_out:
        if spec.name not in out_names:
            raise ContractError(
                f"output {spec.name!r} missing (the graph's outputs are "
                f"{', '.join(out_names) or 'none'}; expected {OUTPUT_MU}, {OUTPUT_SIGMA})"
            )
    by_name = {t.name: t for t in [*inputs, *outputs]}
    for spec in want_in:
        _check_tensor("input", by_name[spec.name], spec, horizon)
    for spec in want_out:
        _check_tensor("output", by_name[spec.name], spec, horizon)


# ----------------------------------------------------------------------------- provenance
# Which simulator placements the policy's training episodes came from, as JSON
# {"layout": [track seeds]}: `carrt eval` on one of them measures recall, not driving, and says
# so. Optional (a real car's episodes have none; older models lack the key).
SIM_PLACEMENTS = "carrt.sim_placements"


def sim_placements(metas: Iterable[Mapping[str, Any]]) -> dict[str, list[int]]:
    """{layout: sorted track seeds} of the episodes' `sim` blocks (episode meta.json)."""
    seen: dict[str, set[int]] = {}
    for meta in metas:
        sim = meta.get("sim") or {}
        if "layout" in sim and "track_seed" in sim:
            seen.setdefault(str(sim["layout"]), set()).add(int(sim["track_seed"]))
    return {layout: sorted(seeds) for layout, seeds in sorted(seen.items())}


def trained_on(metadata: Mapping[str, str], layout: str, tracks: Iterable[int]) -> list[int]:
    """The given placements of `layout` that the model's training data came from."""
    try:
        placed = json.loads(metadata.get(SIM_PLACEMENTS) or "{}")
    except json.JSONDecodeError:
        return []
    seen = set(placed.get(layout, [])) if isinstance(placed, dict) else set()
    return sorted(t for t in tracks if t in seen)
