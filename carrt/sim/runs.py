"""Simulated runs on disk, and the paper's simulation table over them (`carrt report`).

A run's trajectory (time, position, speed, progress, collisions, laps, resets) is saved next
to its episodes as `sim-runs/<name>.npz` with its metrics and a top-down plot, so the paper's
table can be rebuilt later from any set of runs, like the real-car table from episodes.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from carrt.sim import metrics
from carrt.sim.track import build_track


def save_run(
    out_dir: Path, track: Any, recorder: metrics.TrajectoryRecorder, result: Any, label: str
) -> Path:
    """Write <out>/sim-runs/<stamp>-<label>.{npz,json,png}; return the npz path."""
    runs = Path(out_dir) / "sim-runs"
    runs.mkdir(parents=True, exist_ok=True)
    stem = runs / f"{time.strftime('%Y%m%d-%H%M%S')}-{label}"
    n = 0
    while stem.with_suffix(".npz").exists():
        n += 1
        stem = runs / f"{time.strftime('%Y%m%d-%H%M%S')}-{label}-{n}"
    arrays = recorder.arrays()
    np.savez(stem.with_suffix(".npz"), layout=track.name, track_seed=track.seed, **arrays)
    stem.with_suffix(".json").write_text(json.dumps(asdict(result), indent=2) + "\n")
    metrics.plot_trajectory(
        track, arrays["x"], arrays["y"], arrays["collision"], stem.with_suffix(".png"),
        title=f"{label}: completion {result.completion_ratio:.0%}", speeds=arrays["speed"],
    )  # fmt: skip
    return stem.with_suffix(".npz")


def load_metrics(path: Path) -> tuple[str, Any]:
    with np.load(path) as data:
        track = build_track(str(data["layout"]), int(data["track_seed"]))
        recorder = metrics.TrajectoryRecorder(
            **{name: list(data[name]) for name in metrics.TrajectoryRecorder.__dataclass_fields__}
        )
    return path.stem, recorder.metrics(track.length)


def render_sim_table(rows: list[tuple[str, Any]]) -> str:
    """The paper's simulation table, plus its real-car columns for auto-reset runs and the
    racing numbers (laps per minute of driving, progress per metre driven)."""
    lines = [
        f"{'run':<34} {'avg m/s':>7} {'top m/s':>7} {'completion':>10} {'prog/m':>6} "
        f"{'best lap s':>10} {'laps/min':>8} {'laps':>4} {'collisions':>10} {'5 laps s':>8}",
    ]
    for name, m in rows:
        best = f"{m.best_lap:.2f}" if m.best_lap is not None else "-"
        five = f"{m.time_for_laps:.1f}" if m.time_for_laps is not None else "-"
        lines.append(
            f"{name[:34]:<34} {m.average_speed:7.2f} {m.top_speed:7.2f} "
            f"{m.completion_ratio:10.1%} {m.progress_per_metre:6.2f} {best:>10} "
            f"{m.laps_per_min:8.2f} {m.laps:4d} {m.collisions:10d} {five:>8}"
        )
    return "\n".join(lines)
