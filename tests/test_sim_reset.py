"""The auto-reset sets a crashed car down the way a person would: on the line, along the track,
past what it hit, clear of everything, and without crediting the skipped metres as driving."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from carrt.sim.car import footprint
from carrt.sim.track import build_track, pose_at, project
from carrt.sim.types import Obstacle
from carrt.sim.world import (
    RESET_AHEAD,
    RESET_CLEARANCE,
    RESET_FENCE_CLEARANCE,
    SimWorld,
    _distance_to_body,
)


def _world_with_bucket_at(s: float, lateral: float = 0.0, radius: float = 0.1) -> SimWorld:
    track = build_track("empty")
    x, y, _ = pose_at(track, s, lateral)
    obstacle = Obstacle(x, y, radius, 0.25, (200, 30, 30))
    return SimWorld(track=dataclasses.replace(track, obstacles=(obstacle,)))


def _assert_set_down_well(world: SimWorld, hit: Obstacle | None, crash_s: float) -> None:
    car, track = world.car, world.track
    s, lateral, heading = project(track, car.x, car.y)
    assert abs(lateral) < 1e-3, "on the centerline"
    assert abs((car.yaw - heading + math.pi) % (2 * math.pi) - math.pi) < math.radians(3)
    assert car.v == 0.0 and not world.collided
    for ob in track.obstacles:
        gap = _distance_to_body(car, world.params, ob.x, ob.y) - ob.radius
        assert gap >= RESET_CLEARANCE - 1e-9, "clear of every obstacle by the margin"
    width, height = track.arena
    for x, y in footprint(car, world.params):
        assert RESET_FENCE_CLEARANCE - 1e-9 <= x <= width - RESET_FENCE_CLEARANCE
        assert RESET_FENCE_CLEARANCE - 1e-9 <= y <= height - RESET_FENCE_CLEARANCE
    if hit is not None:
        s_hit = project(track, hit.x, hit.y)[0]
        tail = s - world.params.rear_overhang
        beyond = (tail - (s_hit + hit.radius)) % track.length
        assert RESET_AHEAD - 0.01 <= beyond < 2.0, "past the obstacle it hit, not behind it"
    ahead = (s - crash_s + track.length / 2) % track.length - track.length / 2
    assert -0.05 < ahead < 2.0, "forward from the crash, not back, nor a lap away"


def test_reset_after_hitting_a_bucket_puts_the_car_past_it_on_the_line():
    world = _world_with_bucket_at(1.0)
    for _ in range(300):
        if world.step(0.01, 0.0, 0.5).collision:
            break
    assert world.collided and world.collided_with == "obstacle"
    crash_s = world.s
    progress_before = world.progress
    world.reset()
    _assert_set_down_well(world, world.track.obstacles[0], crash_s)
    skipped = world.progress - progress_before
    assert skipped > 0.2 and world.skipped == skipped


def test_resets_on_the_hard_layout_are_always_clear_and_past_the_obstacle():
    world = SimWorld("hard", 4)
    rng = np.random.default_rng(0)
    obstacle_resets = 0
    for _ in range(6000):
        world.step(0.02, float(rng.uniform(-0.4, 0.4)), 0.8)
        if world.collided:
            hit = world._obstacle_hit()
            crash_s = world.last_safe_s
            world.reset()
            _assert_set_down_well(world, hit, crash_s)
            obstacle_resets += hit is not None
    assert obstacle_resets >= 3, "the wobbly driver hit some buckets"


def test_skipped_metres_do_not_count_towards_laps():
    world = _world_with_bucket_at(1.0)
    length = world.track.length
    for _ in range(300):
        if world.step(0.01, 0.0, 0.5).collision:
            break
    world.reset()
    assert world.skipped > 0.2
    # carried round (in steps, as a person would) to just before the line: crossing it now
    # is a lap of track but not of driving, so no lap is due yet
    for s in (4.0, 8.0, length - 0.05):
        world.reset(s=s)
    for _ in range(60):
        world.step(0.01, 0.0, 0.6)
    assert world.progress >= length and world.progress - world.skipped < length
    assert world.laps == 0
