"""Clocks for the control loop: the wall clock on the car, a simulated one for faster runs.

The loop schedules on absolute deadlines (t0 + k·period) from whichever clock it is given, so
a late tick does not push every later tick back, and the same loop runs hours of simulated
driving in minutes when the clock jumps instead of sleeping.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class WallClock:
    """Monotonic seconds; sleeping really waits."""

    def now(self) -> float:
        return time.monotonic()

    def sleep_until(self, deadline: float) -> None:
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return
            # Sleep most of the way, then a short final nap: time.sleep overshoots by ~0.1 ms.
            time.sleep(remaining if remaining < 0.002 else remaining - 0.001)


class SimClock:
    """Simulated seconds: sleep_until advances time in small steps and lets the world move.

    Listeners (the simulated car, the in-process board) are called after every step with the
    new time and the step length, so everything that happens "while the loop sleeps" happens
    at the right simulated moment, only faster.
    """

    def __init__(self, start: float = 0.0, step_s: float = 0.002) -> None:
        self._t = start
        self.step_s = step_s
        self._listeners: list[Callable[[float, float], None]] = []
        self._lock = threading.Lock()

    def now(self) -> float:
        return self._t

    def add_listener(self, listener: Callable[[float, float], None]) -> None:
        self._listeners.append(listener)

    def sleep_until(self, deadline: float) -> None:
        with self._lock:
            while self._t < deadline - 1e-9:
                dt = min(self.step_s, deadline - self._t)
                self._t += dt
                for listener in self._listeners:
                    listener(self._t, dt)

    def advance(self, dt: float) -> None:
        self.sleep_until(self._t + dt)
