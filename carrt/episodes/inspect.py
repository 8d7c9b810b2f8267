"""An episode for the eye: a video with the controls drawn on, and a contact sheet (OpenCV).

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
from carrt.interfaces import Mode

_MODE_COLOURS = {  # BGR
    int(Mode.DISARMED): (160, 160, 160),
    int(Mode.MANUAL): (80, 200, 80),
    int(Mode.AUTO): (230, 160, 40),
    int(Mode.ESTOP): (40, 40, 230),
}


def _require_frames(ep: Episode) -> None:
    if ep.n == 0:
        raise UserError(f"{ep.path} has no frames to render")


def _bar(img: np.ndarray, x: int, y: int, w: int, h: int, value: float, centred: bool) -> None:
    """A horizontal bar for a value in [-1, 1] (centred) or [0, 1]; NaN draws only the frame."""
    cv2.rectangle(img, (x, y), (x + w, y + h), (200, 200, 200), 1)
    if not np.isfinite(value):
        return
    value = float(np.clip(value, -1.0, 1.0))
    if centred:
        mid = x + w // 2
        end = round(mid + value * w / 2)
        cv2.rectangle(img, (min(mid, end), y + 1), (max(mid, end), y + h - 1), (0, 220, 255), -1)
    else:
        end = round(x + max(value, 0.0) * w)
        cv2.rectangle(img, (x, y + 1), (end, y + h - 1), (0, 220, 255), -1)


def annotate(ep: Episode, i: int, scale: int = 4) -> np.ndarray:
    """Frame i, scaled up (BGR), with mode, speed, steering and throttle drawn on it."""
    rec = ep.steps[i]
    img = cv2.cvtColor(np.asarray(ep.frames[i]), cv2.COLOR_RGB2BGR)
    img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    size = img.shape[1]
    font, fs = cv2.FONT_HERSHEY_SIMPLEX, 0.35 * scale / 2
    mode = int(rec["mode"])
    label = Mode(mode).name if mode in _MODE_COLOURS else str(mode)
    flags = [name for name in ("override", "noise", "lap") if rec[name]]
    cv2.rectangle(img, (0, 0), (size, 14 * scale // 2), (0, 0, 0), -1)
    text = f"{label} {float(rec['speed_mps']):.2f} m/s  #{int(rec['index'])} " + " ".join(flags)
    cv2.putText(img, text, (3, 10 * scale // 2), font, fs, _MODE_COLOURS.get(mode, (255,) * 3), 1)
    steer, throttle = (float(v) for v in rec["executed_action"])
    bar_h, pad = 5 * scale // 2, 4
    cv2.rectangle(img, (0, size - 2 * bar_h - 3 * pad), (size, size), (0, 0, 0), -1)
    _bar(img, pad, size - 2 * bar_h - 2 * pad, size - 2 * pad, bar_h, steer, centred=True)
    _bar(img, pad, size - bar_h - pad, size - 2 * pad, bar_h, throttle, centred=False)
    if ep.collision[i]:
        cv2.rectangle(img, (0, 0), (size - 1, size - 1), (0, 0, 255), max(2, scale))
    return img


def render_video(ep: Episode, out_path: str | os.PathLike, fps: float = 10, scale: int = 4) -> Path:
    """mp4 (mp4v) or avi (MJPG); other suffixes are refused rather than silently mis-encoded."""
    _require_frames(ep)
    out = Path(out_path)
    codecs = {".mp4": "mp4v", ".avi": "MJPG"}
    if out.suffix.lower() not in codecs:
        raise UserError(f"{out}: video must end in .mp4 or .avi")
    size = 96 * scale
    writer = cv2.VideoWriter(
        str(out), cv2.VideoWriter_fourcc(*codecs[out.suffix.lower()]), float(fps), (size, size)
    )
    if not writer.isOpened():
        raise UserError(f"{out}: OpenCV cannot write {codecs[out.suffix.lower()]} video here")
    try:
        for i in range(ep.n):
            writer.write(annotate(ep, i, scale))
    finally:
        writer.release()
    return out


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
    tile, caption = 96, 12
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
