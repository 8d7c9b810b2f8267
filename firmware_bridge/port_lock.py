"""Who holds a stand-in board's port path.

A virtual or emulated board publishes its pty at a stable path (a symlink) so tools can find it.
Two boards on one path would each repoint the link, and the one that stopped first would delete
the link the other's users were on: the host sees its port vanish for no reason. So a board takes
an exclusive lock on `PATH.lock` before it touches the path and holds it while it runs; a second
board on the same path refuses to start, in one line naming the holder. The lock is an flock: the
kernel drops it when the process dies, so a crashed board never blocks the next one. The lock
file itself stays (removing it would let two boards lock two different files of one name).
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path


class PortPathHeld(OSError):
    """Another running board holds this port path."""


class PortLock:
    def __init__(self, port_path: str | os.PathLike) -> None:
        self.path = Path(f"{port_path}.lock")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise PortPathHeld(
                f"{port_path}: another board (pid {holder}) is running on this port path; "
                "stop it or give this one another --port-path"
            ) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd: int | None = fd

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing drops the flock
            self._fd = None
