"""The car's camera in the simulator, behind the same Camera interface as the OpenCV one.

In real time it is a capture thread at the camera's frame rate, so the loop meets frame ages
and phases like a real camera's. On the simulated clock there is no thread to race: a frame is
rendered when the loop asks for one and the last frame is older than one frame period, with
that simulated moment as its capture time.
"""

from __future__ import annotations

import threading
from typing import Any

from carrt.interfaces import CameraFrame


class SimCamera:
    def __init__(self, plant: Any, renderer: Any, clock: Any, *, fps: float = 30.0,
                 realtime: bool = True) -> None:  # fmt: skip
        self.plant = plant
        self.renderer = renderer
        self.clock = clock
        self.period = 1.0 / fps
        self.realtime = realtime
        self._latest: CameraFrame | None = None
        self._seq = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.stalled = False  # a test hook and a demo: the camera stops delivering frames

    def _capture(self) -> None:
        if self.stalled:
            return
        x, y, yaw = self.plant.pose()
        image = self.renderer.render(x, y, yaw)
        self._latest = CameraFrame(image=image, captured_at=self.clock.now(), seq=self._seq)
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

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None

    def latest(self) -> CameraFrame | None:
        if not self.realtime:
            last = self._latest
            if last is None or self.clock.now() - last.captured_at >= self.period - 1e-9:
                self._capture()
        return self._latest

    @property
    def lost(self) -> bool:
        if self._latest is None:
            return False
        return self.stalled and self.clock.now() - self._latest.captured_at > 1.0
