"""Policies shipped inside the carrt package, by name: `carrt drive --model demo`.

Why names: an installed package's files live under a site-packages path nobody wants to type,
and the README's commands should work the same from any directory. Kept free of onnxruntime so
the CLI can resolve a name without loading it.
"""

from __future__ import annotations

import os
from pathlib import Path

from carrt.errors import UserError

SHIPPED_MODELS = {"demo": Path(__file__).resolve().parent / "assets" / "demo_policy.onnx"}


def resolve_model(text: str | os.PathLike[str]) -> Path:
    """A model path, or the name of a policy shipped with carrt (`--model demo`), as a Path.

    A file of that name in the current directory wins over the shipped one, so a name never
    hides a user's own file. The shipped file would otherwise only be reachable through its
    site-packages path."""
    path = Path(text)
    if not path.exists() and str(text) in SHIPPED_MODELS:
        return SHIPPED_MODELS[str(text)]
    if path.is_dir():
        raise UserError(f"model {path}: is a directory, expected an .onnx file")
    if not path.is_file():
        names = ", ".join(SHIPPED_MODELS)
        raise UserError(f"model {path}: no such file (shipped models by name: {names})")
    return path
