"""EpisodeWriter: the loop hands it steps; a thread of its own puts them on disk.

The loop must never wait for a disk (an SD card on a Jetson can stall for a second), so
write() only copies the frame and appends to a bounded queue; when the queue is full the step is
dropped and counted, and the loop carries on. On the simulator's clock nothing is real time, so
there the writer is made with `wait_when_full`: write() waits for room instead, since a dropped
step would be training data lost, and lost differently from run to run (research/LOG.md: a
recording under load dropped steps an idle one kept). Everything that touches the disk
happens on the writer thread: appending frames and records, an fsync at most `sync_every_s`
after a step was appended (the power-cut budget of docs/episodes.md), the atomic metadata at
begin and end.

A full disk (ENOSPC, or EFBIG under a file-size limit) ends the episode where it stands: the
files are cut back to the last whole step, the metadata says "disk full", `error` says so in one
line for the loop's display, and write() keeps answering False until the next begin().
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import os
import sys
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from carrt import __version__
from carrt.episodes import format as fmt
from carrt.episodes.format import write_all  # a module name of its own: tests stall the disk here
from carrt.interfaces import Clock, Step
from carrt.model_contract import HORIZON, IMAGE_SHAPE

_FULL_ERRNOS = {errno.ENOSPC, errno.EFBIG, getattr(errno, "EDQUOT", errno.ENOSPC)}
_RESERVED = {"schema", "format", "start", "end", "end_reason", "counts", "writer", "events"}


@dataclasses.dataclass
class _Episode:
    """Writer-thread state of the episode being written."""

    serial: int
    path: Path | None = None
    meta: dict[str, Any] = dataclasses.field(default_factory=dict)
    dtype: np.dtype = fmt.STEP_DTYPE
    frames_fd: int = -1
    steps_fd: int = -1
    n: int = 0  # steps appended
    synced: int = 0  # steps known durable
    sync_due: float = 0.0
    lost: int = 0  # steps that reached the thread but not the disk
    failed: str | None = None  # end reason forced by a write error


class EpisodeWriter:
    """Implements interfaces.EpisodeSink. One writer serves every episode of a run.

    Counters (read them from any thread): `written` steps appended in this run, `dropped` steps
    handed to write() that are not on disk (queue full, or after a write error), `synced` durable
    steps of the latest episode, `last_episode_path`, and `error` (one line, or None), which
    stays set after a failure so the loop can keep showing it.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        *,
        queue_steps: int = 32,
        sync_every_s: float = 1.0,
        clock: Callable[[], float] | Clock = time.monotonic,
        horizon: int = HORIZON,
        wait_when_full: bool = False,
    ) -> None:
        if queue_steps < 1:
            raise ValueError("queue_steps must be at least 1")
        self.root = Path(root)
        self.queue_steps = queue_steps
        self.sync_every_s = sync_every_s
        self.horizon = horizon
        self.wait_when_full = wait_when_full  # simulated time only: a real car never waits
        self._clock = clock.now if isinstance(clock, Clock) else clock  # a Clock or a function
        self._cond = threading.Condition()
        self._items: deque[tuple] = deque()
        self._queued_steps = 0
        # Loop-thread state.
        self._serial = -1
        self._open = False
        self._closed = False
        self._queue_drops = 0
        self._episode_drops = 0
        # Writer-thread state; plain ints and strings, read by other threads.
        self._failed_serial = -2
        self._lost = 0
        self.written = 0
        self.synced = 0
        self.episodes = 0
        self.last_episode_path: Path | None = None
        self.error: str | None = None
        self._thread = threading.Thread(target=self._run, name="episode-writer", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ loop thread
    @property
    def dropped(self) -> int:
        return self._queue_drops + self._lost

    @property
    def recording(self) -> bool:
        return self._open and self._failed_serial != self._serial

    def begin(self, metadata: dict[str, Any]) -> None:
        """Start a new episode (ending an open one as "stopped"). Returns at once.

        `metadata` is stored in meta.json as given (see format.run_metadata for the keys the
        tools read); an optional "horizon" sets H for this episode's plans.
        """
        if self._closed:
            raise RuntimeError("EpisodeWriter is closed")
        clash = _RESERVED & set(metadata)
        if clash:
            raise ValueError(f"episode metadata may not set {', '.join(sorted(clash))}")
        if self._open:
            self.end("stopped")
        self._serial += 1
        self._open = True
        self._episode_drops = 0
        self._put(("begin", self._serial, dict(metadata), time.time(), self._clock()))

    def write(self, step: Step) -> bool:
        """Queue a step; False (and a counted drop) when behind or after a write error. With
        `wait_when_full` it waits for room instead of dropping (simulated time only).

        The image is copied here, so the caller may reuse its buffer at once.
        """
        if not self._open:
            return False
        if self._failed_serial == self._serial:
            self._drop()
            return False
        image = step.image
        if image.shape != IMAGE_SHAPE or image.dtype != np.uint8:
            raise ValueError(
                f"step image must be uint8 {IMAGE_SHAPE}, got {image.dtype} {image.shape}"
            )
        if self._queued_steps >= self.queue_steps and not self.wait_when_full:
            self._drop()  # unlocked peek: the common full case is cheap
            return False
        data = image.tobytes()
        with self._cond:
            while self.wait_when_full and self._queued_steps >= self.queue_steps:
                if not self._thread.is_alive():
                    break  # nobody will make room: drop it and say so, never hang the loop
                self._cond.wait(0.5)
            if self._queued_steps >= self.queue_steps:
                full = True
            else:
                full = False
                self._queued_steps += 1
                self._items.append(("step", self._serial, step, data))
                self._cond.notify_all()
        if full:
            self._drop()
        return not full

    def event(self, kind: str, detail: dict[str, Any]) -> None:
        """Something that happened to the car during this episode (a board reboot): kept in
        meta.json's "events" with the step it came before and its time, written at once (a
        crash right after it still leaves it on disk). Returns at once."""
        if not self._open:
            return
        self._put(("event", self._serial, kind, dict(detail), time.time(), self._clock()))

    def end(self, reason: str) -> None:
        """End the episode: the writer syncs it and writes the final metadata. Returns at once."""
        if not self._open:
            return
        self._open = False
        self._put(("end", self._serial, reason, time.time(), self._clock(), self._episode_drops))

    def flush(self, timeout: float | None = 10.0) -> bool:
        """Wait until everything queued so far is on disk and synced; False on timeout."""
        done = threading.Event()
        self._put(("flush", done))
        return done.wait(timeout)

    def close(self, timeout: float | None = 10.0) -> None:
        """End an open episode ("stopped") and stop the thread once the queue is written."""
        if self._closed:
            return
        self.end("stopped")
        self._closed = True
        self._put(("stop",))
        self._thread.join(timeout)
        if self._thread.is_alive():
            self.error = f"episode writer still busy after {timeout} s (disk stalled?)"

    def __enter__(self) -> EpisodeWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _drop(self) -> None:
        self._queue_drops += 1
        self._episode_drops += 1

    def _put(self, item: tuple) -> None:
        with self._cond:
            self._items.append(item)
            self._cond.notify_all()

    # ------------------------------------------------------------------ writer thread
    def _run(self) -> None:
        ep: _Episode | None = None
        while True:
            with self._cond:
                while not self._items:
                    if ep is None or ep.failed or ep.n == ep.synced:
                        self._cond.wait()
                        continue
                    wait = ep.sync_due - self._clock()
                    if wait <= 0:
                        break
                    self._cond.wait(min(wait, self.sync_every_s))
                item = self._items.popleft() if self._items else None
                if item is not None and item[0] == "step":
                    self._queued_steps -= 1
                    self._cond.notify_all()  # room for a write() that waits (simulated time)
            try:
                if item is None or item[0] == "flush":
                    if ep is not None and not ep.failed and ep.n > ep.synced:
                        self._sync(ep)
                    if item is not None:
                        item[1].set()
                elif item[0] == "step":
                    self._step(ep, *item[1:])
                elif item[0] == "begin":
                    ep = self._begin(*item[1:])
                elif item[0] == "event":
                    self._event(ep, *item[1:])
                elif item[0] == "end":
                    self._end(ep, *item[1:])
                    ep = None
                elif item[0] == "stop":
                    return
                due = ep is not None and not ep.failed and ep.n > ep.synced
                if due and self._clock() >= ep.sync_due:
                    self._sync(ep)
            except OSError as exc:
                if ep is not None:
                    self._fail(ep, exc)
            except Exception as exc:  # a bug: keep the loop alive, say what happened
                traceback.print_exc(file=sys.stderr)
                if ep is not None:
                    self._fail(ep, exc)

    def _begin(self, serial: int, metadata: dict, wall: float, mono: float) -> _Episode:
        horizon = int(metadata.pop("horizon", self.horizon))
        ep = _Episode(serial=serial, dtype=fmt.step_dtype(horizon))
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            ep.path = fmt.new_episode_dir(self.root, wall)
            self.last_episode_path = ep.path
            self.synced = 0
            self.episodes += 1
            flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND
            ep.frames_fd = os.open(ep.path / fmt.FRAMES, flags, 0o644)
            ep.steps_fd = os.open(ep.path / fmt.STEPS, flags, 0o644)
            ep.meta = {
                "schema": fmt.SCHEMA,
                "horizon": horizon,
                "format": fmt.format_metadata(ep.dtype),
                "start": _stamp(wall, mono),
                "end": None,
                "end_reason": None,
                "counts": None,
                "writer": {
                    "carrt_version": __version__,
                    "queue_steps": self.queue_steps,
                    "sync_every_s": self.sync_every_s,
                },
                **metadata,
            }
            fmt.write_json_atomic(ep.path / fmt.META, ep.meta)
        except OSError as exc:
            where = ep.path or self.root
            self._fail(ep, exc, f"cannot start an episode in {where}")
        return ep

    def _step(self, ep: _Episode | None, serial: int, step: Step, image: bytes) -> None:
        if ep is None or ep.serial != serial or ep.failed:
            self._lost += 1
            if ep is not None and ep.serial == serial:
                ep.lost += 1
            return
        record = fmt.pack_step(step, image, ep.n, ep.dtype)
        try:
            write_all(ep.frames_fd, image)
            write_all(ep.steps_fd, record)
        except OSError:
            self._lost += 1
            ep.lost += 1
            raise
        if ep.n == ep.synced:
            ep.sync_due = self._clock() + self.sync_every_s
        ep.n += 1
        self.written += 1

    def _sync(self, ep: _Episode) -> None:
        fmt.datasync(ep.frames_fd)
        fmt.datasync(ep.steps_fd)
        n = ep.n
        fmt.write_json_atomic(ep.path / fmt.SYNCED, {"steps": n})
        ep.synced = n
        self.synced = n

    def _event(
        self, ep: _Episode | None, serial: int, kind: str, detail: dict, wall: float, mono: float
    ) -> None:
        if ep is None or ep.serial != serial or ep.path is None or ep.failed:
            return
        events = ep.meta.setdefault("events", [])
        events.append({"kind": kind, "step": ep.n, **_stamp(wall, mono), **detail})
        fmt.write_json_atomic(ep.path / fmt.META, ep.meta)

    def _end(
        self, ep: _Episode | None, serial: int, reason: str, wall: float, mono: float, drops: int
    ) -> None:
        if ep is None or ep.serial != serial or ep.path is None:
            return
        if ep.failed:
            # The episode already ended at the error; record the loop's drops and its reason.
            if not ep.meta.get("end"):
                return
            ep.meta["end"]["requested"] = _stamp(wall, mono, reason)
            ep.meta["counts"]["dropped"] = drops + ep.lost
            with contextlib.suppress(OSError):
                fmt.write_json_atomic(ep.path / fmt.META, ep.meta)
            return
        if ep.n > ep.synced:
            self._sync(ep)
        _close_fds(ep)
        ep.meta["end"] = _stamp(wall, mono, reason)
        ep.meta["end_reason"] = reason
        ep.meta["counts"] = {"steps": ep.n, "dropped": drops + ep.lost}
        fmt.write_json_atomic(ep.path / fmt.META, ep.meta)

    def _fail(self, ep: _Episode, exc: BaseException, what: str | None = None) -> None:
        """Stop this episode where it stands and leave it readable."""
        if ep.failed:
            return
        full = isinstance(exc, OSError) and exc.errno in _FULL_ERRNOS
        ep.failed = fmt.END_DISK_FULL if full else fmt.END_WRITE_ERROR
        self._failed_serial = ep.serial
        detail = exc.strerror if isinstance(exc, OSError) and exc.strerror else repr(exc)
        if what is None:
            name = ep.path.name if ep.path else "?"
            what = f"{ep.failed}: episode {name} stopped after {ep.n} steps"
        self.error = f"{what} ({detail})"
        if ep.path is None or ep.frames_fd < 0:
            _close_fds(ep)
            return
        try:  # cut a half-written step off, so the reader need not
            os.ftruncate(ep.frames_fd, ep.n * fmt.FRAME_BYTES)
            os.ftruncate(ep.steps_fd, ep.n * ep.dtype.itemsize)
            fmt.datasync(ep.frames_fd)
            fmt.datasync(ep.steps_fd)
            fmt.write_json_atomic(ep.path / fmt.SYNCED, {"steps": ep.n})
            ep.synced = ep.n
            self.synced = ep.n
        except OSError:
            pass
        _close_fds(ep)
        if "schema" not in ep.meta:
            return
        ep.meta["end"] = {**_stamp(time.time(), self._clock(), ep.failed), "error": self.error}
        ep.meta["end_reason"] = ep.failed
        ep.meta["counts"] = {"steps": ep.n, "dropped": ep.lost}
        with contextlib.suppress(OSError):
            fmt.write_json_atomic(ep.path / fmt.META, ep.meta)


def _stamp(wall: float, mono: float, reason: str | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {
        "wall": wall,
        "monotonic": mono,
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(wall)),
    }
    if reason is not None:
        out["reason"] = reason
    return out


def _close_fds(ep: _Episode) -> None:
    for name in ("frames_fd", "steps_fd"):
        fd = getattr(ep, name)
        if fd >= 0:
            with contextlib.suppress(OSError):
                os.close(fd)
            setattr(ep, name, -1)
