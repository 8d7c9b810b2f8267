"""The loop's settings (`carrt-train --iterations`): a documented dataclass, its flags and its file.

The loop's flags say who drives each policy and where it is compared; they are not an
iteration's settings (no run reads them), so they live here rather than in TrainingConfig, and
carrt-train makes them into flags as training/config.py's settings are made into --set: each
flag's help, type, default and allowed values are its field's declaration (training/setting.py).
A loop writes them into OUT/training_loop.json, so its folder says how it was driven; running the
same command again (resuming) rewrites that file with the flags it is given, as before.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from training.compare import DriveSpec
from training.config import UsageError
from training.setting import kind, problems, setting

FILE = "training_loop.json"  # in the loop's OUT: the flags it ran with
METAVARS = {"iterations": "N", "drive_tracks": "SEEDS", "drive_layouts": "LIST",
            "drive_seconds": "S", "compare_tracks": "SEEDS", "compare_seconds": "S",
            "compare_seeds": "LIST"}  # fmt: skip


@dataclass
class TrainingLoopConfig:
    """The paper's Algorithm 1 as carrt-train runs it: imitation into OUT/iter_0, then
    `iterations` take-over rounds, each policy driven (by the car or the simulator) and, in the
    simulator, compared with the one before it on validation placements."""

    GROUPS: ClassVar[tuple[tuple[str, str], ...]] = (
        ("The loop's flags (--iterations: Algorithm 1; without it, one iteration)", "iterations"),
    )

    iterations: int | None = setting(
        None, "imitation into OUT/iter_0, then N take-over rounds (the policy drives and records "
        "while the person takes over; it imitates again) into OUT/iter_1..N", lo=1,
    )  # fmt: skip
    drive: str = setting(
        "car", "who drives each policy: car (the loop stops and says how) or sim (the "
        "simulator, in worker processes)", choices=("car", "sim"),
    )  # fmt: skip
    drive_tracks: str = setting("1000-1009", "sim: training placements to drive")
    drive_layouts: str = setting("hard", "sim: layouts, taken in turn")
    drive_seconds: float = setting(60.0, "sim: simulated s per placement", above=0)
    compare_tracks: str = setting(
        DriveSpec.tracks, "sim: validation placements (200-259, hard) each iteration's policy is "
        "driven on against the one before it",
    )  # fmt: skip
    compare_seconds: float = setting(
        DriveSpec.seconds, "sim: simulated s per validation run", above=0
    )
    compare_seeds: str = setting(DriveSpec.seeds, "sim: run seeds of each validation placement")
    jobs: int = setting(DriveSpec.jobs, "sim: drives at once", lo=1)


def flag(name: str) -> str:
    """A setting's command-line flag: drive_tracks → --drive-tracks."""
    return "--" + name.replace("_", "-")


def add_loop_args(group: argparse._ArgumentGroup) -> None:
    """The loop's flags, one per field of TrainingLoopConfig, its doc the help."""
    types = {"int": int, "float": float, "str": str}
    for spec in dataclasses.fields(TrainingLoopConfig):
        default = "" if spec.default is None else " (default: %(default)s)"
        group.add_argument(
            flag(spec.name), type=types[kind(spec).split(" ")[0]], default=spec.default,
            choices=spec.metadata["choices"], metavar=METAVARS.get(spec.name),
            help=spec.metadata["doc"].replace("%", "%%") + default,
        )  # fmt: skip


def loop_config(a: argparse.Namespace) -> TrainingLoopConfig:
    """The loop's settings of parsed flags, each checked against its declaration (one line
    naming the flag)."""
    names = [spec.name for spec in dataclasses.fields(TrainingLoopConfig)]
    cfg = TrainingLoopConfig(**{name: getattr(a, name) for name in names})
    found = problems(cfg)
    if found:
        name, _, rest = found[0].partition(" ")
        raise UsageError(f"{flag(name)} {rest}")
    return cfg


def save(cfg: TrainingLoopConfig, out: str | Path) -> Path:
    """OUT/training_loop.json: the loop's settings, beside its iterations."""
    path = Path(out) / FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(dataclasses.asdict(cfg), indent=2) + "\n")
    return path
