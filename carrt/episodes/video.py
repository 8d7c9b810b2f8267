"""Episodes as one video a browser plays: H.264 through PyAV, with what the car did drawn beside.

Why H.264 and PyAV: the videos are for people, who open them in a browser or on GitHub, and
those play H.264 in an mp4 (yuv420p, moov atom first), not OpenCV's mp4v. PyAV is the
well-kept binding to FFmpeg and its wheels carry libx264, so no system FFmpeg is needed.

Each frame is the camera image enlarged, and beside it a panel: episode, step, time, mode
(coloured), speed and flags; bars for steering and throttle as the person commanded (a*), as
the policy planned (first step) and as executed; and the policy's plan μ over its H steps, the
two actions as lines. Several episodes go into one file, in order (a run of the demo).
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np

from carrt.episodes.reader import Episode
from carrt.errors import UserError
from carrt.interfaces import Mode
from carrt.model_contract import IMAGE_SHAPE

PANEL_W = 272  # the side panel; with a 384-px camera image the frame is 656×384 (even: yuv420p)
MODE_COLOURS = {  # RGB
    int(Mode.DISARMED): (170, 170, 170),
    int(Mode.MANUAL): (90, 210, 110),
    int(Mode.AUTO): (80, 160, 250),
    int(Mode.ESTOP): (240, 70, 70),
}
ACTIONS = (("a* (person)", "human_action"), ("policy", "policy_action"),
           ("executed", "executed_action"))  # fmt: skip
FONT = cv2.FONT_HERSHEY_SIMPLEX


def _text(img: np.ndarray, text: str, xy: tuple[int, int], colour=(230, 230, 230), size=0.45):
    cv2.putText(img, text, xy, FONT, size, colour, 1, cv2.LINE_AA)


def _bar(img: np.ndarray, x: int, y: int, w: int, value: float, colour) -> None:
    """A bar for a value in [-1, 1] from a marked zero; NaN (no such action) draws the frame."""
    h = 9
    cv2.rectangle(img, (x, y), (x + w, y + h), (90, 90, 100), 1)
    mid = x + w // 2
    cv2.line(img, (mid, y - 2), (mid, y + h + 2), (200, 200, 200), 1)
    if not np.isfinite(value):
        return
    end = round(mid + float(np.clip(value, -1.0, 1.0)) * w / 2)
    cv2.rectangle(img, (min(mid, end), y + 2), (max(mid, end), y + h - 2), colour, -1)


def _plan(img: np.ndarray, x: int, y: int, w: int, h: int, mu: np.ndarray) -> None:
    """μ over the plan's H steps: steering and throttle as two lines on [-1, 1]."""
    cv2.rectangle(img, (x, y), (x + w, y + h), (90, 90, 100), 1)
    cv2.line(img, (x, y + h // 2), (x + w, y + h // 2), (70, 70, 80), 1)
    if mu is None or mu.size == 0 or not np.isfinite(mu).all():
        _text(img, "no plan", (x + 6, y + h // 2 - 4), (150, 150, 150), 0.4)
        return
    steps = np.linspace(x + 4, x + w - 4, len(mu))
    for k, colour in ((0, (250, 200, 80)), (1, (120, 220, 250))):
        ys = y + h / 2 - np.clip(mu[:, k], -1, 1) * (h / 2 - 3)
        points = np.stack([steps, ys], axis=1).round().astype(np.int32)
        cv2.polylines(img, [points], False, colour, 2, cv2.LINE_AA)


def compose(ep: Episode, i: int, scale: int = 4) -> np.ndarray:
    """Frame i of `ep` enlarged, with its panel: an RGB image (96·scale) × (96·scale + PANEL_W)."""
    rec = ep.steps[i]
    size = IMAGE_SHAPE[0] * scale
    camera = cv2.resize(np.asarray(ep.frames[i]), (size, size), interpolation=cv2.INTER_NEAREST)
    if ep.collision[i]:
        cv2.rectangle(camera, (0, 0), (size - 1, size - 1), (255, 40, 40), max(2, scale))
    panel = np.full((size, PANEL_W, 3), 24, dtype=np.uint8)
    mode = int(rec["mode"])
    t = float(ep.timestamps[i] - ep.timestamps[0])
    _text(panel, ep.name, (8, 18), (170, 170, 180), 0.42)
    _text(panel, f"step {int(rec['index'])}   t {t:6.1f} s", (8, 38))
    name = Mode(mode).name if mode in MODE_COLOURS else str(mode)
    _text(panel, name, (8, 66), MODE_COLOURS.get(mode, (255, 255, 255)), 0.7)
    _text(panel, f"{float(rec['speed_mps']):4.2f} m/s", (150, 66), size=0.6)
    flags = [f for f in ("override", "noise", "lap", "collision") if rec[f]]
    if ep.collision[i] and "collision" not in flags:
        flags.append("collision label")
    _text(panel, " ".join(flags) or "-", (8, 88), (250, 210, 90), 0.42)
    y = 114
    for title, k in (("steering  (left -1 .. +1 right)", 0), ("throttle  (brake -1 .. +1)", 1)):
        _text(panel, title, (8, y), (170, 170, 180), 0.4)
        for row, (label, field) in enumerate(ACTIONS):
            value = float(rec[field][k])
            yy = y + 10 + row * 16
            _text(panel, label, (8, yy + 9), size=0.38)
            _bar(panel, 96, yy, 120, value, (120, 190, 250))
            _text(panel, "-" if not np.isfinite(value) else f"{value:+.2f}", (222, yy + 9),
                  size=0.38)  # fmt: skip
        y += 66
    _text(panel, "plan mu over H:", (8, y + 6), (170, 170, 180), 0.4)
    _text(panel, "steer", (150, y + 6), (250, 200, 80), 0.4)
    _text(panel, "throttle", (196, y + 6), (120, 220, 250), 0.4)
    mu = ep.steps["plan_mu"][i] if "plan_mu" in ep.steps.dtype.names else None
    _plan(panel, 8, y + 14, PANEL_W - 16, size - y - 24, None if mu is None else np.asarray(mu))
    return np.concatenate([camera, panel], axis=1)


def frames_of(episodes: Sequence[Episode], scale: int) -> Iterator[np.ndarray]:
    for ep in episodes:
        for i in range(ep.n):
            yield compose(ep, i, scale)


def write_h264(frames: Iterator[np.ndarray], out: Path, fps: float) -> int:
    """Encode RGB frames to an H.264 mp4 a browser plays (yuv420p, faststart); returns frames."""
    import av  # a missing PyAV becomes carrt.deps' one-line install hint

    if "libx264" not in av.codecs_available:
        raise UserError("this PyAV has no libx264 encoder: install PyAV's wheel (pip install av)")
    n = 0
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}.mp4")
    try:
        with av.open(str(tmp), mode="w", options={"movflags": "+faststart"}) as container:
            stream = None
            for image in frames:
                if stream is None:
                    stream = container.add_stream("libx264", rate=Fraction(fps).limit_denominator())
                    stream.height, stream.width = image.shape[:2]
                    stream.pix_fmt = "yuv420p"  # what browsers decode
                    stream.options = {"crf": "20", "preset": "veryfast", "profile": "high"}
                for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
                    container.mux(packet)
                n += 1
            if stream is not None:
                for packet in stream.encode():
                    container.mux(packet)
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return n


def render_video(
    episodes: Sequence[Episode], out_path: str | os.PathLike, fps: float = 10, scale: int = 4
) -> Path:
    """All `episodes`, in order, into one video: .mp4 is H.264 (browsers, GitHub), .avi is
    MJPG through OpenCV; other suffixes are refused rather than silently mis-encoded."""
    episodes = [ep for ep in episodes if ep.n > 0]
    if not episodes:
        raise UserError("no frames to render: the episodes are empty")
    if not (np.isfinite(fps) and fps > 0) or scale < 1:
        raise UserError(f"--fps must be > 0 and --scale >= 1, got {fps} and {scale}")
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    suffix = out.suffix.lower()
    if suffix == ".mp4":
        write_h264(frames_of(episodes, scale), out, fps)
    elif suffix == ".avi":
        _write_mjpg(frames_of(episodes, scale), out, fps, scale)
    else:
        raise UserError(f"{out}: video must end in .mp4 (H.264) or .avi (MJPG)")
    return out


def _write_mjpg(frames: Iterator[np.ndarray], out: Path, fps: float, scale: int) -> None:
    size = (IMAGE_SHAPE[1] * scale + PANEL_W, IMAGE_SHAPE[0] * scale)
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*"MJPG"), float(fps), size)
    if not writer.isOpened():
        raise UserError(f"{out}: OpenCV cannot write MJPG video here")
    try:
        for image in frames:
            writer.write(cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    finally:
        writer.release()
