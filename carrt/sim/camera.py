"""The car's camera in the simulator, behind the same Camera interface as the OpenCV one.

It is a free-running camera at its frame rate on either clock, so the loop meets frame ages and
phases like a real camera's: in real time a capture thread, on the simulated clock a listener
that renders at every frame time as the clock passes it. A camera that rendered on demand at
each control tick would hand the policy frames of age 0, which no real camera does: a policy
trained on them drove into obstacles once its frames were 17 ms old (measured: 1 → 8
collisions in 40 s on a held-out placement). `phase_s` offsets the first frame from the start.
"""

from __future__ import annotations

import threading
from typing import Any

from carrt.frame_lock import NewFrameSignal
from carrt.interfaces import CameraFrame


class SimCamera:
    def __init__(self, plant: Any, renderer: Any, clock: Any, *, fps: float = 30.0,
                 realtime: bool = True, phase_s: float = 0.0) -> None:  # fmt: skip
        self.plant = plant
        self.renderer = renderer
        self.clock = clock
        self.period = 1.0 / fps
        self.realtime = realtime
        self.phase_s = phase_s % self.period
        self._latest: CameraFrame | None = None
        self._seq = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.stalled = False  # a test hook and a demo: the camera stops delivering frames
        self._new_frame = NewFrameSignal()
        self._next_frame = 0.0

    def _capture(self) -> None:
        if self.stalled:
            return
        x, y, yaw = self.plant.pose()
        image = self.renderer.render(x, y, yaw)
        self._latest = CameraFrame(image=image, captured_at=self.clock.now(), seq=self._seq)
        self._new_frame.announce(self._seq)
        self._seq += 1

    def _run(self) -> None:
        next_frame = self.clock.now()
        while not self._stop.is_set():
            self._capture()
            next_frame += self.period
            self.clock.sleep_until(next_frame)

    def start(self) -> None:
        if self.realtime and self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="sim-camera", daemon=True)
            self._thread.start()
        elif not self.realtime:
            self._capture()
            self._next_frame = self.clock.now() + (self.phase_s or self.period)
            self.clock.add_listener(self._on_tick)

    def _on_tick(self, now: float, dt: float) -> None:
        """Simulated clock: a frame at every frame time, whatever the loop is doing."""
        if now >= self._next_frame - 1e-9 and not self._stop.is_set():
            self._capture()
            self._next_frame += self.period

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def latest(self) -> CameraFrame | None:
        return self._latest

    def wait_newer(self, seq: int, until: float) -> None:
        """In real time the capture thread announces frames; on the simulated clock waiting
        is advancing the clock, frame time by frame time, so the world moves meanwhile."""
        if self.realtime:
            self._new_frame.wait_newer(seq, until - self.clock.now())
            return
        while not self._has_newer(seq) and self.clock.now() < until - 1e-9:
            coming = not self.stalled and self._next_frame > self.clock.now() + 1e-9
            self.clock.sleep_until(min(until, self._next_frame) if coming else until)

    def _has_newer(self, seq: int) -> bool:
        return self._latest is not None and self._latest.seq > seq

    @property
    def lost(self) -> bool:
        if self._latest is None:
            return False
        return self.stalled and self.clock.now() - self._latest.captured_at > 1.0
