"""One placement of carrt-sim-data: its job, its run in a pool worker, its publication.

A worker runs the placement's drive in-process (carrt.session.run_session: no interpreter start
per placement) and everything the drive says goes into the placement's log through the `carrt`
loggers and an explicit stream, never a redirected stdout. It records into a hidden staging
folder (`.partial-TRACK`) published into OUT only when it finished (training/sim_data.py).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from carrt.errors import EXIT_USAGE, UserError
from carrt.session import DRIVE_ERRORS, DriveConfig, run_session
from carrt.user_errors import one_line


@dataclass(frozen=True)
class Job:
    """One placement's recording: its drive (recording into `staging`), where it logs, its
    done-marker and the folder it is published into."""

    drive: DriveConfig
    log: Path
    marker: Path
    out: Path
    track: int

    @property
    def staging(self) -> Path:
        return staging_of(self.out, self.track)

    @property
    def complete(self) -> Path:
        return self.out / f".complete-{self.track}"


def staging_of(out: Path, track: int) -> Path:
    return out / f".partial-{track}"


def publish(job: Job) -> None:
    """A finished placement into OUT; each step can be repeated after a kill at any point: the
    staging folder is renamed (from then on the attempt counts), its entries are moved in
    (folders such as sim-runs/ merged), then the marker is written."""
    if job.staging.exists():
        os.replace(job.staging, job.complete)
    if job.complete.exists():
        _merge(job.complete, job.out)
        shutil.rmtree(job.complete)
    job.marker.touch()


def _merge(src: Path, dst: Path) -> None:
    """Every entry of src into dst. Two workers publish at once: a folder (sim-runs/) the other
    created a moment ago is merged into, never raced with a check first."""
    for entry in sorted(src.iterdir()):
        target = dst / entry.name
        if (entry / "meta.json").exists():
            _move_episode(entry, dst)
        elif entry.is_dir():
            try:
                os.rename(entry, target)  # fails while target holds something
            except OSError as exc:
                if exc.errno not in (errno.EEXIST, errno.ENOTEMPTY, errno.EISDIR):
                    raise
                _merge(entry, target)
                entry.rmdir()
        else:
            os.replace(entry, target)


def _move_episode(episode: Path, dst: Path) -> None:
    """Episodes of placements recorded side by side can share a name (the second they began):
    the next free serial of the same second, as the writer itself picks one; a rename onto an
    existing episode fails, so two workers publishing at once cannot take the same name."""
    stem = episode.name.rsplit("-", 1)[0]
    names = [episode.name] + [f"{stem}-{n:03d}" for n in range(1000)]
    for name in names:
        try:
            os.rename(episode, dst / name)
            return
        except OSError as exc:
            if exc.errno not in (errno.EEXIST, errno.ENOTEMPTY):
                raise
    raise UserError(f"{dst}: no free episode name for {episode.name}")


def run_placement(job: Job) -> tuple[Job, int]:
    """In a pool worker: the placement's session in-process (no interpreter start per
    placement), everything it says written into the placement's log; its exit code as the
    command's would be (0, 2 for an error the user can fix, 128 + a signal)."""
    job.log.parent.mkdir(parents=True, exist_ok=True)
    if job.staging.exists():  # an interrupted attempt's partial output: it starts again
        shutil.rmtree(job.staging)
    with job.log.open("w") as log, _carrt_logging_into(log):
        code = _drive(job.drive, log)
    if code == 0:
        publish(job)
    return job, code


def _drive(drive: DriveConfig, log) -> int:
    """The drive, its lines and report into `log`, an error the user can fix as the one line
    `carrt teleop|drive` prints for it."""
    try:
        return run_session(drive, log=logging.getLogger("carrt.session"), out=log).exit_code
    except (*DRIVE_ERRORS, OSError) as exc:
        message = one_line(exc)
        if message is None:  # not the user's to fix: a bug, with its traceback
            raise
        print(f"carrt {drive.command}: error: {message}", file=log)
        return EXIT_USAGE


class _LogLines(logging.Handler):
    """The `carrt` loggers' lines as the console shows them (info as it is, warnings and
    errors with their level in front), into a placement's log."""

    def __init__(self, stream) -> None:
        super().__init__()
        self.stream = stream

    def emit(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        if record.levelno >= logging.WARNING:
            text = f"{record.levelname.lower()}: {text}"
        print(text, file=self.stream)


@contextlib.contextmanager
def _carrt_logging_into(stream):
    """While one placement runs in this worker (one at a time), the `carrt` loggers write into
    its log, at the command line's default level (info)."""
    logger = logging.getLogger("carrt")
    handler, level, propagate = _LogLines(stream), logger.level, logger.propagate
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    logger.propagate = False
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
        logger.propagate = propagate


__all__ = ["Job", "publish", "run_placement", "staging_of"]
