"""Give an exported policy a throttle ceiling.

    carrt-throttle-ceiling IN.onnx -o OUT.onnx --max-throttle 0.8

Why a ceiling belongs to the policy file: a policy that imitates from one frame enters a tight bend
faster than its demonstrator when the obstacle behind the bend is not yet in view, and a slightly
slower car sees it in time (research/results/demo_policy_validation.json: the shipped network's
collisions on validation placements fell from 0.70 to 0.30 per minute at a ceiling of 0.8, at the
expert's own pace). DonkeyCar users tune the same thing with a throttle multiplier in their config;
carrt keeps it in the model, so whoever drives the file (`carrt drive`, `carrt eval`, `make demo`)
drives what was measured. The ceiling is the contract's `carrt.action_high`, narrowed: carrt already
clips every plan to its model's own bounds, so nothing new runs on the car. The board's
`pwm.max_forward` still clamps whatever arrives.

The network and every other metadata key are copied unchanged; the file is written under a
temporary name and renamed into place only after carrt's own loader has accepted it.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import onnx

from carrt import model_contract as mc
from carrt.errors import UserError
from export.graph import carrt_accepts, get_metadata, set_metadata, write_checked
from firmware_bridge.timing import CONTROL_PERIOD_S

THROTTLE = mc.ACTION_NAMES.index("throttle")


def apply_throttle_ceiling(src: str | Path, dst: str | Path, ceiling: float) -> dict[str, str]:
    """Copy the policy at `src` to `dst` with its throttle bound lowered to `ceiling`.

    Returns the new metadata. Raises UserError for a ceiling outside (0, 1] (NaN included), a
    file that is not a carrt policy, or a ceiling at or below the model's own lower bound.
    """
    if not (math.isfinite(ceiling) and 0.0 < ceiling <= 1.0):
        raise UserError(f"--max-throttle must be a number in (0, 1], got {ceiling}")
    src, dst = Path(src), Path(dst)
    if not src.is_file():
        raise UserError(f"model {src}: no such file")
    try:
        model = onnx.load(str(src))
    except Exception as exc:  # onnx raises several kinds for a bad file
        raise UserError(f"model {src}: not an ONNX file ({type(exc).__name__})") from None
    meta = get_metadata(model)
    try:
        mc.validate_metadata(meta, CONTROL_PERIOD_S)
    except mc.ContractError as exc:
        raise UserError(f"model {src}: {exc}") from None
    low, high = mc.action_bounds(meta)
    if ceiling <= low[THROTTLE]:
        raise UserError(
            f"--max-throttle {ceiling} is not above the model's lowest throttle {low[THROTTLE]}"
        )
    new_high = list(high)
    new_high[THROTTLE] = min(high[THROTTLE], ceiling)
    meta["carrt.action_high"] = ",".join(str(x) for x in new_high)
    meta["carrt.throttle_ceiling"] = str(new_high[THROTTLE])
    mc.validate_metadata(meta, CONTROL_PERIOD_S)
    set_metadata(model, meta)
    write_checked(model, dst, carrt_accepts)
    return meta


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="carrt-throttle-ceiling",
        description="Copy an exported policy with a lower throttle bound (carrt.action_high).",
        epilog="example: carrt-throttle-ceiling run/policy.onnx -o policy.onnx --max-throttle 0.8",
    )
    p.add_argument("model", help="policy .onnx written by export/ or training/iterate.py")
    p.add_argument("-o", "--out", required=True, help="where to write the copy")
    p.add_argument("--max-throttle", type=float, required=True, help="new ceiling, in (0, 1]")
    args = p.parse_args(argv)
    try:
        meta = apply_throttle_ceiling(args.model, args.out, args.max_throttle)
    except UserError as exc:
        print(f"export.throttle_ceiling: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    low, high = meta["carrt.action_low"], meta["carrt.action_high"]
    print(f"wrote {args.out}: action range {low} .. {high}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
