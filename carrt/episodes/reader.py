"""Read episodes with numpy alone; recover a torn tail without a repair step.

The reader never writes. It trusts the steps that `synced.json` says were durable and checks
each record after that (magic, record number, CRC over record and frame), stopping at the first
that fails: that is where the power went. With `verify_all` it checks the durable steps too, and
a record that fails there is not a cut but damage (a flipped bit on disk, a bad copy): the
episode says so (`Episode.damage`: which step, which file, how many intact steps follow) instead
of passing it off as a torn tail. Collision labels are derived here, from the recorded flags and
the end reason, so nothing on disk is ever rewritten after the fact.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from carrt.episodes import format as fmt
from carrt.errors import UserError
from carrt.interfaces import Mode
from carrt.model_contract import IMAGE_SHAPE

DRIVING = (int(Mode.MANUAL), int(Mode.AUTO))


@dataclass(frozen=True)
class Damage:
    """A step inside the region the writer had made durable that fails its checks."""

    step: int  # the first damaged step; the episode is read up to it
    durable: int  # steps the writer had synced (or closed the episode with)
    where: str  # the file(s) at fault
    intact_after: int  # later durable steps that pass their own checks (salvageable)

    def describe(self, path: Path) -> str:
        return (
            f"{path}: corrupted at step {self.step} of the {self.durable} written durably "
            f"({self.where}); reading stops there; {self.intact_after} intact steps after it"
        )


@dataclass
class Episode:
    """One episode as read: `frames[i]` is the image of `steps[i]`; `collision[i]` its label c."""

    path: Path
    meta: dict[str, Any]
    frames: np.ndarray  # np.memmap (N, 96, 96, 3) uint8, read-only (a plain empty array if N=0)
    steps: np.ndarray  # structured (N,), dtype from meta.json
    collision: np.ndarray  # uint8 (N,)
    torn: bool  # bytes after the last valid step were ignored
    damage: Damage | None = None  # verify_all found damage inside the durable steps
    start: int = 0  # a segment of the recorded episode (marks): its first step in the files
    part: str = ""  # the segment's suffix to the name ("#1")

    @property
    def name(self) -> str:
        return self.path.name + self.part

    @property
    def n(self) -> int:
        return len(self.steps)

    @property
    def timestamps(self) -> np.ndarray:
        """Measured frame capture times (clock seconds)."""
        return self.steps["frame_captured_at"]

    @property
    def duration_s(self) -> float:
        """From the first frame's capture to the last's (0 for fewer than two steps)."""
        t = self.timestamps
        return float(t[-1] - t[0]) if len(t) > 1 else 0.0

    @property
    def end_reason(self) -> str:
        end = self.meta.get("end") or {}
        return str(end.get("reason") or fmt.END_CRASHED)

    @property
    def finished(self) -> bool:
        """The writer wrote the end metadata (otherwise the run crashed or lost power)."""
        return bool(self.meta.get("end"))


def read_meta(path: Path) -> dict[str, Any]:
    meta_path = path / fmt.META
    if not meta_path.is_file():
        raise UserError(f"{path} is not a carrt episode (no {fmt.META})")
    try:
        meta = json.loads(meta_path.read_text())
    except (ValueError, OSError) as exc:
        raise UserError(f"{meta_path}: unreadable ({exc})") from exc
    schema = str(meta.get("schema", ""))
    if not schema.startswith("carrt.episode/"):
        raise UserError(f"{path} is not a carrt episode (schema {schema!r})")
    if schema.rsplit("/", 1)[1] != fmt.SCHEMA_MAJOR:
        raise UserError(f"{path}: episode schema {schema} is not {fmt.SCHEMA}; update carrt")
    return meta


def read_episode(path: str | os.PathLike, *, verify_all: bool = False) -> Episode:
    """Open an episode. `verify_all` checks every CRC instead of only the unsynced tail."""
    path = Path(path)
    if path.name == fmt.META and path.is_file():
        path = path.parent
    if not path.exists():
        raise UserError(f"{path} does not exist")
    meta = read_meta(path)
    try:
        dtype = fmt.dtype_from_json(meta["format"]["steps"]["dtype"])
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{path}: {fmt.META} has no usable step format ({exc!r})") from exc
    steps_path, frames_path = path / fmt.STEPS, path / fmt.FRAMES
    steps_size = _size(steps_path)
    frames_size = _size(frames_path)
    candidates = min(steps_size // dtype.itemsize, frames_size // fmt.FRAME_BYTES)

    frames = _map_frames(frames_path, candidates)
    raw = np.fromfile(steps_path, dtype=dtype, count=candidates) if candidates else None
    trusted = 0 if verify_all else min(_synced(path), candidates)
    n = trusted + _valid_prefix(raw, frames, trusted, dtype) if candidates else 0

    damage = _damage(path, meta, raw, frames, n, dtype) if verify_all else None
    steps = raw[:n] if raw is not None else np.zeros(0, dtype=dtype)
    frames = frames[:n]
    torn = steps_size != n * dtype.itemsize or frames_size != n * fmt.FRAME_BYTES
    collision = collision_labels(steps, end_reason=(meta.get("end") or {}).get("reason"))
    return Episode(path, meta, frames, steps, collision, torn and damage is None, damage)


def segment(ep: Episode, start: int, end: int, index: int) -> Episode:
    """Steps [start, end) of an episode as an episode of its own (views, nothing copied)."""
    return Episode(ep.path, ep.meta, ep.frames[start:end], ep.steps[start:end],
                   ep.collision[start:end], ep.torn, ep.damage, ep.start + start,
                   f"#{index}")  # fmt: skip


def _damage(path: Path, meta: dict, raw, frames, n: int, dtype: np.dtype) -> Damage | None:
    """Damage when the whole records read (n) stop short of the steps the writer made durable:
    those synced, or, for an episode closed cleanly, every step it counted."""
    durable = _synced(path)
    if meta.get("end"):
        durable = max(durable, int((meta.get("counts") or {}).get("steps") or 0))
    if n >= durable:
        return None
    have = 0 if raw is None else len(raw)
    if n >= have:  # the files end before the durable steps do
        return Damage(n, durable, f"{fmt.STEPS} and {fmt.FRAMES} end at step {have}", 0)
    record = raw[n]
    if record["magic"] != fmt.MAGIC or record["seq"] != n:
        where = f"{fmt.STEPS}: record {n}'s header"
    else:
        where = f"{fmt.STEPS} record {n} or its frame in {fmt.FRAMES}: CRC mismatch"
    intact = intact_records(raw, frames, n + 1, min(durable, have), dtype)
    return Damage(n, durable, where, len(intact))


def intact_records(raw: np.ndarray, frames: np.ndarray, start: int, stop: int,
                   dtype: np.dtype) -> list[int]:  # fmt: skip
    """Indices in [start, stop) of the records that pass their own checks (magic, record
    number, CRC over record and frame): the steps a damaged episode still holds whole."""
    return [i for i in range(start, stop) if _valid_prefix(raw[: i + 1], frames, i, dtype) == 1]


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except FileNotFoundError:
        return 0


def _synced(path: Path) -> int:
    """Steps the writer knew durable; 0 (check everything) if the file is missing or torn."""
    try:
        return max(0, int(json.loads((path / fmt.SYNCED).read_text())["steps"]))
    except (OSError, ValueError, KeyError, TypeError):
        return 0


def _map_frames(frames_path: Path, n: int) -> np.ndarray:
    if n == 0:
        empty = np.zeros((0, *IMAGE_SHAPE), dtype=np.uint8)
        empty.flags.writeable = False
        return empty
    return np.memmap(frames_path, dtype=np.uint8, mode="r", shape=(n, *IMAGE_SHAPE))


def _valid_prefix(raw: np.ndarray, frames: np.ndarray, start: int, dtype: np.dtype) -> int:
    """How many records from `start` on are whole: magic, record number and CRC all agree."""
    count = len(raw) - start
    if count <= 0:
        return 0
    tail = raw[start:]
    ok = (tail["magic"] == fmt.MAGIC) & (tail["seq"] == np.arange(start, len(raw), dtype=np.uint32))
    bad = np.flatnonzero(~ok)
    limit = int(bad[0]) if len(bad) else count
    records = tail.view(np.uint8).reshape(count, dtype.itemsize)
    crcs = tail["crc"]
    for i in range(limit):
        if fmt.record_crc(records[i], frames[start + i]) != int(crcs[i]):
            return i
    return limit


def collision_events(steps: np.ndarray, end_reason: str | None = None) -> np.ndarray:
    """Indices k of collision events: the collision flag, an e-stop latched while driving, or
    the last step of an episode that ended by collision or e-stop."""
    n = len(steps)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    event = steps["collision"].astype(bool).copy()
    estop = steps["estop"].astype(bool)
    mode = steps["mode"].astype(np.int64)
    prev_estop = np.concatenate(([False], estop[:-1]))
    prev_mode = np.concatenate((mode[:1], mode[:-1]))
    driving = np.isin(mode, DRIVING) | np.isin(prev_mode, DRIVING)
    event |= estop & ~prev_estop & driving
    if end_reason in fmt.COLLISION_END_REASONS:
        event[-1] = True
    return np.flatnonzero(event)


def collision_labels(steps: np.ndarray, end_reason: str | None = None) -> np.ndarray:
    """c = 1 for every step captured in (t_k − 0.5 s, t_k] of an event at step k (the paper)."""
    t = steps["frame_captured_at"] if len(steps) else np.zeros(0)
    return labels_before(t, collision_events(steps, end_reason))


def labels_before(t: np.ndarray, events: Iterable[int]) -> np.ndarray:
    """1 for every step whose capture time lies in (t_k − 0.5 s, t_k] of an event step k: the
    paper's collision window, which training also puts before a person's take-over."""
    labels = np.zeros(len(t), dtype=np.uint8)
    for k in events:
        tk = t[k]
        labels[(t > tk - fmt.COLLISION_WINDOW_S + fmt.WINDOW_TOLERANCE_S) & (t <= tk)] = 1
    return labels


def speed_stats(speed: np.ndarray, mode: np.ndarray) -> tuple[float, float]:
    """(average, top) speed over the steps where someone was driving (MANUAL or AUTO); parked
    time before arming or after an e-stop would only dilute the average."""
    speeds = np.asarray(speed, dtype=np.float64)[np.isin(mode, DRIVING)]
    speeds = speeds[np.isfinite(speeds)]
    if len(speeds) == 0:
        return 0.0, 0.0
    return float(speeds.mean()), float(speeds.max())


def estop_count(steps: np.ndarray) -> int:
    estop = steps["estop"].astype(bool)
    return int(np.count_nonzero(estop & ~np.concatenate(([False], estop[:-1]))))


def is_episode(path: Path) -> bool:
    return (path / fmt.META).is_file()


def list_episodes(root_or_paths: str | os.PathLike | Iterable[str | os.PathLike]) -> list[Path]:
    """Episode directories, sorted by name (= start time), from episode dirs and/or dirs of them.

    Raises UserError for a path that does not exist, that is neither an episode nor holds any,
    and when nothing at all was found.
    """
    if isinstance(root_or_paths, (str, os.PathLike)):
        root_or_paths = [root_or_paths]
    found: set[Path] = set()
    for item in root_or_paths:
        path = Path(item)
        if path.name == fmt.META and path.is_file():
            path = path.parent
        if not path.exists():
            raise UserError(f"{path} does not exist")
        if is_episode(path):
            found.add(path)
            continue
        if not path.is_dir():
            raise UserError(f"{path} is not a carrt episode (no {fmt.META})")
        children = [c for c in path.iterdir() if c.is_dir() and is_episode(c)]
        if not children:
            raise UserError(f"no episodes in {path}")
        found.update(children)
    if not found:
        raise UserError("no episodes given")
    return sorted(found, key=lambda p: (p.name, str(p)))


def in_order(paths: Iterable[str | os.PathLike]) -> list[Path]:
    """Episodes in the order given, each folder of episodes expanded in place (by name, as
    `list_episodes` does): the commands that play episodes in sequence take what `ls` takes."""
    return [episode for path in paths for episode in list_episodes(path)]


def iter_episodes(root_or_paths: Any, *, verify_all: bool = False) -> Iterable[Episode]:
    for path in list_episodes(root_or_paths):
        yield read_episode(path, verify_all=verify_all)
