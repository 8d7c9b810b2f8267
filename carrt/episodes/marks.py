"""Marks: what a person says about an episode after recording it, beside it, never in it.

A person who drove into the fence for three seconds wants those seconds out of training, not
the whole episode gone; DonkeyCar's tub cleaner and LeRobot's dataset editor do that by
rewriting the data. carrt's recorded files are crash-safe and stay exactly as written (their
CRCs mean something); the marks live in `marks.json` beside them, written atomically, and every
change keeps the previous marks so it can be undone. Ranges are in seconds from the episode's
first frame (what the scrubber and `carrt episodes show` display), so they mean the same on
every copy of the episode.

    carrt episodes mark EP --exclude 12.5-15.0     # add a range (repeatable)
    carrt episodes mark EP --exclude-last 3s       # the last 3 s (a crash at the end)
    carrt episodes mark EP --exclude-all           # the whole episode
    carrt episodes mark EP --note "fence at 14 s"  # a note
    carrt episodes mark EP --list | --clear | --undo

Training (training/episodes.load_episodes) reads an episode's kept steps as separate
segments, so no imitation target, world-model window or held-out count includes an excluded
step.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from carrt.episodes import format as fmt
from carrt.episodes.reader import Episode, segment
from carrt.errors import UserError

MARKS = "marks.json"
HISTORY = 20  # earlier states kept for --undo


@dataclass
class Marks:
    exclude: list[tuple[float, float]] = field(default_factory=list)  # [start, end) s
    whole: bool = False  # the whole episode is excluded
    notes: list[str] = field(default_factory=list)
    history: list[dict[str, Any]] = field(default_factory=list)  # earlier states, newest last

    @property
    def empty(self) -> bool:
        return not (self.exclude or self.whole or self.notes)

    def state(self) -> dict[str, Any]:
        return {"exclude": [list(r) for r in self.exclude], "whole": self.whole,
                "notes": list(self.notes)}  # fmt: skip

    def excluded(self, t: np.ndarray) -> np.ndarray:
        """Which steps (capture times t, clock s) are excluded: t − t[0] inside a range."""
        if self.whole:
            return np.ones(len(t), dtype=bool)
        rel = np.asarray(t, dtype=np.float64) - (float(t[0]) if len(t) else 0.0)
        out = np.zeros(len(t), dtype=bool)
        for lo, hi in self.exclude:
            out |= (rel >= lo) & (rel < hi)
        return out

    def describe(self) -> str:
        if self.empty:
            return "none"
        parts = ["the whole episode excluded"] if self.whole else []
        parts += [f"excluded {lo:g}–{hi:g} s" for lo, hi in self.exclude]
        parts += [f"note: {note}" for note in self.notes]
        return "; ".join(parts)


def read_marks(episode: str | Path) -> Marks:
    path = Path(episode) / MARKS
    if not path.is_file():
        return Marks()
    try:
        data = json.loads(path.read_text())
        marks = Marks(
            exclude=[_range(r) for r in data.get("exclude", [])],
            whole=bool(data.get("whole", False)),
            notes=[str(n) for n in data.get("notes", [])],
            history=list(data.get("history", [])),
        )
    except (ValueError, TypeError, AttributeError) as exc:
        raise UserError(f"{path}: not a marks file ({exc})") from None
    return marks


def _range(r: Any) -> tuple[float, float]:
    lo, hi = (float(x) for x in r)
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo < 0 or hi <= lo:
        raise ValueError(f"range {r!r}: expected 0 <= start < end, finite")
    return (lo, hi)


def parse_range(text: str) -> tuple[float, float]:
    """'12.5-15.0' → (12.5, 15.0) seconds; one line naming what is wrong otherwise."""
    lo, sep, hi = text.partition("-")
    try:
        if not sep:
            raise ValueError
        return _range((lo, hi))
    except ValueError:
        raise UserError(
            f"--exclude {text}: expected START-END in seconds, e.g. 12.5-15.0"
        ) from None


def parse_seconds(text: str) -> float:
    """'3s' or '3' → 3.0."""
    try:
        value = float(text[:-1] if text.endswith("s") else text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise UserError(f"--exclude-last {text}: expected a positive duration, e.g. 3s")
    return value


def write_marks(episode: str | Path, marks: Marks) -> None:
    """Atomically (a kill leaves the old marks or the new, never half), never touching the
    recorded files."""
    payload = {"version": 1, **marks.state(), "history": marks.history[-HISTORY:]}
    fmt.write_json_atomic(Path(episode) / MARKS, payload)


def change(episode: str | Path, update) -> Marks:
    """Apply `update(marks)` and save it, the previous state kept for undo."""
    marks = read_marks(episode)
    before = marks.state()
    update(marks)
    if marks.state() != before:
        marks.history.append(before)
    write_marks(episode, marks)
    return marks


def undo(episode: str | Path) -> Marks:
    marks = read_marks(episode)
    if not marks.history:
        raise UserError(f"{episode}: no earlier marks to go back to")
    previous = marks.history.pop()
    restored = Marks(exclude=[_range(r) for r in previous["exclude"]], whole=previous["whole"],
                     notes=list(previous["notes"]), history=marks.history)  # fmt: skip
    write_marks(episode, restored)
    return restored


def kept_segments(excluded: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) runs of steps that are not excluded."""
    out, start = [], None
    for i, bad in enumerate(excluded):
        if not bad and start is None:
            start = i
        elif bad and start is not None:
            out.append((start, i))
            start = None
    if start is not None:
        out.append((start, len(excluded)))
    return out


def apply_marks(ep: Episode) -> list[Episode]:
    """The episode's steps a person did not exclude (its marks.json), as segments:
    unmarked it is itself; excluded ranges split it, so no window or sequence spans one."""
    marks = read_marks(ep.path)
    if marks.empty:
        return [ep]
    excluded = marks.excluded(ep.timestamps)
    if not excluded.any():
        return [ep]
    runs = kept_segments(excluded)
    return [segment(ep, a, b, i) for i, (a, b) in enumerate(runs)]
