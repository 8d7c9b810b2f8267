"""What both calibrations (`carrt calibrate`, `--receiver`) share: a board disarmed before a
CONFIG goes to it (it refuses one while armed), and the car's TOML edited so that it still loads.

The file is the user's: hand-written, commented, in whichever TOML style they like (a `[pwm]`
header with a comment, dotted `pwm.steer_left_us = ...` keys, an inline `pwm = {...}`). A line
regex once turned the first two into a second `[pwm]` table that no TOML reader accepts, and the
calibration, reported as written, was lost on the next start. So the edit goes through
tomlkit (carrt/toml_edit.py), which keeps every comment and style it need not change; the
result is checked with the loader `carrt drive` uses before anything is written, and replaces
the file atomically: an edit that would not load, or a full disk, leaves the old file as it was
and says so in a line.
"""

from __future__ import annotations

import os
import stat
import sys
import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from carrt import config as car_config
from carrt.episodes.format import fsync_dir
from carrt.errors import UserError
from carrt.user_errors import DISK_FULL
from firmware_bridge import messages as m
from firmware_bridge.link import BoardLink

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10 (JetPack 6)
    import tomli as tomllib


def disarm_and_wait(link: BoardLink, timeout_s: float = 1.0) -> None:
    """Disarm now and wait until the board says so: it refuses CONFIG while armed."""
    link.disarm()
    link.set_command(0.0, 0.0, send_now=True)
    deadline = time.monotonic() + timeout_s
    while link.board_state == m.State.ARMED:
        if time.monotonic() > deadline:
            raise UserError("board stayed armed after a disarm request")
        time.sleep(0.005)


def update_toml_section(text: str, section: str, values: Mapping[str, object]) -> str:
    """Set keys of the top-level table `section` in a TOML text, in whichever style it is
    written (carrt/toml_edit.py); ValueError when it is not TOML or `section` not a table."""
    from carrt import toml_edit  # tomlkit only when calibrating (its docstring says why)

    return toml_edit.update_section(text, section, values)


@dataclass(frozen=True)
class ConfigEdit:
    """A checked edit of a car's TOML: `before` as read, `after` as it will be written."""

    path: Path
    before: bytes
    after: str
    summary: str  # the values, for a line that says what could not be written


def plan_edit(path: Path, section: str, values: Mapping[str, object]) -> ConfigEdit:
    """The edited text, checked with carrt's own loader and against the original (every key
    outside `values` reads the same), before the board or the file is touched; UserError in
    one line naming the file when it cannot be done."""
    path = Path(path)
    summary = ", ".join(f"{section}.{k} = {v}" for k, v in values.items())
    try:
        before = path.read_bytes()
    except OSError as exc:
        raise UserError(f"cannot read {path} ({exc.strerror}): calibration not written") from exc
    if not os.access(path, os.W_OK):
        raise UserError(f"{path} is read-only: calibration not written (make it writable)")
    try:
        text = before.decode("utf-8")
        old = tomllib.loads(text)
        after = update_toml_section(text, section, values)
        new = tomllib.loads(after)
    except (UnicodeDecodeError, tomllib.TOMLDecodeError, ValueError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise UserError(
            f"{path} is not a TOML file carrt can edit ({reason}): calibration not written, "
            "the file is unchanged"
        ) from exc
    try:
        car_config.from_dict(new)
    except UserError as exc:
        raise UserError(
            f"{path} would not load with the calibration ({exc}): not written, the file is "
            f"unchanged; the calibration was {summary}"
        ) from exc
    expected = {**old, section: {**old.get(section, {}), **values}}
    if new != expected:
        raise UserError(f"{path}: the edit would change other keys: not written ({summary})")
    return ConfigEdit(path, before, after, summary)


def commit(edit: ConfigEdit) -> None:
    """Replace the file with the edit, atomically: a temporary file beside it, written, synced
    and loaded with `carrt drive`'s loader, then renamed over it (the file's mode kept, a link
    followed). Any failure, a full disk above all, removes the temporary file and leaves the
    original intact, in one line."""
    target = Path(os.path.realpath(edit.path))
    tmp = None
    try:
        if target.read_bytes() != edit.before:
            raise UserError(
                f"{edit.path} changed while calibrating: not written (the calibration was "
                f"{edit.summary})"
            )
        st = target.stat()
        fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
        try:
            os.fchmod(fd, stat.S_IMODE(st.st_mode))
            if os.geteuid() == 0:  # `sudo carrt calibrate` keeps the user's file the user's
                os.fchown(fd, st.st_uid, st.st_gid)
            data = memoryview(edit.after.encode("utf-8"))
            while data:
                data = data[os.write(fd, data) :]
            os.fsync(fd)
        finally:
            os.close(fd)
        _check_loads(Path(tmp), edit)
        os.replace(tmp, target)
    except OSError as exc:
        why = "disk full" if exc.errno in DISK_FULL else "cannot write"
        raise UserError(
            f"{edit.path} not written ({why}: {exc.strerror}): the file is unchanged; the "
            f"calibration was {edit.summary}"
        ) from exc
    finally:
        if tmp is not None and os.path.exists(tmp):
            os.unlink(tmp)
    fsync_dir(target.parent)  # the rename survives a power cut (the battery unplugged)


def _check_loads(written: Path, edit: ConfigEdit) -> None:
    """The bytes on disk, read back by the loader `carrt drive --config` uses."""
    try:
        car_config.load(written)
    except UserError as exc:
        reason = str(exc).replace(str(written), str(edit.path))
        raise UserError(f"{edit.path} not written: it would not load ({reason})") from exc
