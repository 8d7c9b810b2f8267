"""The OpenCV camera against real video files (MJPG .avi) and a stand-in capture that can
stall or fail on demand: ordering, capture timestamps, pacing, loss, crop and colour order."""

from __future__ import annotations

import itertools
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from carrt.camera import OpenCVCamera, frame_age, gstreamer_available, parse_source, preprocess
from carrt.config import CameraConfig
from carrt.errors import UserError
from carrt.interfaces import Camera, CameraFrame

W, H = 64, 48


def level(i: int) -> int:
    """Grey level that encodes frame index i (JPEG keeps flat grey to within a few steps)."""
    return 10 + 20 * i


def index_of(image: np.ndarray) -> int:
    return round((float(image.mean()) - 10) / 20)


def write_video(path: Path, frames: list[np.ndarray], fps: float) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (W, H))
    assert writer.isOpened()
    for frame in frames:
        writer.write(frame)
    writer.release()
    return path


def numbered_video(path: Path, n: int, fps: float) -> Path:
    return write_video(path, [np.full((H, W, 3), level(i), np.uint8) for i in range(n)], fps)


def wait_for(predicate, timeout_s: float = 3.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.002)
    return predicate()


def collect(camera: OpenCVCamera, until, timeout_s: float = 3.0) -> list[CameraFrame]:
    """Poll latest() like a fast loop would; return each distinct frame seen, in order."""
    seen: list[CameraFrame] = []
    end = time.monotonic() + timeout_s
    while time.monotonic() < end and not until(seen):
        frame = camera.latest()
        if frame is not None and (not seen or frame is not seen[-1]):
            seen.append(frame)
        time.sleep(0.001)
    return seen


class JumpClock:
    """A simulated clock: sleeping jumps time forward instead of waiting."""

    def __init__(self) -> None:
        self._t = 100.0
        self._lock = threading.Lock()

    def now(self) -> float:
        with self._lock:
            return self._t

    def sleep_until(self, deadline: float) -> None:
        with self._lock:
            self._t = max(self._t, deadline)
        time.sleep(0.0005)  # let the test thread run


class FakeCapture:
    """Stands in for cv2.VideoCapture: a device that can stall, fail or never open."""

    def __init__(self, *, opened: bool = True, fail: bool = False) -> None:
        self.opened, self.fail = opened, fail
        self.stalled = threading.Event()
        self.released = threading.Event()
        self.props: dict[int, float] = {}
        self.reads = 0

    def __call__(self, target, api):  # the opener
        return self

    def isOpened(self) -> bool:  # cv2's spelling
        return self.opened

    def set(self, prop: int, value: float) -> bool:
        self.props[prop] = value
        return True

    def get(self, prop: int) -> float:
        return self.props.get(prop, 0.0)

    def read(self):
        while self.stalled.is_set() and not self.released.is_set():
            time.sleep(0.002)
        time.sleep(0.005)  # ~200 fps
        self.reads += 1
        if self.fail:
            return False, None
        return True, np.full((H, W, 3), 7, np.uint8)

    def release(self) -> None:
        self.released.set()


# ----------------------------------------------------------------------------- sources
def test_parse_source_kinds(tmp_path):
    dev = parse_source("0")
    assert dev.kind == "device" and dev.target == 0
    video = numbered_video(tmp_path / "v.avi", 2, 10)
    assert parse_source(str(video)).kind == "file"
    with pytest.raises(UserError, match="no such file or device"):
        parse_source("/dev/video97")
    with pytest.raises(UserError, match="no appsink"):
        parse_source("v4l2src ! videoconvert ! fakesink")


@pytest.mark.skipif(gstreamer_available(), reason="this OpenCV has GStreamer")
def test_gstreamer_pipeline_without_gstreamer_says_so():
    with pytest.raises(UserError) as err:
        OpenCVCamera(CameraConfig(source="nvarguscamerasrc ! nvvidconv ! appsink")).start()
    assert "built without GStreamer" in str(err.value)
    assert "\n" not in str(err.value)


def test_missing_file_is_a_user_error(tmp_path):
    camera = OpenCVCamera(CameraConfig(source=str(tmp_path / "nope.avi")))
    with pytest.raises(UserError, match=r"camera source .*nope\.avi: no such file or device"):
        camera.start()


def test_not_a_video_is_a_user_error(tmp_path):
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"this is not a video" * 100)
    with pytest.raises(UserError, match="cannot decode"):
        OpenCVCamera(CameraConfig(source=str(junk))).start()


def test_absent_device_index_fails_fast():
    camera = OpenCVCamera(CameraConfig(source="57"))
    start = time.monotonic()
    try:
        camera.start()
    except UserError as exc:
        assert "cannot open" in str(exc) and "\n" not in str(exc)
    else:  # some platform opened *something*: then it must report lost, not hang
        assert wait_for(lambda: camera.lost, 3.0)
    finally:
        camera.stop()
    assert time.monotonic() - start < 3.5


# ----------------------------------------------------------------------------- video files
def test_frames_in_order_with_paced_capture_timestamps(tmp_path):
    fps, n = 20.0, 8
    video = numbered_video(tmp_path / "v.avi", n, fps)
    camera = OpenCVCamera(CameraConfig(source=str(video)))
    assert isinstance(camera, Camera)
    camera.start()
    try:
        seen = collect(camera, lambda s: not camera.running, timeout_s=3.0)
    finally:
        camera.stop()
    assert [f.seq for f in seen] == sorted({f.seq for f in seen})
    assert [index_of(f.image) for f in seen] == [f.seq for f in seen]
    assert len(seen) >= n - 2  # a 2 ms poll sees nearly every 50 ms frame
    stamps = np.array([f.captured_at for f in seen])
    assert np.all(np.diff(stamps) > 0)
    per_frame = (stamps[-1] - stamps[0]) / (seen[-1].seq - seen[0].seq)
    assert 0.8 / fps < per_frame < 1.5 / fps  # paced at the file's rate, not decoded flat out
    assert seen[-1].image.shape == (H, W, 3) and seen[-1].image.dtype == np.uint8


def test_simulated_clock_stamps_frames_at_the_file_rate(tmp_path):
    fps = 25.0
    video = numbered_video(tmp_path / "v.avi", 6, fps)
    clock = JumpClock()
    camera = OpenCVCamera(CameraConfig(source=str(video)), clock=clock)
    t0 = clock.now()
    camera.start()
    try:
        # on the jumping clock the file can be over before this thread first looks (a loaded
        # 3.10 run saw nothing): the last frame stays latest(), so look at least once
        seen = collect(camera, lambda s: s and not camera.running)
    finally:
        camera.stop()
    assert seen
    for frame in seen:  # decoding takes no simulated time, so the stamp is the schedule
        assert frame.captured_at == pytest.approx(t0 + frame.seq / fps, abs=1e-9)
        assert frame_age(frame, clock.now()) >= 0


def test_end_of_file_is_a_stall_then_lost(tmp_path):
    fps = 50.0
    video = numbered_video(tmp_path / "v.avi", 3, fps)
    camera = OpenCVCamera(CameraConfig(source=str(video), lost_after_s=0.3))
    camera.start()
    try:
        assert wait_for(lambda: not camera.running)
        last = camera.latest()
        assert last.seq == 2 and camera.frames_captured == 3
        # like a stalled camera: the last frame ages (the loop goes neutral) before it is lost
        if time.monotonic() - last.captured_at < 0.2:
            assert not camera.lost
        assert wait_for(lambda: camera.lost, 2.0)
        assert time.monotonic() - last.captured_at >= 0.3
        assert camera.lost_reason.startswith(f"end of video file {video}: no new frame for")
    finally:
        camera.stop()


def test_loop_video_keeps_going_and_latest_never_goes_back(tmp_path):
    n = 4
    video = numbered_video(tmp_path / "v.avi", n, 100.0)
    camera = OpenCVCamera(CameraConfig(source=str(video), loop_video=True))
    camera.start()
    try:
        seen = collect(camera, lambda s: bool(s) and s[-1].seq >= 3 * n)
        assert not camera.lost
    finally:
        camera.stop()
    assert seen[-1].seq >= 3 * n and camera.restarts >= 2
    assert all(b.seq > a.seq and b.captured_at > a.captured_at for a, b in itertools.pairwise(seen))
    assert all(index_of(f.image) == f.seq % n for f in seen)


def test_colour_order_is_rgb_through_camera_and_preprocess(tmp_path):
    bgr = np.zeros((H, W, 3), np.uint8)
    bgr[:, : W // 2] = (0, 0, 255)  # red, in OpenCV's BGR
    bgr[:, W // 2 :] = (255, 0, 0)  # blue
    video = write_video(tmp_path / "rb.avi", [bgr] * 3, 30.0)
    camera = OpenCVCamera(CameraConfig(source=str(video)))
    camera.start()
    try:
        assert wait_for(lambda: camera.latest() is not None)
        frame = camera.latest()
    finally:
        camera.stop()
    small = preprocess(frame.image, camera.config)
    assert small.shape == (96, 96, 3) and small.dtype == np.uint8
    assert np.abs(small[48, 10].astype(int) - (255, 0, 0)).max() < 25
    assert np.abs(small[48, 85].astype(int) - (0, 0, 255)).max() < 25


def test_stop_joins_the_thread(tmp_path):
    video = numbered_video(tmp_path / "v.avi", 5, 10.0)
    camera = OpenCVCamera(CameraConfig(source=str(video), loop_video=True))
    camera.start()
    thread = camera._thread
    assert wait_for(lambda: camera.latest() is not None)
    start = time.monotonic()
    camera.stop()
    assert time.monotonic() - start < 0.5  # not a whole 100 ms period per slice, no hang
    assert not thread.is_alive()
    assert camera.lost and camera.lost_reason == "camera stopped"
    camera.stop()  # idempotent
    last = camera.latest().seq
    camera.start()  # a restart continues the sequence: seq never goes backwards
    try:
        assert wait_for(lambda: camera.latest().seq > last and not camera.lost)
    finally:
        camera.stop()


# ----------------------------------------------------------------------------- live devices
def test_device_settings_requested_only_when_nonzero():
    fake = FakeCapture()
    camera = OpenCVCamera(CameraConfig(source="0", width=640, height=0, fps=60.0), opener=fake)
    camera.start()
    camera.stop()
    assert fake.props[cv2.CAP_PROP_FRAME_WIDTH] == 640
    assert cv2.CAP_PROP_FRAME_HEIGHT not in fake.props
    assert fake.props[cv2.CAP_PROP_FPS] == 60.0


def test_device_that_does_not_open_is_a_user_error():
    camera = OpenCVCamera(CameraConfig(source="0"), opener=FakeCapture(opened=False))
    with pytest.raises(UserError, match="cannot open V4L2 device /dev/video0"):
        camera.start()


def test_stalled_device_is_lost_then_recovers():
    fake = FakeCapture()
    camera = OpenCVCamera(CameraConfig(source="0", lost_after_s=0.15), opener=fake)
    camera.start()
    try:
        assert wait_for(lambda: camera.latest() is not None)
        assert not camera.lost
        fake.stalled.set()
        assert wait_for(lambda: camera.lost, 1.0)
        assert camera.lost_reason.startswith("no new frame for")
        fake.stalled.clear()
        assert wait_for(lambda: not camera.lost, 1.0)
    finally:
        camera.stop()


def test_device_that_never_delivers_is_lost():
    fake = FakeCapture()
    fake.stalled.set()
    camera = OpenCVCamera(CameraConfig(source="0", lost_after_s=0.1), opener=fake)
    camera.start()
    try:
        assert camera.latest() is None and not camera.lost
        assert wait_for(lambda: camera.lost, 1.0)
        assert "after start" in camera.lost_reason
    finally:
        fake.stalled.clear()  # a read blocked in a driver would hold stop() up to its timeout
        camera.stop()


def test_failing_reads_are_lost_and_counted():
    fake = FakeCapture(fail=True)
    camera = OpenCVCamera(CameraConfig(source="0", lost_after_s=0.1), opener=fake)
    camera.start()
    try:
        assert wait_for(lambda: camera.lost, 1.0)
        assert camera.lost_reason.startswith("reads failing")
        assert camera.read_failures > 1
    finally:
        camera.stop()


# ----------------------------------------------------------------------------- preprocess
def test_preprocess_crops_by_fractions_then_resizes():
    image = np.zeros((200, 100, 3), np.uint8)
    image[:50] = (0, 255, 0)  # top quarter green: the sky, cropped away
    image[50:, :50] = (255, 0, 0)
    image[50:, 50:] = (0, 0, 255)
    image[:, 90:] = (255, 255, 255)  # right tenth white: cropped away
    config = CameraConfig(crop_top=0.25, crop_right=0.1)
    out = preprocess(image, config)
    assert out.shape == (96, 96, 3) and out.dtype == np.uint8 and out.flags.c_contiguous
    assert not (out == (0, 255, 0)).all(axis=2).any()
    assert not (out == (255, 255, 255)).all(axis=2).any()
    assert (out[:, :50] == (255, 0, 0)).all()  # 50 of 90 columns are red: 53 of 96
    assert (out[:, 56:] == (0, 0, 255)).all()


def test_preprocess_without_crop_is_a_plain_area_resize():
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (192, 288, 3), dtype=np.uint8)
    out = preprocess(image, CameraConfig())
    expected = image.reshape(96, 2, 96, 3, 3).mean(axis=(1, 3))
    assert np.abs(out.astype(float) - expected).max() <= 1.0


def test_preprocess_refuses_non_rgb_uint8():
    with pytest.raises(ValueError):
        preprocess(np.zeros((10, 10), np.uint8), CameraConfig())
    with pytest.raises(ValueError):
        preprocess(np.zeros((10, 10, 3), np.float32), CameraConfig())


def test_no_camera_on_this_machine_names_the_simulator():
    with pytest.raises(UserError, match=r"/dev/video97: no such file .*--sim drives the built-in"):
        parse_source("/dev/video97")
    camera = OpenCVCamera(CameraConfig(source="0"), opener=FakeCapture(opened=False))
    with pytest.raises(UserError, match=r"--sim drives the built-in simulator"):
        camera.start()
