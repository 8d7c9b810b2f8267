"""What the virtual board's outputs drive: the physical side of the car, as seen by the board.

A plant turns the pulses the firmware applies into the encoder count the firmware reads. The
default is a drivetrain alone (ESC → wheel speed with lag → quantised ticks), enough to make
the link's telemetry behave like a real car on a stand. The simulator plugs in a full vehicle
model through the same two-method interface.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol


class Plant(Protocol):
    def step(self, dt_s: float, steer_us: int, throttle_us: int) -> int:
        """Advance by dt_s under these pulses; return the cumulative encoder tick count."""
        ...

    def reset(self) -> None:
        """Put the car back at rest (the board rebooted, or a test starts over)."""
        ...


def pulse_to_unit(
    pulse_us: int, low_us: int, mid_us: int, high_us: int, deadband_us: int = 0
) -> float:
    """What a servo or ESC makes of a pulse: -1 at low, 0 at mid (± deadband), +1 at high."""
    offset = pulse_us - mid_us
    if abs(offset) <= deadband_us:
        return 0.0
    span = high_us - mid_us if offset > 0 else mid_us - low_us
    return max(-1.0, min(1.0, offset / span)) if span else 0.0


@dataclass
class WheelPlant:
    """A wheel driven by an ESC: first-order speed lag, a neutral deadband, a real encoder.

    The encoder count is the floor of distance × ticks per metre, so at crawl speed ticks come
    rarely and irregularly, as on a real car (which the stall check has to live with).
    """

    top_speed_mps: float = 2.5
    time_constant_s: float = 0.3
    ticks_per_metre: float = 200.0
    esc_reverse_us: int = 1000
    esc_neutral_us: int = 1500
    esc_forward_us: int = 2000
    esc_deadband_us: int = 20
    stiction_mps: float = 0.05  # below this, with no drive, friction holds the car still
    blocked: bool = False  # wheels held (against a wall, or a test of the stall check)
    speed_mps: float = 0.0
    distance_m: float = 0.0

    def throttle_fraction(self, throttle_us: int) -> float:
        return pulse_to_unit(
            throttle_us,
            self.esc_reverse_us,
            self.esc_neutral_us,
            self.esc_forward_us,
            self.esc_deadband_us,
        )

    def step(self, dt_s: float, steer_us: int, throttle_us: int) -> int:
        del steer_us  # a wheel on a stand does not care where the front wheels point
        target = 0.0 if self.blocked else self.throttle_fraction(throttle_us) * self.top_speed_mps
        alpha = 1.0 - math.exp(-max(dt_s, 0.0) / self.time_constant_s)
        self.speed_mps += (target - self.speed_mps) * alpha
        if self.blocked or (target == 0.0 and abs(self.speed_mps) < self.stiction_mps):
            self.speed_mps = 0.0
        self.distance_m += self.speed_mps * dt_s
        return self.ticks

    @property
    def ticks(self) -> int:
        return math.floor(self.distance_m * self.ticks_per_metre)

    def reset(self) -> None:
        self.speed_mps = 0.0
        self.distance_m = 0.0
