"""Value types and parsers of what the user typed, shared by carrt's commands, the simulator's
tools and training's scripts.

Its own module so that a script needing one (training/sim_data.py, carrt/sim/counterfactual.py)
imports neither the car session stack (carrt.session pulls in the rig, the link and the config:
~150 modules) nor a command-line module (the CLI sits on top; nothing below imports it).
"""

from __future__ import annotations

import argparse
import math

from carrt.errors import UserError


def _finite_at_least(text: str, low: float, inclusive: bool) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and (value >= low if inclusive else value > low)):
        bound = f"{'>=' if inclusive else '>'} {low:g}"
        raise argparse.ArgumentTypeError(f"expected a finite number {bound}, got {text!r}")
    return value


def finite_non_negative(text: str) -> float:
    """An argparse type for a σ: NaN and infinities are bad input, like negatives (argparse then
    ends with the option's name and exit 2)."""
    return _finite_at_least(text, 0.0, inclusive=True)


def finite_positive(text: str) -> float:
    """An argparse type for a duration: NaN, infinities, 0 and negatives are bad input (a NaN
    duration would reach every placement's drive, an infinite one would never end)."""
    return _finite_at_least(text, 0.0, inclusive=False)


def parse_int_list(text: str, what: str) -> list[int]:
    """'100-104,120' → [100, 101, 102, 103, 104, 120]; anything else is a UserError."""
    out: list[int] = []
    for part in str(text).split(","):
        part = part.strip()
        try:
            if "-" in part[1:]:
                lo, hi = (int(p) for p in part.split("-", 1))
                if hi < lo:
                    raise ValueError
                out.extend(range(lo, hi + 1))
            else:
                out.append(int(part))
        except ValueError:
            raise UserError(
                f"--{what}: {text!r} is not a list of numbers and ranges like 100-104,120"
            ) from None
    if any(v < 0 for v in out):
        raise UserError(f"--{what}: seeds are >= 0, got {text!r}")
    return out


def format_int_list(values: list[int]) -> str:
    """[100, 101, 102, 120] → '100-102,120': parse_int_list's form, for messages."""
    parts: list[str] = []
    for v in sorted(set(values)):
        if parts and "-" not in parts[-1][1:] and int(parts[-1]) == v - 1:
            parts[-1] = f"{v - 1}-{v}"
        elif parts and "-" in parts[-1][1:] and int(parts[-1].split("-")[1]) == v - 1:
            parts[-1] = f"{parts[-1].split('-')[0]}-{v}"
        else:
            parts.append(str(v))
    return ",".join(parts)
