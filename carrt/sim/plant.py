"""The simulated car as the virtual board's plant: pulses in, motion and encoder ticks out.

The board (real C core) decides the pulses; the plant interprets them the way a servo and an
ESC do (with their own endpoints and a neutral deadband) and moves the simulated car, so every
failsafe, slew limit and calibration error shows up in the car's motion exactly as on a real
one. One lock guards the world: the board steps it, the camera renders it, the pad resets it,
possibly from three threads in real-time mode.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

from firmware_bridge.drivetrain import pulse_to_unit


@dataclass(frozen=True)
class ActuatorCalibration:
    """How the simulated servo and ESC read pulses (a real car's are measured by calibrate)."""

    steer_left_us: int = 1000
    steer_center_us: int = 1500
    steer_right_us: int = 2000
    esc_reverse_us: int = 1000
    esc_neutral_us: int = 1500
    esc_forward_us: int = 2000
    esc_deadband_us: int = 20


class SimPlant:
    def __init__(self, world, calibration: ActuatorCalibration = ActuatorCalibration()) -> None:
        self.world = world
        self.calibration = calibration
        self.lock = threading.RLock()
        self._collisions = 0
        self._collisions_reported = 0
        self.last_collision = ""
        self._was_collided = False

    def step(self, dt_s: float, steer_us: int, throttle_us: int) -> int:
        c = self.calibration
        steering = pulse_to_unit(steer_us, c.steer_left_us, c.steer_center_us, c.steer_right_us)
        throttle = pulse_to_unit(
            throttle_us, c.esc_reverse_us, c.esc_neutral_us, c.esc_forward_us, c.esc_deadband_us
        )
        with self.lock:
            if dt_s > 0:
                info = self.world.step(dt_s, steering, throttle)
                if info.collision and not self._was_collided:  # the world stays collided
                    self._collisions += 1
                    self.last_collision = info.collided_with
                self._was_collided = info.collision
            return self.world.car.encoder_ticks

    def take_collision(self) -> bool:
        """True once for each collision since the last call (the loop labels and e-stops)."""
        with self.lock:
            new = self._collisions > self._collisions_reported
            self._collisions_reported = self._collisions
            return new

    def reset(self, s: float | None = None) -> None:
        """Put the car back on the track at rest: after a collision (the paper's auto-reset),
        or at arc position s."""
        with self.lock:
            self.world.reset(s)
            self._was_collided = False

    def pose(self) -> tuple[float, float, float]:
        with self.lock:
            state = self.world.car
            return state.x, state.y, state.yaw
