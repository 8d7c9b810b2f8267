"""The paper's evaluation numbers from a recorded trajectory, and a picture of the run.

Simulation table (DIRL, Table I): average speed, top speed, completion ratio (how far round the
track the car got before its first crash or takeover, as a share of a lap), lap time. Real-car
table: with auto-reset after each crash, collisions, interventions (the person took over from
the policy: the same count as the loop's summary and `carrt report`) and the time for 5 laps not
counting the time spent resetting.

Racing numbers beside them, because completion stops at the first failure and is capped at one
lap, so it cannot tell a car that races from one that drives fast anywhere (full-speed loops
across the infield): laps per minute of driving time, the mean clean lap time, and progress per
metre (metres gained along the track per metre driven: 1 on the centerline, a little more on an
inside line, less when the car wanders, loops or goes backwards).

Everything works on plain arrays sampled along the run, so the same code scores the simulator,
a recorded episode or the real car's log. Sample i covers the interval (t[i-1], t[i]].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from carrt.sim.types import Track

TELEPORT_M = 0.3  # consecutive samples further apart than this were a reset, not driving


@dataclass(frozen=True)
class SimMetrics:
    average_speed: float  # m/s over driving time (not resetting, not standing crashed)
    top_speed: float  # m/s
    completion_ratio: float  # safe distance along the track before the first failure / length
    lap_times: tuple[float, ...]  # s, each complete lap without a collision or intervention
    laps: int  # laps completed, clean or not
    collisions: int
    interventions: int  # takeovers from the policy (the loop's and carrt report's count)
    time_for_laps: float | None  # s to complete n_laps laps, reset time excluded; None if fewer
    driving_time: float  # s
    distance: float  # m driven (path length, resets' jumps excluded)
    along_track: float = math.nan  # m of progress along the track over that same path; nan: unknown
    laps_timed: int = 5  # time_for_laps is the time for this many laps (the paper's five)
    # derived, stored (not properties) so that dataclasses.asdict and the saved JSON carry them
    laps_per_min: float = field(init=False)  # laps per minute of driving time
    lap_time_mean: float | None = field(init=False)  # s, mean of lap_times; None without one
    progress_per_metre: float = field(init=False)  # along_track / distance; 0 when not driven

    def __post_init__(self) -> None:
        minutes = self.driving_time / 60.0
        per_min = self.laps / minutes if minutes > 0 else 0.0
        mean = sum(self.lap_times) / len(self.lap_times) if self.lap_times else None
        per_metre = self.along_track / self.distance if self.distance > 0 else 0.0
        object.__setattr__(self, "laps_per_min", per_min)
        object.__setattr__(self, "lap_time_mean", mean)
        object.__setattr__(self, "progress_per_metre", per_metre)

    @property
    def best_lap(self) -> float | None:
        return min(self.lap_times) if self.lap_times else None


def compute_metrics(
    t,
    x,
    y,
    speed,
    progress,
    collision,
    lap,
    track_length: float,
    *,
    resetting=None,
    intervention=None,
    n_laps: int = 5,
) -> SimMetrics:
    """Score a run. progress is the unwrapped arc position (metres along the track, growing
    lap after lap); collision, lap, resetting and intervention are per-sample flags (lap: a lap
    was completed during this sample; resetting: this sample's time was spent resetting)."""
    t = np.asarray(t, dtype=np.float64)
    n = len(t)
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    speed = np.abs(np.asarray(speed, np.float64))
    progress = np.asarray(progress, np.float64)
    crash = _flags(collision, n)
    lap = _flags(lap, n)
    resetting = _flags(resetting, n)
    failure = crash | _flags(intervention, n)
    if n == 0:
        return SimMetrics(0.0, 0.0, 0.0, (), 0, 0, 0, None, 0.0, 0.0, 0.0)

    dt = np.diff(t, prepend=t[0])
    driving = ~resetting & ~crash
    driving_time = float(np.sum(dt[driving]))
    average = float(np.sum(speed[driving] * dt[driving]) / driving_time) if driving_time else 0.0
    top = float(np.max(speed[driving])) if driving.any() else 0.0

    steps = np.hypot(np.diff(x, prepend=x[0]), np.diff(y, prepend=y[0]))
    after_break = np.concatenate(([True], (failure | resetting)[:-1]))
    moving = driving & ~after_break & (steps < TELEPORT_M)
    distance = float(np.sum(steps[moving]))
    # the progress made on exactly those steps: a reset's jump along the track is no driving
    along_track = float(np.sum(np.diff(progress, prepend=progress[0])[moving]))

    first_failure = int(np.argmax(failure)) if failure.any() else n - 1
    safe = float(np.max(progress[: first_failure + 1]) - progress[0])
    completion = min(max(safe / track_length, 0.0), 1.0) if track_length > 0 else 0.0

    lap_idx = np.nonzero(lap)[0]
    lap_times = []
    start = 0
    for k in lap_idx:
        inside = slice(start + 1, k + 1)
        if not (failure[inside].any() or resetting[inside].any()):
            lap_times.append(float(t[k] - t[start]))
        start = k

    time_for_laps = None
    if n_laps > 0 and len(lap_idx) >= n_laps:
        k = lap_idx[n_laps - 1]
        reset_time = float(np.sum(dt[1 : k + 1][resetting[1 : k + 1]]))
        time_for_laps = float(t[k] - t[0]) - reset_time

    return SimMetrics(
        average_speed=average,
        top_speed=top,
        completion_ratio=completion,
        lap_times=tuple(lap_times),
        laps=len(lap_idx),
        collisions=_rising(crash),
        interventions=_rising(_flags(intervention, n)),
        time_for_laps=time_for_laps,
        driving_time=driving_time,
        distance=distance,
        along_track=along_track,
        laps_timed=n_laps,
    )


_COLUMNS = ("t", "x", "y", "speed", "progress", "collision", "lap", "resetting", "intervention")


@dataclass
class TrajectoryRecorder:
    """Collects the arrays compute_metrics wants from a SimWorld, one sample per step."""

    t: list[float] = field(default_factory=list)
    x: list[float] = field(default_factory=list)
    y: list[float] = field(default_factory=list)
    speed: list[float] = field(default_factory=list)
    progress: list[float] = field(default_factory=list)
    collision: list[bool] = field(default_factory=list)
    lap: list[bool] = field(default_factory=list)
    resetting: list[bool] = field(default_factory=list)
    intervention: list[bool] = field(default_factory=list)

    def record(
        self, world, info=None, *, resetting: bool = False, intervention: bool = False
    ) -> None:
        """Append the world's state after a step (`info` is what that step returned); record
        once with no info before the first step, so the first lap is timed from the start."""
        row = (world.time, world.car.x, world.car.y, world.car.v, world.progress)
        hit, lap = (bool(info.collision), bool(info.lap_completed)) if info else (False, False)
        flags = (hit, lap, resetting, intervention)
        for name, value in zip(_COLUMNS, row + flags, strict=True):
            getattr(self, name).append(value)

    def arrays(self) -> dict[str, np.ndarray]:
        return {name: np.asarray(getattr(self, name)) for name in _COLUMNS}

    def metrics(self, track_length: float, n_laps: int = 5) -> SimMetrics:
        a = self.arrays()
        return compute_metrics(
            *(a[name] for name in _COLUMNS[:7]),
            track_length,
            resetting=a["resetting"],
            intervention=a["intervention"],
            n_laps=n_laps,
        )


def run_metrics(track: Track, trajectory, *, n_laps: int = 5) -> SimMetrics:
    """compute_metrics on anything with t, x, y, speed, progress, collision and lap sequences
    (resetting and intervention too, where it has them): a TrajectoryRecorder, a rig's log."""
    if isinstance(trajectory, TrajectoryRecorder):
        return trajectory.metrics(track.length, n_laps)
    cols = {name: getattr(trajectory, name, None) for name in _COLUMNS}
    return compute_metrics(
        *(cols[name] for name in _COLUMNS[:7]),
        track.length,
        resetting=cols["resetting"],
        intervention=cols["intervention"],
        n_laps=n_laps,
    )


def format_metrics(m: SimMetrics) -> str:
    """The run's numbers as a short human-readable block."""
    timed = f"{m.time_for_laps:.1f} s" if m.time_for_laps is not None else "not reached"
    mean_lap = f"{m.lap_time_mean:.2f} s" if m.lap_time_mean is not None else "—"
    per_metre = "—" if math.isnan(m.progress_per_metre) else f"{m.progress_per_metre:.2f}"
    return "\n".join(
        [
            f"average speed    {m.average_speed:.2f} m/s (top {m.top_speed:.2f} m/s)",
            f"completion ratio {m.completion_ratio:.3f}",
            f"laps             {m.laps}{_clean_laps(m)}",
            f"racing           {m.laps_per_min:.2f} laps/min of driving, mean lap {mean_lap}, "
            f"progress {per_metre} m per m driven",
            f"collisions       {m.collisions}, interventions {m.interventions}",
            f"time for {m.laps_timed} laps {timed} (resets excluded)",
            f"distance         {m.distance:.1f} m in {m.driving_time:.1f} s of driving",
        ]
    )


def _clean_laps(m: SimMetrics) -> str:
    """The lap times, which are those of clean laps only (no collision, take-over or reset
    inside the lap): said so that "laps 3" beside no times does not read as a contradiction."""
    if m.lap_times:
        times = ", ".join(f"{t:.2f}" for t in m.lap_times)
        if len(m.lap_times) >= m.laps:
            return f" (all clean, lap times {times} s)"
        return f" ({len(m.lap_times)} clean, without a collision or take-over: {times} s)"
    if m.laps:
        return " (no clean lap: every lap had a collision or take-over)"
    return ""


def plot_trajectory(
    track: Track, xs, ys, collisions, out_png, title: str = "", *, speeds=None
) -> None:
    """Top view of a run: fence, markings, obstacles, the path coloured by speed, crashes.

    Without `speeds` the colour is the distance between consecutive samples (speed, for a run
    sampled at a fixed rate). Uses matplotlib's Agg canvas directly: no pyplot, no display.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle, Rectangle

    from carrt.sim.track import boundary_polylines

    xs, ys = np.asarray(xs, np.float64), np.asarray(ys, np.float64)
    crashes = _flags(collisions, len(xs))
    steps = np.hypot(np.diff(xs), np.diff(ys))
    if speeds is None:
        colour, label = np.concatenate(([0.0], steps)), "distance per sample (m)"
    else:
        colour, label = np.abs(np.asarray(speeds, np.float64)), "speed (m/s)"

    width, height = track.arena
    fig = Figure(figsize=(9, 9 * height / width + 0.6), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.set_facecolor(np.array(track.floor_colour) / 255)
    ax.add_patch(Rectangle((0, 0), width, height, fill=False, edgecolor="black", linewidth=3))
    for line in boundary_polylines(track):
        closed = np.vstack([line, line[:1]])
        ax.plot(closed[:, 0], closed[:, 1], color="white", linewidth=1.2)
    centre = np.vstack([track.centerline, track.centerline[:1]])
    ax.plot(
        centre[:, 0],
        centre[:, 1],
        color=np.array(track.centre_marking_colour) / 255,
        linewidth=0.8,
        linestyle="--",
    )
    for ob in track.obstacles:
        ax.add_patch(Circle((ob.x, ob.y), ob.radius, color=np.array(ob.colour) / 255, zorder=3))
    if len(xs) > 1:
        pts = np.stack([xs, ys], axis=1)
        segs = np.stack([pts[:-1], pts[1:]], axis=1)
        keep = steps < TELEPORT_M  # resets jump: do not draw the jump
        lines = LineCollection(segs[keep], cmap="viridis", linewidths=2, zorder=4)
        lines.set_array(colour[1:][keep])
        ax.add_collection(lines)
        fig.colorbar(lines, ax=ax, label=label, shrink=0.8)
    hits = np.nonzero(crashes & ~np.concatenate(([False], crashes[:-1])))[0]
    if len(hits):
        ax.scatter(
            xs[hits],
            ys[hits],
            marker="x",
            s=90,
            color="red",
            linewidths=2.5,
            zorder=5,
            label=f"collisions ({len(hits)})",
        )
        ax.legend(loc="upper right")
    ax.set_xlim(-0.1, width + 0.1)
    ax.set_ylim(-0.1, height + 0.1)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    if title:
        ax.set_title(title)
    fig.savefig(out_png, bbox_inches="tight")


def _flags(values, n: int) -> np.ndarray:
    if values is None:
        return np.zeros(n, dtype=bool)
    return np.asarray(values, dtype=bool).reshape(n)


def _rising(flags: np.ndarray) -> int:
    return int(np.sum(flags & ~np.concatenate(([False], flags[:-1]))))
