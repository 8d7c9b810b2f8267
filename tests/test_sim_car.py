"""The simulated car's physics and the world's collision and progress bookkeeping."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from carrt.sim.car import CarParams, footprint, step_car
from carrt.sim.track import build_track, pose_at, project
from carrt.sim.types import CarState, Obstacle
from carrt.sim.world import SimWorld, StepInfo

P = CarParams()


def _drive(state, seconds, steering, throttle, dt=0.01, params=P):
    states = []
    for _ in range(round(seconds / dt)):
        state = step_car(state, params, dt, steering, throttle)
        states.append(state)
    return state, states


def test_full_throttle_settles_at_top_speed():
    state, states = _drive(CarState(0, 0, 0), 6.0, 0.0, 1.0)
    assert state.v == pytest.approx(2.5, abs=0.03)
    assert max(s.v for s in states) <= 2.5 + 1e-9
    assert state.y == pytest.approx(0.0) and state.yaw == pytest.approx(0.0), "straight is straight"
    half, _ = _drive(CarState(0, 0, 0), 6.0, 0.0, 0.5)
    assert 0.9 < half.v < 1.5, "half throttle is a cruising speed, not top speed"


def test_braking_stops_then_reverse_settles_at_reverse_speed():
    fast, _ = _drive(CarState(0, 0, 0), 5.0, 0.0, 1.0)
    stopped_at = None
    state = fast
    for i in range(300):
        state = step_car(state, P, 0.01, 0.0, -1.0)
        if state.v <= 0 and stopped_at is None:
            stopped_at = i * 0.01
    assert stopped_at is not None and stopped_at < 1.0, "brakes stop it from top speed in < 1 s"
    assert state.v == pytest.approx(-P.reverse_speed, abs=0.05)
    coast, _ = _drive(fast, 6.0, 0.0, 0.0)
    assert coast.v == 0.0, "rolling resistance stops it; drag never pushes it backwards"


def test_minimum_turning_radius_at_low_speed_is_the_kinematic_one():
    state, states = _drive(CarState(0, 0, 0), 12.0, -1.0, 0.2)
    assert 0.2 < state.v < 0.8 and not any(s.sliding for s in states)
    radius = P.wheelbase / math.tan(P.max_steer)
    assert state.v / state.yaw_rate == pytest.approx(radius, rel=1e-3)
    xs = np.array([s.x for s in states[-600:]])
    ys = np.array([s.y for s in states[-600:]])
    assert (xs.max() - xs.min()) / 2 == pytest.approx(radius, rel=0.02), "the drawn circle"
    assert (ys.max() - ys.min()) / 2 == pytest.approx(radius, rel=0.02)
    assert state.yaw_rate > 0, "steering −1 (the protocol's left) turns counter-clockwise"


def test_full_lock_at_speed_slides_wide_and_scrubs_speed():
    fast, _ = _drive(CarState(0, 0, 0), 5.0, 0.0, 1.0)
    state, states = _drive(fast, 1.0, 1.0, 1.0)
    assert any(s.sliding for s in states)
    kinematic = P.wheelbase / math.tan(P.max_steer)
    sliding = [s for s in states if s.sliding]
    for s in sliding:
        assert abs(s.v * s.yaw_rate) <= P.max_lateral_accel + 1e-6, "grip caps lateral accel"
        assert abs(s.v / s.yaw_rate) > 1.2 * kinematic, "understeer: wider than the wheels ask"
    assert state.v < fast.v - 0.3, "the slide scrubs speed"
    assert 6.0 <= P.max_lateral_accel <= 8.0


def test_gentle_steering_does_not_slide():
    fast, _ = _drive(CarState(0, 0, 0), 5.0, 0.0, 1.0)
    _, states = _drive(fast, 1.0, 0.1, 1.0)
    assert not any(s.sliding for s in states)


def test_steering_and_motor_lag_are_first_order():
    state, _ = _drive(CarState(0, 0, 0), P.steer_tau, 1.0, 0.0, dt=0.001)
    assert -state.steer / P.max_steer == pytest.approx(1 - math.exp(-1), abs=0.01)
    state, _ = _drive(CarState(0, 0, 0), P.motor_tau, 0.0, 1.0, dt=0.001)
    assert state.motor == pytest.approx(1 - math.exp(-1), abs=0.01)
    after, _ = _drive(CarState(0, 0, 0), 0.05, 0.0, 1.0)
    assert after.v < 0.15, "the car does not jump to speed"


def test_encoder_ticks_match_the_distance_within_one_tick():
    rng = np.random.default_rng(0)
    state = CarState(0, 0, 0)
    for _ in range(400):
        state = step_car(state, P, 0.02, rng.uniform(-1, 1), rng.uniform(-0.3, 1))
        assert state.encoder_ticks == math.floor(state.odometer * P.ticks_per_metre)
    assert state.odometer > 3.0
    # straight driving: odometer equals the distance covered
    state, _ = _drive(CarState(0, 0, 0), 3.0, 0.0, 0.8)
    assert abs(state.encoder_ticks / P.ticks_per_metre - state.x) <= 1 / P.ticks_per_metre


def test_large_steps_are_stable_and_agree_with_small_ones():
    coarse, _ = _drive(CarState(0, 0, 0), 4.0, 0.6, 0.7, dt=0.02)
    fine, _ = _drive(CarState(0, 0, 0), 4.0, 0.6, 0.7, dt=0.001)
    assert all(math.isfinite(v) for v in (coarse.x, coarse.y, coarse.v))
    assert math.hypot(coarse.x - fine.x, coarse.y - fine.y) < 0.02
    assert coarse.v == pytest.approx(fine.v, abs=0.02)


def test_commands_are_clipped_and_nan_is_no_command():
    a = step_car(CarState(0, 0, 0), P, 0.5, 5.0, 9.0)
    b = step_car(CarState(0, 0, 0), P, 0.5, 1.0, 1.0)
    assert a == b
    c = step_car(CarState(0, 0, 0), P, 0.5, float("nan"), float("nan"))
    assert c.v == 0.0 and c.steer == 0.0


# -- the world: collisions from the body, resets, progress ----------------------------------


def _world_with_obstacle(x, y, radius=0.1):
    track = dataclasses.replace(
        build_track("empty"), obstacles=(Obstacle(x, y, radius, 0.25, (200, 30, 30)),)
    )
    return SimWorld(track=track)


def _run(world, seconds, steering, throttle, dt=0.01):
    for _ in range(round(seconds / dt)):
        info = world.step(dt, steering, throttle)
        if info.collision:
            return info
    return info


@pytest.mark.parametrize("offset, hits", [(0.14, True), (0.165, False)])
def test_obstacle_is_hit_by_the_body_side_not_only_the_centre(offset, hits):
    # arena coordinates, away from the track: drive along +x past a bucket at y = 1.9
    world = _world_with_obstacle(3.5, 1.9)
    world.car = CarState(2.8, 1.9 - offset, 0.0)
    info = _run(world, 1.5, 0.0, 0.4)
    assert info.collision is hits
    if hits:
        assert info.collided_with == "obstacle" and world.collided
        car = world.car
        centre_gap = math.hypot(car.x + 0.07 - 3.5, car.y - 1.9)
        assert centre_gap > 0.1, "the body's centre never reached the bucket"
        assert abs(car.y - 1.9) > 0.1, "its centreline passes beside it"


def test_front_corner_touching_the_fence_is_a_collision():
    world = SimWorld("empty")
    # heading diagonally into the left fence: a front corner reaches x = 0 first
    world.car = CarState(0.4, 1.5, math.radians(150))
    info = _run(world, 2.0, 0.0, 0.3)
    assert info.collision and info.collided_with == "fence"
    corners = world.footprint()
    assert min(x for x, _ in corners) <= 0.01
    assert sum(x <= 0.01 for x, _ in corners) == 1, "one corner, not the whole front"
    assert world.car.x > 0.1, "the reference point is still well inside"


def test_collided_car_stands_until_reset_which_lifts_it_back_onto_the_centerline():
    world = SimWorld("empty")
    world.step(0.5, 0.0, 1.0)
    assert not world.collided and world.last_safe_s > 0
    world.car = dataclasses.replace(world.car, yaw=world.car.yaw - math.pi / 2)  # face the fence
    info = _run(world, 3.0, 0.0, 1.0)
    assert info.collision and info.collided_with == "fence"
    frozen = world.car
    assert frozen.v == 0.0
    safe = world.last_safe_s
    t0 = world.time
    for _ in range(5):
        again = world.step(0.1, 0.0, 1.0)
        assert again.collision and again.collided_with == "fence"
    assert world.car == frozen and world.time == pytest.approx(t0 + 0.5)
    assert world.collisions == 1
    world.reset()
    assert not world.collided and world.car.v == 0.0
    s, lat, heading = project(world.track, world.car.x, world.car.y)
    gap = (s - safe) % world.track.length
    assert gap < 0.06 and abs(lat) < 1e-6, "set down where it left the line, not behind it"
    assert world.car.yaw == pytest.approx(heading)
    assert world.distance == 0.0
    world.reset(s=5.0)
    assert world.s == pytest.approx(5.0, abs=1e-6)
    assert (world.car.x, world.car.y) == pytest.approx(pose_at(world.track, 5.0)[:2])


def test_reset_moves_on_past_a_bucket_at_the_set_down_place():
    track = build_track("empty")
    x, y, _ = pose_at(track, 4.0)
    world = _world_with_obstacle(x, y)
    world.last_safe_s = 4.2  # setting it down here would put its tail against the bucket
    world.reset()
    assert world.s > 4.2 and not world._collision()
    assert world._clear_at(world.s)


def test_laps_progress_and_off_track_bookkeeping():
    world = SimWorld("empty")
    length = world.track.length
    world.reset(s=length - 0.3)  # just behind the start line: no lap done yet
    assert world.progress == pytest.approx(-0.3)
    _run(world, 2.0, 0.0, 0.6)
    assert world.laps == 0 and world.progress > 0
    for s in (4.0, 8.0, length - 0.3):  # carried round the track by resets, in steps
        world.reset(s=s)
    assert world.progress == pytest.approx(length - 0.3)
    info = _run(world, 2.0, 0.0, 0.6)
    assert world.laps == 1 and 0.0 < world.s < 2.0
    # back over the line and forward again: still one lap
    world.reset(s=length - 0.1)
    laps = [world.step(0.01, 0.0, 0.6).lap_completed for _ in range(100)]
    assert world.laps == 1 and not any(laps)
    assert world.distance > 0.1
    # off the markings is not a crash
    world.reset(s=0.3)
    world.car = dataclasses.replace(world.car, yaw=world.car.yaw + 0.6)  # aim at the infield
    infos = [world.step(0.01, 0.0, 0.5) for _ in range(150)]
    assert any(i.off_track for i in infos) and world.off_track
    assert not any(i.collision for i in infos)
    assert isinstance(info, StepInfo)


def test_world_is_deterministic_and_fast_enough():
    def run():
        world = SimWorld("hard", 3)
        out = []
        rng = np.random.default_rng(5)
        for _ in range(300):
            info = world.step(0.02, rng.uniform(-1, 1), rng.uniform(0, 1))
            out.append((world.car.x, world.car.y, world.progress, info))
            if info.collision:
                world.reset()
        return out, world.time

    assert run() == run()
    import time

    world = SimWorld("hard", 0)
    start = time.perf_counter()
    for _ in range(2000):
        world.step(0.01, 0.1, 0.3)
        if world.collided:
            world.reset()
    rate = 2000 / (time.perf_counter() - start)
    assert rate > 2000, f"{rate:.0f} steps/s"


def test_footprint_is_the_body_rectangle():
    corners = footprint(CarState(1.0, 1.0, 0.0), P)
    xs, ys = zip(*corners, strict=True)
    assert min(xs) == pytest.approx(1.0 - P.rear_overhang)
    assert max(xs) == pytest.approx(1.0 - P.rear_overhang + P.length)
    assert max(ys) - min(ys) == pytest.approx(P.width)


def test_steering_the_other_way_mirrors_the_path():
    """Mirroring a recorded window (training/augment.mirror_batch negates the steering) is only
    physical if the car turns the same either way: −s must trace +s's path mirrored, slides
    and lags included."""
    for steering in (0.3, 1.0):
        _, rs = _drive(CarState(0, 0, 0), 3.0, steering, 0.8)
        _, ls = _drive(CarState(0, 0, 0), 3.0, -steering, 0.8)
        assert ls[50].yaw > 0.05, "−1 turns left (counter-clockwise)"
        for a, b in zip(rs, ls, strict=True):
            assert (a.x, a.v) == pytest.approx((b.x, b.v), abs=1e-9)
            assert (a.y, a.yaw) == pytest.approx((-b.y, -b.yaw), abs=1e-9)
