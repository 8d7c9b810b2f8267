"""The tick's phase lock to the camera (carrt/frame_lock.py) on the simulated clock: ticks start
on frame arrival, keep 10 Hz whatever the camera's rate and phase, and still run when the
camera stalls."""

from __future__ import annotations

import itertools

import pytest

from carrt.clock import SimClock
from carrt.frame_lock import FrameLock
from carrt.interfaces import CameraFrame


class FramesAt:
    """A camera whose frames are captured at phase + k/fps on the simulated clock, until
    `stall_at`."""

    def __init__(self, clock: SimClock, fps: float, phase: float, stall_at: float = 1e9) -> None:
        self.clock, self.period, self.stall_at = clock, 1.0 / fps, stall_at
        self.next_at, self.frame = phase, None
        clock.add_listener(self._on_tick)

    def _on_tick(self, now: float, dt: float) -> None:
        while now >= self.next_at - 1e-9 and self.next_at < self.stall_at:
            seq = 0 if self.frame is None else self.frame.seq + 1
            self.frame = CameraFrame(image=None, captured_at=self.next_at, seq=seq)
            self.next_at += self.period

    def latest(self):
        return self.frame

    def wait_newer(self, seq: int, until: float) -> None:
        while (self.frame is None or self.frame.seq <= seq) and self.clock.now() < until - 1e-9:
            self.clock.sleep_until(min(until, max(self.next_at, self.clock.now() + 1e-4)))


def run_ticks(camera_fps, phase, n=60, stall_at=1e9, work_s=0.004):
    """Tick starts and the age of the frame each used, with `work_s` of compute per tick."""
    clock = SimClock(step_s=0.001)
    camera = FramesAt(clock, camera_fps, phase, stall_at)
    lock = FrameLock(period=0.1, frame_period=1 / 30)
    deadline, starts, ages, overruns = 0.0, [], [], 0
    for _ in range(n):
        trigger = lock.wait(clock, camera, deadline)
        starts.append(trigger.at)
        frame = camera.latest()
        ages.append(float("nan") if frame is None else trigger.at - frame.captured_at)
        clock.advance(work_s)
        deadline, late = lock.realign(lock.next_deadline(deadline, trigger), clock.now())
        overruns += late
    return starts, ages, overruns


@pytest.mark.parametrize("phase", [0.0, 0.005, 0.017, 0.031])
def test_ticks_start_on_frame_arrival_at_10_hz(phase):
    starts, ages, overruns = run_ticks(30.0, phase)
    assert overruns == 0
    # Every tick used a frame no older than the clock's step: it started when the frame came.
    assert max(ages[1:]) <= 0.001 + 1e-9
    gaps = [b - a for a, b in itertools.pairwise(starts[5:])]
    assert gaps == pytest.approx([0.1] * len(gaps), abs=0.0011)


def test_a_camera_whose_rate_is_not_a_multiple_keeps_10_hz_on_average():
    starts, ages, overruns = run_ticks(25.0, 0.013, n=100)
    assert overruns == 0
    assert (starts[-1] - starts[0]) / (len(starts) - 1) == pytest.approx(0.1, abs=0.002)
    assert max(ages[1:]) <= 0.001 + 1e-9


def test_a_stalled_camera_never_stops_the_ticks():
    starts, ages, _ = run_ticks(30.0, 0.01, n=40, stall_at=1.0)
    assert starts[-1] == pytest.approx(3.9 + 0.025, abs=0.03)  # 10 Hz on, after the stall
    assert ages[-1] > 2.5  # on the last frame it had: the arbiter's age check takes over


def test_a_slow_tick_is_an_overrun_and_the_grid_skips_ahead():
    lock = FrameLock(period=0.1, frame_period=1 / 30)
    deadline, late = lock.realign(1.0, now=1.25)
    assert late and deadline == pytest.approx(1.3)
    assert lock.realign(1.0, now=0.97) == (1.0, False)
