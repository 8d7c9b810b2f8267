"""An episode for the eye: a contact sheet of its frames (OpenCV; the video is in video.py).

These exist so a human can check a recording before it goes into training: that the camera was
pointing where it should, that the e-stops and collisions are where they remember them, that
the noise injection was on for about half of the time.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from carrt.episodes.reader import Episode
from carrt.errors import UserError
from carrt.model_contract import IMAGE_SHAPE


def _require_frames(ep: Episode) -> None:
    if ep.n == 0:
        raise UserError(f"{ep.path} has no frames to render")


def render_contact_sheet(
    ep: Episode, out_png: str | os.PathLike, every: int = 10, columns: int = 10
) -> Path:
    """Every `every`-th frame in a grid, each captioned with its step and time since the start;
    collision-labelled frames are framed in red."""
    _require_frames(ep)
    if every < 1 or columns < 1:
        raise UserError("--every and columns must be at least 1")
    picks = list(range(0, ep.n, every))
    rows = -(-len(picks) // columns)
    cols = min(columns, len(picks))
    tile, caption = IMAGE_SHAPE[0], 12  # frames at their own size
    sheet = np.full((rows * (tile + caption), cols * tile, 3), 32, dtype=np.uint8)
    t0 = float(ep.timestamps[0])
    for slot, i in enumerate(picks):
        y, x = (slot // columns) * (tile + caption), (slot % columns) * tile
        img = cv2.cvtColor(np.asarray(ep.frames[i]), cv2.COLOR_RGB2BGR)
        if ep.collision[i]:
            img = img.copy()
            cv2.rectangle(img, (0, 0), (tile - 1, tile - 1), (0, 0, 255), 2)
        sheet[y : y + tile, x : x + tile] = img
        text = f"{i} {float(ep.timestamps[i]) - t0:.1f}s"
        cv2.putText(sheet, text, (x + 2, y + tile + 9), cv2.FONT_HERSHEY_PLAIN, 0.7, (230,) * 3)
    out = Path(out_png)
    if not cv2.imwrite(str(out), sheet):
        raise UserError(f"{out}: cannot write the image (does the directory exist?)")
    return out
