"""Speed from encoder telemetry (board-timed) and the two clocks."""

from __future__ import annotations

import time

import pytest

from carrt.clock import SimClock, WallClock
from carrt.speed import SpeedEstimator
from firmware_bridge import messages as m


def tel(ms, ticks):
    return m.Telemetry(mcu_time_ms=ms, encoder_ticks=ticks)


def test_speed_uses_the_board_clock_over_the_window():
    est = SpeedEstimator(metres_per_tick=0.01, window_s=0.1)
    assert est.update(tel(0, 0)) == 0.0
    for i in range(1, 11):  # 50 Hz telemetry, 2 ticks per 20 ms = 1 m/s
        speed = est.update(tel(20 * i, 2 * i))
    assert speed == pytest.approx(1.0)
    assert est.update(tel(200, 20)) == pytest.approx(1.0), "a repeated sample changes nothing"


def test_speed_restarts_after_a_board_reboot():
    est = SpeedEstimator(metres_per_tick=0.01)
    for i in range(10):
        est.update(tel(1000 + 20 * i, 500 + 5 * i))
    assert est.speed_mps > 0
    assert est.update(tel(5, 0)) == 0.0


def test_sim_clock_jumps_and_wall_clock_waits():
    clock = SimClock(10.0)
    clock.sleep_until(12.5)
    assert clock.now() == 12.5
    clock.sleep_until(11.0)
    assert clock.now() == 12.5, "time never goes back"
    wall = WallClock()
    start = time.monotonic()
    wall.sleep_until(wall.now() + 0.05)
    assert 0.05 <= time.monotonic() - start < 0.5
