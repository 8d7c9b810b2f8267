"""Episodes that flag their own problems: what is suspect in a recording, and at which steps.

A frozen camera, a dead encoder or a stick stuck at full lock make an episode that looks
normal in `carrt episodes ls` and teaches the policy something wrong. Each check below is one
function of the episode returning the [start, end) step ranges where it holds; the thresholds
are the named constants, chosen so that a clean recording (the simulator's expert, a person
driving the car) flags nothing. Collisions and take-overs are counted the same way but are not
faults: they are what the world model and the interventions learn from.

`carrt episodes ls` names an episode's flags, `show` gives each with its steps, `ls --flags
NAME` keeps the episodes that have one, `carrt episodes mark EP --exclude-flag NAME` excludes
exactly the steps a flag names (marks.json: training never sees them), and the scrubber draws
them on its timeline. Numpy only, as the rest of the reader.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from carrt.episodes.reader import DRIVING, Episode, collision_events
from carrt.errors import UserError

FROZEN_STEPS = 5  # more identical frames in a row than this (0.5 s at 10 Hz) is a frozen camera
CLOCK_GAP_PERIODS = 1.8  # a capture-to-capture step longer than this many loop periods is a gap
MOVING_THROTTLE = 0.2  # forward executed throttle above this commands the car to move
DEAD_SPEED_S = 1.0  # commanded to move while the speed reads exactly 0 for longer than this
PIN_LEVEL = 0.999  # |executed steering or throttle| at least this is at its limit
PINNED_S = 5.0  # at a limit for longer than this (the sim expert holds full throttle up to 2 s)
SHORT_S = 2.0  # an episode whose first and last frames are less than this apart is short
SAMPLE_ROWS = (16, 48, 80)  # rows compared first; only frames alike there are compared whole

Ranges = list[tuple[int, int]]


@dataclass(frozen=True)
class Check:
    name: str
    find: Callable[[Episode], Ranges]
    fault: bool  # False: an event counted, not a fault (collisions, take-overs)
    what: str


def rate_hz(ep: Episode) -> float:
    """The loop rate the episode was recorded at (meta rate_hz, else the car config's), or the
    one its median capture interval gives."""
    loop = ((ep.meta.get("car_config") or {}).get("loop")) or {}
    for value in (ep.meta.get("rate_hz"), loop.get("rate_hz")):
        try:
            rate = float(value)
        except (TypeError, ValueError):
            continue
        if math.isfinite(rate) and rate > 0:
            return rate
    dt = np.diff(ep.timestamps.astype(np.float64))
    dt = dt[dt > 0]
    return 1.0 / float(np.median(dt)) if len(dt) else 10.0


def runs(mask: np.ndarray, longer_than: int = 0) -> Ranges:
    """[start, end) runs of True in `mask` holding more than `longer_than` steps."""
    edges = np.flatnonzero(np.diff(np.concatenate(([0], np.asarray(mask, np.int8), [0]))))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)
            if b - a > longer_than]  # fmt: skip


def same_as_previous(frames: np.ndarray) -> np.ndarray:
    """same[i]: frame i is byte for byte frame i − 1. A few rows are compared for every frame
    (a memory map reads only their pages), the whole frame only where those agree."""
    n = len(frames)
    same = np.zeros(n, dtype=bool)
    if n < 2:
        return same
    rows = np.asarray(frames[:, list(SAMPLE_ROWS)])
    alike = (rows[1:] == rows[:-1]).reshape(n - 1, -1).all(axis=1)
    for i in np.flatnonzero(alike) + 1:
        same[i] = np.array_equal(frames[i], frames[i - 1])
    return same


def _moving(ep: Episode) -> np.ndarray:
    """The car moves, or is commanded to, by its speed sensor or its executed throttle."""
    throttle = ep.steps["executed_action"][:, 1]
    return (ep.steps["speed_mps"] > 0) | (throttle > MOVING_THROTTLE)


def frozen_camera(ep: Episode) -> Ranges:
    """More than FROZEN_STEPS byte-identical frames in a row while the car moves or is commanded
    to: a camera that stopped delivering (a parked simulated car renders the same frame every
    step, and that is no fault). The range holds every copy, the first frame included."""
    same = same_as_previous(ep.frames)
    moving = _moving(ep)
    out = []
    for a, b in runs(same):
        start = a - 1  # the frame the copies repeat
        if b - start > FROZEN_STEPS and moving[start:b].any():
            out.append((start, b))
    return out


def clock_gaps(ep: Episode) -> Ranges:
    """The step after a gap in the step clock: its frame was captured more than
    CLOCK_GAP_PERIODS loop periods after the previous one, not after it at all, or the loop's
    step index skipped (steps the writer dropped). Excluding that step cuts the episode there,
    so no training window spans the gap."""
    if ep.n < 2:
        return []
    dt = np.diff(ep.timestamps.astype(np.float64))
    skipped = np.diff(ep.steps["index"].astype(np.int64)) != 1
    gap = (dt > CLOCK_GAP_PERIODS / rate_hz(ep)) | (dt <= 0) | skipped
    return [(int(i) + 1, int(i) + 2) for i in np.flatnonzero(gap)]


def dead_speed_sensor(ep: Episode) -> Ranges:
    """Driving (MANUAL or AUTO) with the executed throttle beyond MOVING_THROTTLE and the speed
    exactly 0 for longer than DEAD_SPEED_S: an encoder that reads nothing (a car starting from
    rest reads speed within a few tenths of a second). Reverse and brake do not count."""
    steps = ep.steps
    mask = (np.isin(steps["mode"], DRIVING) & (steps["executed_action"][:, 1] > MOVING_THROTTLE)
            & (steps["speed_mps"] == 0))  # fmt: skip
    return runs(mask, longer_than=int(DEAD_SPEED_S * rate_hz(ep)))


def _pinned(ep: Episode, axis: int) -> Ranges:
    steps = ep.steps
    at_limit = np.abs(steps["executed_action"][:, axis]) >= PIN_LEVEL
    mask = at_limit & np.isin(steps["mode"], DRIVING)
    return runs(mask, longer_than=int(PINNED_S * rate_hz(ep)))


def pinned_steering(ep: Episode) -> Ranges:
    """The executed steering at full lock (|s| ≥ PIN_LEVEL) for more than PINNED_S while
    driving: a stick or a calibration stuck at an end."""
    return _pinned(ep, 0)


def pinned_throttle(ep: Episode) -> Ranges:
    """The executed throttle at full forward or full reverse for more than PINNED_S while
    driving."""
    return _pinned(ep, 1)


def short_episode(ep: Episode) -> Ranges:
    """The whole episode, when its first and last frames are less than SHORT_S apart (an arm
    and a disarm, a crash at the start)."""
    return [(0, ep.n)] if ep.duration_s < SHORT_S else []


def collisions(ep: Episode) -> Ranges:
    """Each collision event's step (the collision flag, an e-stop while driving, an episode
    that ended by one): counted, not a fault."""
    return [(int(k), int(k) + 1) for k in collision_events(ep.steps, _end(ep))]


def takeovers(ep: Episode) -> Ranges:
    """The steps a person took over from the policy (the override flag): counted, not a
    fault."""
    return runs(ep.steps["override"].astype(bool))


def _end(ep: Episode) -> str | None:
    return (ep.meta.get("end") or {}).get("reason")


CHECKS = (
    Check("frozen-camera", frozen_camera, True, "identical frames while moving"),
    Check("clock-gap", clock_gaps, True, "gap in the step clock"),
    Check("dead-speed", dead_speed_sensor, True, "speed 0 while commanded to move"),
    Check("pinned-steering", pinned_steering, True, "steering at its limit"),
    Check("pinned-throttle", pinned_throttle, True, "throttle at its limit"),
    Check("short", short_episode, True, f"shorter than {SHORT_S:g} s"),
    Check("collision", collisions, False, "collisions (counted, not a fault)"),
    Check("takeover", takeovers, False, "take-overs (counted, not a fault)"),
)
NAMES = tuple(check.name for check in CHECKS)


def find_flags(ep: Episode, names: tuple[str, ...] = NAMES) -> dict[str, Ranges]:
    """Each named check that holds somewhere in the episode, with its step ranges, in CHECKS'
    order."""
    found = {}
    for check in CHECKS:
        if check.name in names and (ranges := check.find(ep)):
            found[check.name] = ranges
    return found


def parse_names(text: str, option: str = "--flags") -> tuple[str, ...]:
    """'frozen-camera,clock-gap' → the names; one line naming the unknown one otherwise."""
    names = tuple(name.strip() for name in text.split(",") if name.strip())
    for name in names or ("",):
        if name not in NAMES:
            raise UserError(f"{option} {text}: unknown flag {name!r}; one of {', '.join(NAMES)}")
    return names


def is_fault(name: str) -> bool:
    return next(check.fault for check in CHECKS if check.name == name)


def label(name: str, ranges: Ranges) -> str:
    """How `ls` names a flag: a fault by its name, a counted event with its count."""
    return name if is_fault(name) else f"{name}({len(ranges)})"


def describe_ranges(ranges: Ranges, times: np.ndarray, most: int = 8) -> str:
    """'steps 10–29 (1.00–2.90 s), 41 (4.10 s)': inclusive steps and their seconds from the
    first frame, the first `most` of them."""
    rel = np.asarray(times, dtype=np.float64) - (float(times[0]) if len(times) else 0.0)
    parts = []
    for a, b in ranges[:most]:
        if b <= a:
            parts.append("no steps")
        elif b - a == 1:
            parts.append(f"{a} ({rel[a]:.2f} s)")
        else:
            parts.append(f"{a}–{b - 1} ({rel[a]:.2f}–{rel[b - 1]:.2f} s)")
    more = f", and {len(ranges) - most} more" if len(ranges) > most else ""
    return "steps " + ", ".join(parts) + more


def exclusions(ranges: Ranges, times: np.ndarray) -> list[tuple[float, float]]:
    """The marks' [lo, hi) seconds that exclude exactly the steps of `ranges` (as the scrubber
    marks a range: from the first step's time to just after the last's)."""
    t = np.asarray(times, dtype=np.float64)
    rel = t - (float(t[0]) if len(t) else 0.0)
    return [(float(rel[a]), float(rel[b - 1]) + 1e-3) for a, b in ranges if b > a]
