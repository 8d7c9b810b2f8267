"""The one code version string that checkpoints, exported models and reports carry.

carrt's version, plus `git describe --always --dirty` of the source tree when the code runs
from a checkout: the commit tells two runs of the same release apart, and "-dirty" says the
tree had uncommitted changes. Outside a checkout (an installed wheel) the version alone.
Training and export used to compute this twice, differently, so a checkpoint and the ONNX file
made from it disagreed; both call this now.
"""

from __future__ import annotations

import functools
import subprocess
from pathlib import Path

import carrt


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    version = carrt.__version__
    root = Path(carrt.__file__).resolve().parent.parent
    try:
        described = subprocess.run(
            ["git", "-C", str(root), "describe", "--always", "--dirty", "--tags"],
            capture_output=True, text=True, timeout=5, check=True,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return version
    return f"{version}+g{described}" if described else version
