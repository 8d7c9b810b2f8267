"""The OpenCV camera: a V4L2 device, a GStreamer pipeline (Jetson CSI) or a video file.

A capture thread reads frames as fast as the source delivers them and keeps only the newest,
because a control loop fed from OpenCV's internal buffer would steer on frames that are
several periods old. Each frame is stamped with the injected clock the moment read() returns:
that stamp is what the loop compares against its age limit (docs/safety.md: older than 150 ms →
neutral, camera lost → e-stop), so it must be measured, never computed from a frame rate.

A video file is paced at its own frame rate on the same clock, so a recorded drive replays
like a live camera (frames get skipped when the loop is slower, never queued). At its end it
restarts (camera.loop_video) or stalls like a dying camera: stale, then lost.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from carrt.clock import WallClock
from carrt.config import CameraConfig
from carrt.errors import UserError
from carrt.frame_lock import NewFrameSignal
from carrt.interfaces import CameraFrame, Clock
from carrt.model_contract import IMAGE_SHAPE

# Pause between retries after a failed read on a live device, so a dead camera does not spin
# a core; it is reported lost by the staleness rule meanwhile.
_FAIL_BACKOFF_S = 0.01
# Slice for interruptible waits (video pacing), so stop() never waits a whole frame period.
_WAIT_SLICE_S = 0.05
_JOIN_TIMEOUT_S = 2.0


@dataclass(frozen=True)
class CameraSource:
    """What config.source names: kind is "device", "gstreamer" or "file"."""

    kind: str
    target: int | str  # device index, device path, pipeline string or file path
    api: int  # cv2.CAP_* backend

    def describe(self) -> str:
        if self.kind == "device":
            name = f"/dev/video{self.target}" if isinstance(self.target, int) else self.target
            return f"V4L2 device {name}"
        if self.kind == "gstreamer":
            return "GStreamer pipeline"
        return f"video file {self.target}"


def gstreamer_available() -> bool:
    for line in cv2.getBuildInformation().splitlines():
        if line.strip().startswith("GStreamer:"):
            return "YES" in line.split(":", 1)[1]
    return False


# A laptop has no camera at /dev/video0: the first `carrt drive` there should name the way on.
NO_CAMERA_HINT = "no camera here? --sim drives the built-in simulator, --camera FILE a video"


def parse_source(source: str) -> CameraSource:
    """Classify config.source; raise UserError when it cannot name anything usable."""
    text = source.strip()
    device_api = cv2.CAP_V4L2 if sys.platform.startswith("linux") else cv2.CAP_ANY
    if text.isdigit():
        return CameraSource("device", int(text), device_api)
    if text.startswith("/dev/video"):
        if not os.path.exists(text):
            raise UserError(f"camera source {text}: no such file or device ({NO_CAMERA_HINT})")
        return CameraSource("device", text, device_api)
    if "!" in text:
        if "appsink" not in text:
            raise UserError(
                f"camera source {text!r}: looks like a GStreamer pipeline but has no appsink "
                "(end it with '! appsink drop=true max-buffers=1')"
            )
        if not gstreamer_available():
            raise UserError(
                "camera source is a GStreamer pipeline, but this OpenCV was built without "
                "GStreamer (the PyPI opencv wheels never have it; on a Jetson use the "
                "system OpenCV from JetPack, or give a V4L2 device or a video file)"
            )
        return CameraSource("gstreamer", text, cv2.CAP_GSTREAMER)
    if not Path(text).is_file():
        raise UserError(f"camera source {text}: no such file or device")
    return CameraSource("file", text, cv2.CAP_ANY)


def _to_rgb(frame: np.ndarray) -> np.ndarray:
    if frame.ndim == 2:
        return cv2.cvtColor(frame, cv2.COLOR_GRAY2RGB)
    if frame.shape[2] == 4:
        return cv2.cvtColor(frame, cv2.COLOR_BGRA2RGB)
    return cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)


@contextlib.contextmanager
def _quiet_opencv():
    """OpenCV logs its own multi-line warnings when an open fails; our UserError says it once."""
    log = getattr(getattr(cv2, "utils", None), "logging", None)
    if log is None:
        yield
        return
    level = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_ERROR)
    try:
        yield
    finally:
        log.setLogLevel(level)


def preprocess(image: np.ndarray, config: CameraConfig) -> np.ndarray:
    """Crop by the config's fractions and shrink to the policy's (96, 96, 3) uint8 RGB.

    Runs on the loop thread for the frames actually used, so the capture thread never pays
    for frames that get dropped. INTER_AREA because it averages instead of aliasing when
    shrinking a full camera frame ~7x.
    """
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 image, got {image.shape} {image.dtype}")
    h, w = image.shape[:2]
    top, bottom = round(h * config.crop_top), h - round(h * config.crop_bottom)
    left, right = round(w * config.crop_left), w - round(w * config.crop_right)
    if bottom - top < 1 or right - left < 1:
        raise ValueError(f"camera crop leaves no image of a {w}x{h} frame")
    cropped = image[top:bottom, left:right]
    out = cv2.resize(cropped, (IMAGE_SHAPE[1], IMAGE_SHAPE[0]), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(out, dtype=np.uint8)


def frame_age(frame: CameraFrame, now: float) -> float:
    """Seconds since the frame was captured, on the same clock that stamped it."""
    return now - frame.captured_at


Opener = Callable[[int | str, int], Any]


class OpenCVCamera:
    """The Camera protocol over cv2.VideoCapture, with a capture thread.

    `opener(target, api)` builds the capture object (cv2.VideoCapture by default); a test can
    pass a stand-in that stalls or fails on demand, which no real device does reliably.
    """

    def __init__(
        self,
        config: CameraConfig,
        clock: Clock | None = None,
        *,
        opener: Opener = cv2.VideoCapture,
    ) -> None:
        self.config = config
        self._clock: Clock = clock or WallClock()
        self._opener = opener
        self.source: CameraSource | None = None  # parsed at start(), where errors belong
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._latest: CameraFrame | None = None
        self._started_at: float | None = None
        self._dead: str | None = None  # why the source ended for good (set by the thread)
        self._ended: str | None = None  # a video file ran out: lost once its last frame is stale
        self._fail_since: float | None = None
        self._seq = 0  # survives stop/start, so seq never goes backwards
        self._new_frame = NewFrameSignal()
        self.read_failures = 0
        self.restarts = 0
        self.file_fps: float | None = None
        self.info = ""

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        if self._thread is not None:
            return
        self.source = src = parse_source(self.config.source)
        cap = self._open(src)
        self._describe(cap, src)
        # A fresh event per run: a thread from an earlier run still stuck in a driver read
        # must not be revived by this start.
        self._stop = stop = threading.Event()
        self._dead = self._ended = None
        self._started_at = self._clock.now()
        self._thread = threading.Thread(
            target=self._run, args=(cap, src, stop), name="carrt-camera", daemon=True
        )
        self._thread.start()

    def stop(self) -> None:
        thread, self._thread = self._thread, None
        if thread is None:
            return
        self._stop.set()
        self._dead = "camera stopped"
        # A V4L2 read can block for seconds on a dying device; the thread is a daemon, so a
        # stuck read cannot keep the process alive, and it releases the capture itself.
        thread.join(_JOIN_TIMEOUT_S)

    def __enter__(self) -> OpenCVCamera:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------------ Camera protocol
    def latest(self) -> CameraFrame | None:
        return self._latest

    def wait_newer(self, seq: int, until: float) -> None:
        self._new_frame.wait_newer(seq, until - self._clock.now())

    @property
    def lost(self) -> bool:
        return self.lost_reason is not None

    @property
    def lost_reason(self) -> str | None:
        """Why the camera counts as lost right now, for the loop's e-stop message; else None."""
        if self._dead is not None:
            return self._dead
        if self._started_at is None:
            return "camera not started"
        now = self._clock.now()
        frame = self._latest
        last = frame.captured_at if frame is not None else self._started_at
        silent = now - last
        if silent <= self.config.lost_after_s:
            return None
        if self._ended is not None:
            return f"{self._ended}: no new frame for {silent:.2f} s"
        if self._fail_since is not None:
            return f"reads failing for {now - self._fail_since:.2f} s ({self.read_failures} failed)"
        if frame is None:
            return f"no frame {silent:.2f} s after start"
        return f"no new frame for {silent:.2f} s"

    @property
    def running(self) -> bool:
        """The capture thread is alive (False once a file has ended, or after stop())."""
        thread = self._thread
        return thread is not None and thread.is_alive()

    @property
    def frames_captured(self) -> int:
        frame = self._latest
        return 0 if frame is None else frame.seq + 1

    # ------------------------------------------------------------------ internals
    def _open(self, src: CameraSource) -> Any:
        with _quiet_opencv():
            cap = self._opener(src.target, src.api)
        if not cap.isOpened():
            cap.release()
            if src.kind == "device":
                raise UserError(
                    f"camera source {self.config.source}: cannot open {src.describe()} "
                    "(not connected, or in use by another program? see `ls /dev/video*`; "
                    f"{NO_CAMERA_HINT})"
                )
            if src.kind == "gstreamer":
                raise UserError(
                    "camera source: the GStreamer pipeline did not start (test it with "
                    "gst-launch-1.0, replacing appsink by fakesink)"
                )
            raise UserError(
                f"camera source {self.config.source}: cannot decode this video file "
                "(not a video, or a codec this OpenCV build lacks)"
            )
        if src.kind == "device":
            cfg = self.config
            # Keep the driver's queue short: the thread drains it anyway, this bounds latency
            # if the loop and thread are briefly starved.
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
            if cfg.width:
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, cfg.width)
            if cfg.height:
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, cfg.height)
            if cfg.fps:
                cap.set(cv2.CAP_PROP_FPS, cfg.fps)
        if src.kind == "file":
            fps = cap.get(cv2.CAP_PROP_FPS)
            # Some containers do not say; fall back to the configured camera rate.
            self.file_fps = fps if fps and np.isfinite(fps) and 0 < fps <= 1000 else self.config.fps
        return cap

    def _describe(self, cap: Any, src: CameraSource) -> None:
        width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH) or 0)
        height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT) or 0)
        fps = self.file_fps if self.file_fps is not None else cap.get(cv2.CAP_PROP_FPS)
        size = f"{width}x{height}" if width and height else "size unknown"
        rate = f" @ {fps:g} fps" if fps else ""
        self.info = f"{src.describe()}, {size}{rate}"

    def _wait_until(self, deadline: float, stop: threading.Event) -> None:
        """Pace on the injected clock in short slices, so stop() is honoured promptly."""
        while not stop.is_set():
            now = self._clock.now()
            if now >= deadline:
                return
            self._clock.sleep_until(min(deadline, now + _WAIT_SLICE_S))

    def _run(self, cap: Any, src: CameraSource, stop: threading.Event) -> None:
        is_file = src.kind == "file"
        period = 1.0 / self.file_fps if is_file and self.file_fps else 0.0
        deadline = self._clock.now()
        try:
            while not stop.is_set():
                if is_file:
                    self._wait_until(deadline, stop)
                    if stop.is_set():
                        break
                ok, frame = cap.read()
                captured_at = self._clock.now()
                if not ok or frame is None:
                    if is_file:
                        cap = self._end_of_file(cap, src)
                        if cap is None:
                            break
                        continue
                    self.read_failures += 1
                    if self._fail_since is None:
                        self._fail_since = captured_at
                    time.sleep(_FAIL_BACKOFF_S)
                    continue
                self._fail_since = None
                image = _to_rgb(frame)
                self._latest = CameraFrame(image=image, captured_at=captured_at, seq=self._seq)
                self._new_frame.announce(self._seq)
                self._seq += 1
                if is_file:
                    # No catch-up burst after a stall: a late frame resets the schedule.
                    deadline = max(deadline + period, captured_at)
        except Exception as exc:  # a driver error must become "lost", never a silent thread
            if not stop.is_set():
                self._dead = f"capture thread failed: {type(exc).__name__}: {exc}"
        finally:
            if cap is not None:
                cap.release()

    def _end_of_file(self, cap: Any, src: CameraSource) -> Any:
        """At the end of a video: reopen it when looping, else stop delivering frames.

        A file that ends behaves like a camera that stalls: its last frame ages past
        max_age_s (the loop goes neutral), then past lost_after_s (lost, e-stop), so a short
        recording is also the stalled-camera fault injection.
        """
        cap.release()
        if not self.config.loop_video:
            self._ended = f"end of video file {src.target}"
            return None
        with _quiet_opencv():
            cap = self._opener(src.target, src.api)
        ok = cap.isOpened()
        if ok and self.restarts > 0 and self.frames_captured == 0:
            ok = False  # reopened but never yields a frame: would spin forever
        if not ok:
            cap.release()
            self._dead = f"video file {src.target} could not be restarted"
            return None
        self.restarts += 1
        return cap
