"""Judge a policy by driving it: the paper's table over placements and seeds (`carrt eval`).

Each run is exactly `carrt drive --sim --autopilot` (or `carrt teleop --sim --expert auto` for
the scripted expert's baseline) on the simulated clock: the same loop, arbitration, C firmware
core, camera and auto-reset after every collision, only faster than real time. Nothing here
steps the simulator itself, so what is measured is what the car's software does.

Numbers per run, then mean ± std over every (placement, seed) run:
  completion ratio   share of a lap driven from the start before the first collision (≤ 1)
  collisions / min   collisions per minute of the run's simulated time (resets included, as a
                     person watching a clock would count them)
  average speed      m/s over driving time (standing crashed and resetting excluded)
  laps               laps completed; metres skipped by auto-resets are not credited
  laps / min         laps per minute of driving time (standing crashed and resetting
                     excluded, unlike collisions / min): the racing number completion cannot
                     see, as it stops at the first failure and is capped at one lap
  lap time           mean of the clean laps (no collision, take-over or reset inside), s;
                     runs without a clean lap are left out of its mean (`null` in the JSON)
  progress / m       metres gained along the track per metre driven: 1 on the centerline,
                     lower when the car wanders off the line, loops or goes backwards
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from carrt.sim.pool import worker_pool

METRICS = (
    "completion_ratio",
    "collisions_per_min",
    "average_speed",
    "laps",
    "laps_per_min",
    "progress_per_metre",
)
OPTIONAL = ("lap_time_mean", "best_lap")  # None in a run without a clean lap


def evaluate(
    model_path: str | Path | None,
    layout: str = "hard",
    tracks: list[int] | tuple[int, ...] = (100, 101, 102, 103, 104),
    seconds: float = 60.0,
    seeds: list[int] | tuple[int, ...] = (0,),
    jobs: int = 1,
    *,
    intervene: bool = False,
    isolated: bool = False,
) -> dict[str, Any]:
    """Drive `model_path` (None: the scripted expert) on every placement × seed.

    Returns {"config": ..., "runs": [per-run dict], "aggregate": {metric: {"mean", "std"}}}.
    jobs > 1 runs placements in that many 'spawn' processes, one math thread each (pool.py);
    `isolated`: even one job runs in such a process, never in this one (the training loop's
    process holds torch, and the simulator does not run beside it).
    """
    tasks = [
        (None if model_path is None else str(model_path), layout, int(t), float(seconds), int(s),
         bool(intervene))
        for t in tracks
        for s in seeds
    ]  # fmt: skip
    if isolated or (jobs > 1 and len(tasks) > 1):
        with worker_pool(min(jobs, len(tasks)), "spawn") as pool:
            runs = list(pool.map(run_one, *zip(*tasks, strict=True)))
    else:
        runs = [run_one(*task) for task in tasks]
    return {
        "config": {
            "model": None if model_path is None else str(model_path),
            "layout": layout,
            "tracks": [int(t) for t in tracks],
            "seeds": [int(s) for s in seeds],
            "seconds": float(seconds),
            "intervene": bool(intervene),
        },
        "runs": runs,
        "aggregate": aggregate(runs),
    }


def run_one(
    model_path: str | None,
    layout: str,
    track: int,
    seconds: float,
    seed: int,
    intervene: bool = False,
) -> dict[str, Any]:
    """One drive: exactly the `carrt drive --sim --autopilot` (or, with no model, `carrt teleop
    --sim --expert auto`) a user would type, run from its config; nothing said, metrics kept."""
    from carrt.session import DriveConfig, run_session

    drive = DriveConfig(
        model=model_path,
        rig="sim",
        expert=model_path is None,
        autopilot=model_path is not None,
        expert_intervene=model_path is not None and intervene,
        layout=layout,
        track_seed=track,
        duration=seconds,
        seed=seed,
    )
    sim = run_session(drive).rig
    m, recorder = sim.metrics, sim.recorder
    span = (recorder.t[-1] - recorder.t[0]) if len(recorder.t) > 1 else 0.0
    minutes = span / 60.0
    return {
        "track": track,
        "seed": seed,
        "completion_ratio": m.completion_ratio,
        "collisions": m.collisions,
        "collisions_per_min": m.collisions / minutes if minutes > 0 else 0.0,
        "average_speed": m.average_speed,
        "top_speed": m.top_speed,
        "laps": m.laps,
        "laps_per_min": m.laps_per_min,
        "lap_time_mean": m.lap_time_mean,
        "best_lap": m.best_lap,
        "progress_per_metre": m.progress_per_metre,
        "interventions": m.interventions,
        "distance": m.distance,
        "driving_time": m.driving_time,
        "simulated_s": span,
    }


def aggregate(runs: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Mean and (population) standard deviation of each metric over the runs; the lap times
    over the runs that have one (`runs`: how many; mean and std None when none has)."""
    out: dict[str, dict[str, Any]] = {}
    for name in (*METRICS, "collisions", "top_speed", "distance"):
        out[name] = _mean_std([float(r[name]) for r in runs])
    for name in OPTIONAL:
        values = [float(r[name]) for r in runs if r.get(name) is not None]
        stats = _mean_std(values) if values else {"mean": None, "std": None}
        out[name] = {**stats, "runs": len(values)}
    return out


def _mean_std(values: list[float]) -> dict[str, float]:
    n = len(values)
    mean = sum(values) / n if n else math.nan
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / n) if n else math.nan
    return {"mean": mean, "std": std}


def format_table(result: dict[str, Any], label: str) -> str:
    """The paper's table with the racing columns: one row for the policy (mean ± std), then one
    row per run. A lap time is over the runs with a clean lap ("—": none had one)."""
    agg = result["aggregate"]

    def pm(name: str, digits: int) -> str:
        if agg[name]["mean"] is None:
            return "—"
        return f"{agg[name]['mean']:.{digits}f} ± {agg[name]['std']:.{digits}f}"

    runs = result["runs"]
    lines = [
        "| policy | runs | completion | collisions / min | avg m/s | laps | laps / min "
        "| lap time s | progress / m |",
        "|---|---|---|---|---|---|---|---|---|",
        f"| {label} | {len(runs)} | {pm('completion_ratio', 2)} | "
        f"{pm('collisions_per_min', 1)} | {pm('average_speed', 2)} | {pm('laps', 1)} | "
        f"{pm('laps_per_min', 2)} | {pm('lap_time_mean', 2)} | {pm('progress_per_metre', 2)} |",
        "",
        f"{'track':>6} {'seed':>5} {'completion':>10} {'coll/min':>9} {'avg m/s':>8} {'laps':>5} "
        f"{'laps/min':>8} {'lap s':>6} {'prog/m':>6}",
    ]
    for r in runs:
        lap = "—" if r["lap_time_mean"] is None else f"{r['lap_time_mean']:.2f}"
        lines.append(
            f"{r['track']:>6} {r['seed']:>5} {r['completion_ratio']:>10.2f} "
            f"{r['collisions_per_min']:>9.1f} {r['average_speed']:>8.2f} {r['laps']:>5d} "
            f"{r['laps_per_min']:>8.2f} {lap:>6} {r['progress_per_metre']:>6.2f}"
        )
    return "\n".join(lines)
