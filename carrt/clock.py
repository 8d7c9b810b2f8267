"""Clocks for the control loop: the wall clock on the car, a simulated one for faster runs.

The loop schedules on absolute deadlines (t0 + k·period) from whichever clock it is given, so
a late tick does not push every later tick back, and the same loop runs hours of simulated
driving in minutes when the clock jumps instead of sleeping.
"""

from __future__ import annotations

import threading
import time


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
    """Simulated seconds: sleep_until jumps straight to the deadline."""

    def __init__(self, start: float = 0.0) -> None:
        self._t = start
        self._lock = threading.Lock()

    def now(self) -> float:
        return self._t

    def sleep_until(self, deadline: float) -> None:
        with self._lock:
            self._t = max(self._t, deadline)

    def advance(self, dt: float) -> None:
        with self._lock:
            self._t += dt
