"""The recorded runs of research/plan_distil.py's `record` step (one .npz per run: frames,
recorded commands, the teacher's scores), read back as one set. Its own module because both
the distillation (plan_distil.py) and the ground model's training (ground_v2.py) read them, and
neither may import the other (tests/test_import_graph.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from carrt.errors import UserError


def load_recorded(folder: Path) -> dict[str, np.ndarray]:
    """One recorded set, or several joined with commas (their segments kept apart)."""
    if "," in str(folder):
        files = [f for part in str(folder).split(",") for f in sorted(Path(part).glob("*-s*.npz"))]
    else:
        files = sorted(folder.glob("*-s*.npz"))
    files = [f for f in files if ".part" not in f.name]
    if not files:
        raise UserError(f"{folder}: no recorded runs")
    parts = [dict(np.load(f)) for f in files]
    out = {}
    for k in parts[0]:
        out[k] = np.concatenate([p[k] for p in parts])
    # segments unique across runs
    offset, segs = 0, []
    for p in parts:
        segs.append(p["segment"] + offset)
        offset += int(p["segment"].max()) + 1
    out["segment"] = np.concatenate(segs)
    return out
