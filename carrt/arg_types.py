"""argparse value types shared by carrt's commands and training's scripts.

Its own module so that a script needing one (training/sim_data.py) does not import the car
session stack (carrt.session pulls in the rig, the link and the config: ~150 modules) for it.
"""

from __future__ import annotations

import argparse
import math


def finite_non_negative(text: str) -> float:
    """An argparse type for a σ or a duration: NaN and infinities are bad input, like negatives
    (argparse then ends with the option's name and exit 2)."""
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {text!r}")
    return value
