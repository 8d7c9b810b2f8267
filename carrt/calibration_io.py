"""What both calibrations (`carrt calibrate`, `--receiver`) share: a board disarmed before a
CONFIG goes to it (it refuses one while armed), and a TOML section edited in place."""

from __future__ import annotations

import re
import time

from carrt.errors import UserError
from firmware_bridge import messages as m
from firmware_bridge.link import BoardLink


def disarm_and_wait(link: BoardLink, timeout_s: float = 1.0) -> None:
    """Disarm now and wait until the board says so: it refuses CONFIG while armed."""
    link.disarm()
    link.set_command(0.0, 0.0, send_now=True)
    deadline = time.monotonic() + timeout_s
    while link.board_state == m.State.ARMED:
        if time.monotonic() > deadline:
            raise UserError("board stayed armed after a disarm request")
        time.sleep(0.005)


def update_toml_section(text: str, section: str, values: dict[str, object]) -> str:
    """Set keys in one [section] of a TOML text, keeping every other line and comment."""
    lines = text.splitlines()
    start = next((i for i, ln in enumerate(lines) if ln.strip() == f"[{section}]"), None)
    if start is None:
        lines += ["", f"[{section}]"]
        start = len(lines) - 1
    end = next(
        (i for i in range(start + 1, len(lines)) if lines[i].lstrip().startswith("[")), len(lines)
    )
    for key, value in values.items():
        pattern = re.compile(rf"^(\s*{re.escape(key)}\s*=\s*)([^#]*?)(\s*#.*)?$")
        for i in range(start + 1, end):
            match = pattern.match(lines[i])
            if match:
                lines[i] = f"{match.group(1)}{value}{match.group(3) or ''}"
                break
        else:
            lines.insert(end, f"{key} = {value}")
            end += 1
    return "\n".join(lines) + "\n"
