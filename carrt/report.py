"""`carrt report`: the paper's real-car metrics from recorded episodes.

DIRL reports, per trial on the real track: average speed, top speed, interventions, and the time
for five laps with the reset time excluded. Here a run is the episodes given (a trial that was
e-stopped and reset spans several episodes) or each episode alone with --per-episode.

Lap times come only from lap marks (the lap button, pressed each time the car crosses the line,
the start included: N marks make N−1 laps). Without marks there are no lap times: the report says
so rather than guessing from distance. A trial goes on across an episode that ended in a
collision, an e-stop or a failsafe (the car was reset and re-armed) within one drive (its
session; in the simulator, its placement); a deliberate disarm or another drive closes it, so
the next episode's first mark starts a lap and closes none (carrt/laps.py, the rule the
loop's summary and the simulator count by too). Time is the measured frame capture times;
excluded are (a) the stretches after a collision or e-stop while the car is DISARMED or in ESTOP,
until it is driving again (the reset), and (b) anything between two episodes, which was not
recorded. Laps per minute are the timed laps over the minutes of driving (MANUAL or AUTO), as
the simulator's metrics count them (carrt/sim/metrics.py).
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path
from typing import Any

import numpy as np

from carrt.episodes.reader import (
    DRIVING,
    Episode,
    collision_events,
    estop_count,
    list_episodes,
    read_episode,
    speed_stats,
)
from carrt.errors import UserError
from carrt.laps import TRIAL_GOES_ON


def _timeline(episodes: list[Episode]) -> dict[str, np.ndarray]:
    """Per step of the run: the interval to the next step in the same episode (0 at an
    episode's end: the gap is unrecorded), whether it counts, and the lap marks."""
    dts, counted, laps, ep_of = [], [], [], []
    post_event = stopped = False  # a reset can span episodes: the state carries over
    for e, ep in enumerate(episodes):
        n = ep.n
        if n == 0:
            continue
        t = ep.timestamps.astype(np.float64)
        mode = ep.steps["mode"]
        events = set(collision_events(ep.steps, (ep.meta.get("end") or {}).get("reason")).tolist())
        keep = np.ones(n, dtype=bool)
        for j in range(n):
            if j in events:
                post_event, stopped = True, False
            driving = int(mode[j]) in DRIVING
            if post_event and driving and stopped:
                post_event = False  # re-armed after the reset
            if post_event and not driving:
                stopped = True
                keep[j] = False
        dt = np.zeros(n)
        dt[:-1] = np.clip(np.diff(t), 0.0, None)
        dts.append(dt)
        counted.append(keep)
        laps.append(ep.steps["lap"].astype(bool))
        ep_of.append(np.full(n, e))
    if not dts:
        empty = np.zeros(0)
        return {"dt": empty, "counted": empty.astype(bool), "lap": empty.astype(bool), "ep": empty}
    return {
        "dt": np.concatenate(dts),
        "counted": np.concatenate(counted),
        "lap": np.concatenate(laps),
        "ep": np.concatenate(ep_of),
    }


def session_of(ep: Episode) -> tuple:
    """Which drive an episode belongs to: its session id (one per `carrt teleop/drive` run) and,
    in the simulator, its obstacle placement. A trial never spans two: a folder of several
    drives is several trials, not one whose laps run from one drive's last mark into the next
    drive's first."""
    sim = ep.meta.get("sim") or {}
    return ep.meta.get("session_id"), sim.get("layout"), sim.get("track_seed")


def lap_times(episodes: list[Episode]) -> dict[str, Any]:
    """Times between consecutive lap marks, reset time excluded; notes say what was assumed."""
    line = _timeline(episodes)
    marks = np.flatnonzero(line["lap"])
    notes: list[str] = []
    if len(marks) == 0:
        notes.append("no lap marks: press the lap button at the line to time laps")
    elif len(marks) == 1:
        notes.append("one lap mark only: a lap needs a mark at its start and at its end")
    laps, resets = [], []
    for a, b in itertools.pairwise(marks):
        first, last = int(line["ep"][a]), int(line["ep"][b])
        if any(episodes[e].end_reason not in TRIAL_GOES_ON for e in range(first, last)):
            continue  # a trial ended in between: b starts the next one
        if len({session_of(episodes[e]) for e in range(first, last + 1)}) > 1:
            continue  # another session (another drive, another placement): another trial
        dt, keep = line["dt"][a:b], line["counted"][a:b]
        laps.append(float(dt[keep].sum()))
        resets.append(float(dt[~keep].sum()))
        if first != last:
            names = ", ".join(episodes[e].name for e in range(first, last))
            notes.append(
                f"lap {len(laps)} spans the end of {names}: the time between episodes "
                "was not recorded and is not counted"
            )
    return {
        "laps_s": laps,
        "laps_total_s": float(sum(laps)) if laps else None,
        "lap_mean_s": float(np.mean(laps)) if laps else None,
        "reset_excluded_s": float(sum(resets)),
        "notes": notes,
    }


def run_metrics(name: str, episodes: list[Episode]) -> dict[str, Any]:
    def column(name: str) -> np.ndarray:  # episodes may differ in horizon, so not one array
        return np.concatenate([ep.steps[name] for ep in episodes] or [np.zeros(0)])

    avg, top = speed_stats(column("speed_mps"), column("mode"))
    driving_s = 0.0
    for ep in episodes:
        if ep.n > 1:
            dt = np.clip(np.diff(ep.timestamps.astype(np.float64)), 0.0, None)
            driving_s += float(dt[np.isin(ep.steps["mode"][:-1], DRIVING)].sum())
    collisions = sum(
        len(collision_events(ep.steps, (ep.meta.get("end") or {}).get("reason"))) for ep in episodes
    )
    laps = lap_times(episodes)
    return {
        "run": name,
        "episodes": [ep.name for ep in episodes],
        "frames": sum(ep.n for ep in episodes),
        "driving_s": driving_s,
        "avg_speed_mps": avg,
        "top_speed_mps": top,
        "interventions": int(np.count_nonzero(column("override"))),
        "estops": sum(estop_count(ep.steps) for ep in episodes),
        "collisions": collisions,
        **laps,
        "laps_per_min": len(laps["laps_s"]) / (driving_s / 60.0) if driving_s > 0 else None,
    }


def build_report(paths: list[str], per_episode: bool = False) -> list[dict[str, Any]]:
    episodes = [read_episode(p) for p in list_episodes(paths)]
    if per_episode:
        return [run_metrics(ep.name, [ep]) for ep in episodes]
    name = paths[0] if len(paths) == 1 else f"{len(paths)} paths"
    return [run_metrics(str(name), episodes)]


def _fmt(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def render_table(runs: list[dict[str, Any]]) -> str:
    header = (
        f"{'run':<28} {'eps':>4} {'frames':>7} {'drive s':>8} {'avg m/s':>8} {'top m/s':>8} "
        f"{'interv':>6} {'e-stop':>6} {'coll':>5} {'laps':>5} {'lap total s':>12} "
        f"{'mean lap s':>11} {'laps/min':>8}"
    )
    lines = [header, "-" * len(header)]
    for r in runs:
        name = r["run"] if len(r["run"]) <= 28 else "…" + r["run"][-27:]
        lines.append(
            f"{name:<28} {len(r['episodes']):>4} {r['frames']:>7} {r['driving_s']:>8.1f} "
            f"{r['avg_speed_mps']:>8.2f} {r['top_speed_mps']:>8.2f} {r['interventions']:>6} "
            f"{r['estops']:>6} {r['collisions']:>5} {len(r['laps_s']):>5} "
            f"{_fmt(r['laps_total_s']):>12} {_fmt(r['lap_mean_s']):>11} "
            f"{_fmt(r['laps_per_min']):>8}"
        )
    for r in runs:
        prefix = f"{r['run']}: "
        if r["laps_s"]:
            times = ", ".join(f"{t:.2f}" for t in r["laps_s"])
            lines.append(
                f"{prefix}lap times {times} s; reset time excluded {r['reset_excluded_s']:.1f} s"
            )
        lines.extend(prefix + note for note in r["notes"])
    return "\n".join(lines)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "report",
        help="real-car metrics: average/top speed, interventions, lap times without resets",
    )
    parser.add_argument(
        "paths", nargs="+", metavar="EP_OR_DIR", help="episode directories or directories of them"
    )
    parser.add_argument(
        "--per-episode", action="store_true", help="one row per episode instead of one run"
    )
    parser.add_argument("--json", metavar="OUT", help="also write the metrics as JSON")
    parser.set_defaults(func=run)


def find_runs(paths: list[str]) -> list[Path]:
    """Saved simulator runs (sim-runs/*.npz) among the paths; a car's directories have none,
    so the car's report never imports the simulator."""
    found: list[Path] = []
    for raw in paths:
        path = Path(raw)
        if path.suffix == ".npz" and path.is_file():
            found.append(path)
        elif path.is_dir():
            found.extend(sorted(path.glob("sim-runs/*.npz")) + sorted(path.glob("*.npz")))
    return found


def run(args: argparse.Namespace) -> int:
    sim_runs = find_runs(args.paths)
    if sim_runs:  # the paper's simulation table, from the runs' saved trajectories
        from carrt.sim.runs import load_metrics, render_sim_table

        print("simulation (sim-runs/*.npz; plots beside them)")
        print(render_sim_table([load_metrics(p) for p in sim_runs]))
        print()
    try:
        runs = build_report(args.paths, per_episode=args.per_episode)
    except UserError:
        if sim_runs:
            return 0  # runs without recorded episodes: the simulation table is the report
        raise
    print(render_table(runs))
    if args.json:
        out = Path(args.json)
        try:
            out.write_text(json.dumps({"runs": runs}, indent=2) + "\n")
        except OSError as exc:
            raise UserError(f"cannot write {out}: {exc.strerror or exc}") from exc
        print(f"wrote {out}")
    return 0
