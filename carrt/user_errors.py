"""Which errors a user can fix, and the one line a command says for each.

Why one place: `carrt`'s entry point and carrt-sim-data's workers (which run a drive in-process
and write what it says into the placement's log) must print the same line for the same error;
each kept its own tuple of error types and its own disk-full wording before.
"""

from __future__ import annotations

import errno

from carrt.errors import UserError
from firmware_bridge.avr_emulator import AvrEmulatorError
from firmware_bridge.link import LinkError
from firmware_bridge.native import FirmwareBuildError

# Raised for something the user can fix: one line and exit 2 (ContractError is a UserError)
USER_ERRORS = (UserError, LinkError, FirmwareBuildError, AvrEmulatorError)
DISK_FULL = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG}  # a full disk, quota or file-size limit


def one_line(exc: BaseException) -> str | None:
    """The line (without the command's prefix) for an error the user can fix: the message's
    first line, or a full disk with the file being written (any writer of any command: a
    report, a video, the simulator's run files). None: a bug, which keeps its traceback."""
    if isinstance(exc, USER_ERRORS):
        return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    if isinstance(exc, OSError) and exc.errno in DISK_FULL:
        where = f" ({exc.filename})" if exc.filename else ""
        return f"disk full: {exc.strerror}{where}"
    return None
