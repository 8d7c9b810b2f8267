"""One steering sign everywhere, the protocol's: −1 / `steer_left_us` turns the car LEFT.

Left in the arena's x-right/y-up frame is counter-clockwise: the heading grows and the car ends
up on the left of the line it started along. Each test goes through one whole entry point (the
board's pulses into the plant, the gymnasium env, the keyboard), so a mirrored layer anywhere
below it shows up here.
"""

from __future__ import annotations

import math
import os
import time

import numpy as np
import pytest

from carrt.sim.env import CarrtSimEnv
from carrt.sim.expert import ScriptedExpert
from carrt.sim.plant import ActuatorCalibration, SimPlant
from carrt.sim.world import SimWorld


def _left_of_start(x0: float, y0: float, yaw0: float, x: float, y: float) -> float:
    """Signed distance of (x, y) from the start's heading line, positive to its left."""
    return math.cos(yaw0) * (y - y0) - math.sin(yaw0) * (x - x0)


def _unit_to_pulse(value: float, low: int, mid: int, high: int) -> int:
    """What the board sends for a unit command (the inverse of the servo's reading)."""
    return round(mid + value * ((high - mid) if value > 0 else (mid - low)))


def _drive_plant(steer_us: int, throttle_us: int, seconds: float = 1.0):
    plant = SimPlant(SimWorld("empty"))
    x0, y0, yaw0 = plant.pose()
    for _ in range(round(seconds / 0.01)):
        plant.step(0.01, steer_us, throttle_us)
    assert not plant.world.collided
    x, y, yaw = plant.pose()
    return yaw - yaw0, _left_of_start(x0, y0, yaw0, x, y)


def test_a_steer_left_pulse_turns_the_plant_left():
    c = ActuatorCalibration()
    turn, side = _drive_plant(c.steer_left_us, 1650)
    assert turn > 0.2, "counter-clockwise"
    assert side > 0.05, "ends up left of where it was heading"
    turn, side = _drive_plant(c.steer_right_us, 1650)
    assert turn < -0.2 and side < -0.05, "and steer_right_us turns it right"


def test_gym_env_steering_minus_one_turns_left():
    env = CarrtSimEnv(layout="empty")
    env.reset(seed=0)
    car = env.car
    x0, y0, yaw0 = car.x, car.y, car.yaw
    for _ in range(12):
        _, _, terminated, _, _ = env.step(np.array([-1.0, 0.4], np.float32))
        assert not terminated
    car = env.car
    assert car.yaw - yaw0 > 0.2
    assert _left_of_start(x0, y0, yaw0, car.x, car.y) > 0.05


def test_keyboard_left_is_negative_steering_and_turns_left():
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    import pygame

    from carrt.sim.keyboard import KeyboardPad

    class _NoCamera:
        def latest(self):
            return None

    plant = SimPlant(SimWorld("empty"))
    pad = KeyboardPad(plant, _NoCamera())
    pad.start(on_estop=lambda: None)
    try:
        pygame.event.post(pygame.event.Event(pygame.KEYDOWN, key=pygame.K_LEFT))
        deadline = time.monotonic() + 5.0
        while pad.poll().steering > -0.99:
            assert time.monotonic() < deadline, "Left never reached full lock"
            time.sleep(0.01)
        steering = pad.poll().steering
    finally:
        pad.stop()
    assert steering == pytest.approx(-1.0)
    c = ActuatorCalibration()
    pulse = _unit_to_pulse(steering, c.steer_left_us, c.steer_center_us, c.steer_right_us)
    assert pulse == c.steer_left_us
    turn, side = _drive_plant(pulse, 1650)
    assert turn > 0.2 and side > 0.05


def test_the_expert_steers_left_into_a_left_hand_bend():
    """The track runs counter-clockwise: round the first sweeper the expert must steer < 0."""
    world = SimWorld("empty")
    expert = ScriptedExpert(world.track, world.params)
    steering = []
    for _ in range(400):
        action = expert.act(world.car)
        steering.append(action[0])
        world.step(0.05, *action)
        assert not world.collided
    assert world.progress > 5.0
    assert np.mean(steering) < -0.05, "a counter-clockwise lap is mostly left turns"


def test_keyboard_left_turns_the_car_left_through_the_whole_stack(tmp_path):
    """`carrt teleop --sim` in real time: the window's Left key, the loop, the C core's pulse
    over the pty, the plant. The saved trajectory bends counter-clockwise."""
    import pygame
    from e2e_rig import keyboard_teleop

    out = tmp_path / "keys"
    run, key = keyboard_teleop(out)
    key(pygame.KEYDOWN, pygame.K_RETURN)  # arm
    time.sleep(0.5)
    key(pygame.KEYDOWN, pygame.K_UP)
    key(pygame.KEYDOWN, pygame.K_LEFT)
    time.sleep(1.2)
    key(pygame.KEYDOWN, pygame.K_SPACE)  # e-stop
    assert run.result(timeout_s=30) == 0
    (npz,) = (out / "sim-runs").glob("*.npz")
    with np.load(npz) as data:
        x, y = data["x"], data["y"]
    moved = np.hypot(x - x[0], y - y[0]) > 0.05
    assert moved.any(), "the car moved"
    # the start faces along the bottom straight (+x): left of it is +y
    assert y[-1] - y[0] > 0.05 and abs(y[-1] - y[0]) > 0.3 * abs(x[-1] - x[0]) - 0.05
