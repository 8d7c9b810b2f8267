"""How much recording the disk has room for, said before recording starts.

A full disk in the middle of a session loses the rest of it; a person would rather know at the
start that the card holds four minutes, and not start at all with less than a floor
(`episodes.min_free_minutes`). Space is counted in minutes of recording at the loop's rate:
one frame and one step record per tick.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from carrt.episodes import format as fmt
from carrt.errors import UserError
from carrt.model_contract import HORIZON


def step_bytes(horizon: int = HORIZON) -> int:
    """What one recorded step costs on disk (the frame and its record)."""
    return fmt.FRAME_BYTES + fmt.step_dtype(horizon).itemsize


def existing_parent(path: Path) -> Path:
    path = Path(path).absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def minutes_left(directory: str | Path, rate_hz: float, horizon: int = HORIZON) -> float:
    free = shutil.disk_usage(existing_parent(Path(directory))).free
    return free / (step_bytes(horizon) * rate_hz * 60.0)


def check_room(directory: str | Path, rate_hz: float, floor_minutes: float) -> str:
    """The line to show before recording; a UserError (one line) below the floor."""
    left = minutes_left(directory, rate_hz)
    if left < floor_minutes:
        raise UserError(
            f"{directory}: room for {left:.1f} min of recording, under the {floor_minutes:g} "
            "min floor (episodes.min_free_minutes): free some space or record elsewhere (--out)"
        )
    return f"recording into {directory}: room for about {left:.0f} min"
