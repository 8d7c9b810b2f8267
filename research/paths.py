"""Where the study's relative paths point: the repository, whatever the current directory.

Why: a study's steps run their commands with the repository as the working directory while the
runner checks their markers itself, so a relative OUT must name the same folder for both, and
the same folder whether `python -m research.x` runs at the root or `python /path/research/x.py`
runs anywhere else. Files a user names on a command line (results to compare) stay relative to
where the user is; the folders a study writes (OUT and the runs it reads back) are the repo's.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def at_root(path: str) -> str:
    """`path` inside the repository when relative; an absolute one (or "") unchanged."""
    return str(ROOT / path) if path else path


def outs_at_root(cfg):
    """The config dataclass `cfg` with each folder it writes or reads runs from (`out`, any
    `*_out`) at the repository, and the same for the study config it carries (`study`)."""
    changes = {
        f.name: at_root(getattr(cfg, f.name))
        for f in dataclasses.fields(cfg)
        if (f.name == "out" or f.name.endswith("_out")) and isinstance(getattr(cfg, f.name), str)
    }
    if dataclasses.is_dataclass(getattr(cfg, "study", None)):
        changes["study"] = outs_at_root(cfg.study)
    return dataclasses.replace(cfg, **changes)
