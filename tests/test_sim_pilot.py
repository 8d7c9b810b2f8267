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


def _where_it_steers_gently(exact: SimPilot, plant: SimPlant) -> np.ndarray:
    """Put the car, moving, where the clean expert steers under 0.3 (so noise is rarely
    clipped); return the clean command there."""
    for s in np.arange(0.0, plant.world.track.length, 0.25):
        plant.world.reset(float(s))
        plant.world.car.v = 1.5
        clean = np.array(exact.expert.act(plant.world.car))
        if abs(clean[0]) < 0.3:
            return clean
    raise AssertionError("no place where the expert steers gently")


def test_expert_noise_is_gaussian_with_the_given_sigma_and_zero_means_exact():
    exact, plant, clock = _pilot()
    noisy = SimPilot(plant, clock, expert=exact.expert, expert_noise=0.5, seed=1)
    for pilot in (exact, noisy):
        pilot.mode_source = lambda: Mode.MANUAL
    clean = _where_it_steers_gently(exact, plant)
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


def _errors(tau: float, seed: int = 4, n: int = 4000) -> np.ndarray:
    """The noisy pilot's steering error at 10 Hz on a straight, slow stretch (no clipping)."""
    exact, plant, clock = _pilot()
    noisy = SimPilot(plant, clock, expert=exact.expert, expert_noise=0.3, expert_noise_tau=tau,
                     seed=seed)  # fmt: skip
    for pilot in (exact, noisy):
        pilot.mode_source = lambda: Mode.MANUAL
    clean = _where_it_steers_gently(exact, plant)[0]
    errors = []
    for _ in range(n):
        errors.append(noisy.poll().steering - clean)
        clock.advance(0.1)
    return np.array(errors)


def _lag_correlation(x: np.ndarray, lag: int) -> float:
    return float(np.corrcoef(x[:-lag], x[lag:])[0, 1])


def test_a_lasting_error_has_the_same_sigma_and_the_time_constant_it_was_given():
    """expert_noise_tau: the person's error is an Ornstein-Uhlenbeck process, σ per command as
    before, correlated exp(−Δt/τ) between commands Δt apart; τ 0 keeps fresh draws."""
    lasting, fresh = _errors(tau=0.5), _errors(tau=0.0)
    assert 0.25 < lasting.std() < 0.35 and 0.27 < fresh.std() < 0.33
    assert abs(_lag_correlation(lasting, 1) - np.exp(-0.1 / 0.5)) < 0.05  # 0.82
    assert abs(_lag_correlation(lasting, 5) - np.exp(-1.0)) < 0.08  # 0.37
    assert abs(_lag_correlation(lasting, 30)) < 0.08, "forgotten after a few τ"
    assert abs(_lag_correlation(fresh, 1)) < 0.05, "τ 0: a new error every command"


def test_without_tau_the_noise_is_the_same_draws_as_before_it_existed():
    """τ 0 draws the seeded generator exactly as the i.i.d. demonstrator always did, so every
    recording made before the option (and a study run with it off) is made again the same."""
    errors = _errors(tau=0.0, seed=9, n=50)
    rng = np.random.default_rng(9)
    draws = [rng.normal(0.0, 0.3, 2)[0] for _ in range(50)]
    assert np.allclose(errors, draws)


def test_after_a_gap_the_error_is_fresh():
    """Between take-overs the person does not carry the last error: after a pause of many τ
    the new error is uncorrelated with the one before it."""
    exact, plant, clock = _pilot()
    _where_it_steers_gently(exact, plant)
    pairs = []
    for seed in range(300):
        noisy = SimPilot(plant, clock, expert=exact.expert, expert_noise=0.3,
                         expert_noise_tau=0.5, seed=seed)  # fmt: skip
        noisy.mode_source = lambda: Mode.MANUAL
        before = noisy.poll().steering
        clock.advance(0.05)
        soon = noisy.poll().steering
        clock.advance(10.0)
        pairs.append((before, soon, noisy.poll().steering))
    before, soon, later = np.array(pairs).T
    assert np.corrcoef(before, soon)[0, 1] > 0.85
    assert abs(np.corrcoef(soon, later)[0, 1]) < 0.15
