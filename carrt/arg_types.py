"""argparse value types shared by carrt's commands and training's scripts.

Its own module so that a script needing one (training/sim_data.py) does not import the car
session stack (carrt.session pulls in the rig, the link and the config: ~150 modules) for it.
"""

from __future__ import annotations

import argparse
import math


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
