"""Car speed from encoder telemetry, timed by the board's own clock.

Ticks are differenced over a window of board time (mcu_time_ms), not host arrival time, so
USB jitter does not show up as speed noise; the window (about 0.1 s) trades noise against lag
at the quantisation of a real encoder.
"""

from __future__ import annotations

import collections

from firmware_bridge import messages as m


class SpeedEstimator:
    def __init__(self, metres_per_tick: float, window_s: float = 0.1) -> None:
        self.metres_per_tick = metres_per_tick
        self.window_ms = window_s * 1000.0
        self._samples: collections.deque[tuple[int, int]] = collections.deque(maxlen=64)

    def update(self, telemetry: m.Telemetry) -> float:
        """Add a telemetry sample (duplicates are ignored); return the current speed in m/s."""
        sample = (telemetry.mcu_time_ms, telemetry.encoder_ticks)
        if not self._samples or self._samples[-1][0] != sample[0]:
            if self._samples and (sample[0] < self._samples[-1][0] or sample[1] < 0):
                self._samples.clear()  # the board rebooted: its clock and count restarted
            self._samples.append(sample)
        return self.speed_mps

    @property
    def speed_mps(self) -> float:
        if len(self._samples) < 2:
            return 0.0
        t_now, ticks_now = self._samples[-1]
        # The newest sample at least one window old, or the oldest we have.
        reference = next(
            (s for s in reversed(self._samples) if t_now - s[0] >= self.window_ms), self._samples[0]
        )
        t_then, ticks_then = reference
        if t_now == t_then:
            return 0.0
        return (ticks_now - ticks_then) * self.metres_per_tick / ((t_now - t_then) / 1000.0)
