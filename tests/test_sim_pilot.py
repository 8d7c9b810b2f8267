"""The simulated person: random starting places and the imperfect demonstrator (study data)."""

from __future__ import annotations

import numpy as np

from carrt.clock import SimClock
from carrt.interfaces import Mode
from carrt.sim.expert import ScriptedExpert
from carrt.sim.pilot import SETTLE_S, SimPilot
from carrt.sim.plant import SimPlant
from carrt.sim.world import SimWorld


def _pilot(**kwargs) -> tuple[SimPilot, SimPlant, SimClock]:
    world = SimWorld(layout="hard", seed=3)
    plant = SimPlant(world)
    clock = SimClock()
    expert = ScriptedExpert(world.track, world.params)
    return SimPilot(plant, clock, expert=expert, **kwargs), plant, clock


def _start_place(pilot: SimPilot, plant: SimPlant, clock: SimClock) -> tuple[float, bool]:
    """Walk the pilot from DISARMED to its arm press; return where the car stood, and whether
    the arm was pressed only after the car had been placed and had settled."""
    pilot.mode_source = lambda: Mode.DISARMED
    first = pilot.poll()
    placed_at = clock.now()
    assert not first.events.arm, "no arm press in the same tick as the move"
    while not pilot.poll().events.arm:
        clock.advance(0.1)
        assert clock.now() - placed_at < 5.0, "the pilot never armed"
    settled = clock.now() - placed_at >= SETTLE_S
    s = plant.world.s
    pilot.mode_source = lambda: Mode.MANUAL  # armed: the next episode needs a new place
    pilot.poll()
    return s, settled


def test_random_start_puts_every_episode_somewhere_else_and_clear_of_obstacles():
    pilot, plant, clock = _pilot(random_start=True, seed=7)
    places = []
    for _ in range(6):
        s, settled = _start_place(pilot, plant, clock)
        assert settled
        assert plant.world._clear_at(s)
        assert plant.world.car.v == 0.0 and not plant.world.collided
        places.append(s)
    assert len({round(s, 2) for s in places}) == 6
    assert np.ptp(places) > plant.world.track.length / 3, "spread over the track"


def test_without_random_start_the_car_stays_where_it_is():
    pilot, plant, clock = _pilot()
    before = plant.world.s
    s, _ = _start_place(pilot, plant, clock)
    assert s == before


def test_expert_noise_is_gaussian_with_the_given_sigma_and_zero_means_exact():
    exact, plant, clock = _pilot()
    noisy = SimPilot(plant, clock, expert=exact.expert, expert_noise=0.5, seed=1)
    for pilot in (exact, noisy):
        pilot.mode_source = lambda: Mode.MANUAL
    for s in np.arange(0.0, plant.world.track.length, 0.25):  # a place where it steers gently
        plant.world.reset(float(s))
        plant.world.car.v = 1.5
        clean = np.array(exact.expert.act(plant.world.car))
        if abs(clean[0]) < 0.3:
            break
    assert abs(clean[0]) < 0.3
    diffs = []
    for _ in range(2000):
        sticks = exact.poll()
        assert (sticks.steering, sticks.throttle) == (clean[0], clean[1])
        sticks = noisy.poll()
        diffs.append([sticks.steering - clean[0], sticks.throttle - clean[1]])
    diffs = np.array(diffs)
    # Clipped to [-1, 1]: compare the steering spread where clipping is rare.
    assert np.all(np.abs(clean + diffs) <= 1.0)
    assert 0.35 < diffs[:, 0].std() < 0.55
    assert abs(np.median(diffs[:, 0])) < 0.05
