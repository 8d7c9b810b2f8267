"""An iteration's export: `python -m export` (carrt-export) on its policy.pt, in its own process.

The export runs exactly as a person would run it: the arrows run firmware_bridge <- carrt <-
training <- export, so training/ never imports export/, and the end of a run calls it as a
command once policy.pt is saved. A refused or failed export leaves policy.pt intact and makes
the run's exit status 1; a missing export/ (or onnx) is not an error.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path


@dataclass
class Exported:
    """What the export said (report.md's Export section), its ExportReport as a dict (None when
    skipped or failed) and the run's exit status because of it."""

    lines: list[str]
    info: dict | None = None
    exit_code: int = 0


def export_policy(cfg, out: Path) -> Exported:
    """out/policy.pt to out/policy.onnx, checked on the run's episodes (`export` off: skipped)."""
    if not cfg.export:
        return Exported(["export skipped (export=false)"])
    for module in ("export", "onnx"):
        if importlib.util.find_spec(module) is None:
            return Exported([f"export skipped: {module} is not available"])
    # the child finds export/ where this process does (a checkout run as a script, too)
    root = str(Path(importlib.util.find_spec("export").origin).parents[1])
    paths = [root, *filter(None, [os.environ.get("PYTHONPATH")])]
    with tempfile.TemporaryDirectory() as tmp:
        info = Path(tmp) / "export.json"
        argv = [sys.executable, "-m", "export", str(out / "policy.pt"), "-o",
                str(out / "policy.onnx"), "--episodes", *cfg.episodes,
                "--json-out", str(info)]  # fmt: skip
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}
        env |= {"OMP_NUM_THREADS": str(cfg.threads)} if cfg.threads else {}
        done = subprocess.run(argv, capture_output=True, text=True, env=env)
        if done.returncode != 0 or not info.is_file():  # refused or failed: policy.pt is intact
            why = (done.stderr.strip().splitlines() or [f"exit {done.returncode}"])[-1]
            return Exported([f"export FAILED: {' '.join(why.split())}"], None, 1)
        return Exported(done.stdout.rstrip("\n").splitlines(), json.loads(info.read_text()))
