"""Noise injection (DESIGN §2): the share of noisy time, the values, the holds, determinism."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from carrt.config import NoiseConfig
from carrt.noise import NoiseInjector, NoiseSample, apply

DT = 0.01  # finer than the 10 Hz loop, so hold lengths and window edges are measured closely


def run(injector: NoiseInjector, seconds: float, t0: float = 0.0):
    times = t0 + np.arange(round(seconds / DT)) * DT
    samples = [injector.sample(float(t)) for t in times]
    steer = np.array([s.steering for s in samples])
    throttle = np.array([s.throttle for s in samples])
    active = np.array([s.active for s in samples])
    return times, steer, throttle, active


@pytest.fixture(scope="module")
def long_run():
    config = NoiseConfig()  # the paper's numbers: half the time, ±0.3
    injector = NoiseInjector(config, seed=7)
    return config, injector, run(injector, 1000.0)


def test_noisy_share_is_the_fraction(long_run):
    config, _, (_, _, _, active) = long_run
    assert abs(active.mean() - config.fraction) < 0.02


@pytest.mark.parametrize("fraction", [0.0, 0.2, 0.75, 1.0])
def test_noisy_share_over_whole_periods_for_other_fractions(fraction):
    config = NoiseConfig(fraction=fraction, period_s=5.0)
    _, _, _, active = run(NoiseInjector(config, seed=3), 200.0)
    assert abs(active.mean() - fraction) < 0.01


def test_each_period_has_one_window_of_the_right_length():
    config = NoiseConfig(fraction=0.3, period_s=10.0)
    injector = NoiseInjector(config, seed=11)
    starts = []
    for k in range(50):
        start, end = injector.window(k)
        assert 10.0 * k <= start and end <= 10.0 * (k + 1) + 1e-9
        assert end - start == pytest.approx(3.0)
        starts.append(start - 10.0 * k)
    assert np.std(starts) > 1.0  # the window moves around: the human cannot predict it


def test_values_bounded_and_roughly_uniform(long_run):
    config, _, (_, steer, throttle, active) = long_run
    a = config.amplitude
    for values in (steer[active], throttle[active]):
        assert np.all(np.abs(values) <= a)
        assert abs(values.mean()) < 0.03
        assert values.std() == pytest.approx(a / math.sqrt(3), rel=0.1)
        hist, _ = np.histogram(values, bins=4, range=(-a, a))
        assert hist.min() > 0.15 * hist.sum()  # no quarter of the range is starved
    assert abs(np.corrcoef(steer[active], throttle[active])[0, 1]) < 0.15


def test_zero_outside_the_noisy_windows(long_run):
    _, _, (_, steer, throttle, active) = long_run
    assert np.all(steer[~active] == 0.0)
    assert np.all(throttle[~active] == 0.0)
    assert np.all(steer[active] != 0.0)


def test_hold_durations_within_bounds(long_run):
    config, injector, (times, steer, throttle, active) = long_run
    change = np.flatnonzero(
        (np.diff(steer) != 0) | (np.diff(throttle) != 0) | (np.diff(active) != 0)
    )
    lengths = []
    for a, b in itertools.pairwise(change):
        if not active[a + 1]:
            continue
        end_t = times[b + 1]
        k = math.floor(times[a + 1] / config.period_s)
        if end_t >= injector.window(k)[1] - DT:
            continue  # the last hold of a window is cut at the window's end
        lengths.append((b - a) * DT)
    lengths = np.array(lengths)
    assert len(lengths) > 500
    assert lengths.min() >= config.hold_min_s - 2 * DT
    assert lengths.max() <= config.hold_max_s + 2 * DT
    assert lengths.mean() == pytest.approx((config.hold_min_s + config.hold_max_s) / 2, rel=0.1)


def test_deterministic_per_seed_and_independent_of_the_query_order():
    config = NoiseConfig()
    ts = np.linspace(0.0, 120.0, 1201)
    a = [NoiseInjector(config, seed=5).sample(float(t)) for t in ts]
    b = [NoiseInjector(config, seed=5).sample(float(t)) for t in ts]
    assert a == b
    shuffled = NoiseInjector(config, seed=5)
    order = np.random.default_rng(0).permutation(len(ts))
    c = {int(i): shuffled.sample(float(ts[i])) for i in order}
    assert [c[i] for i in range(len(ts))] == a
    other = [NoiseInjector(config, seed=6).sample(float(t)) for t in ts]
    assert other != a


def test_sample_is_a_named_triple():
    sample = NoiseInjector(NoiseConfig(fraction=1.0), seed=1).sample(0.5)
    assert isinstance(sample, NoiseSample)
    steer, throttle, active = sample
    assert active and steer == sample.steering and throttle == sample.throttle


def test_executed_is_the_clipped_sum():
    assert apply((0.2, 0.5), (0.1, -0.3)) == pytest.approx((0.3, 0.2))
    assert apply((0.9, 0.95), (0.3, 0.3)) == (1.0, 1.0)
    assert apply((-0.9, -0.8), (-0.3, -0.3)) == (-1.0, -1.0)
    assert apply((0.4, 0.4), NoiseSample(0.0, 0.0, False)) == (0.4, 0.4)
    injector = NoiseInjector(NoiseConfig(fraction=1.0, amplitude=0.3), seed=2)
    rng = np.random.default_rng(0)
    for t in np.arange(0.0, 30.0, 0.1):
        human = tuple(rng.uniform(-1, 1, size=2))
        noise = injector.sample(float(t))
        executed = apply(human, noise)
        assert injector.apply(human, noise[:2]) == executed  # the same rule, on the injector
        expected = np.clip(np.array(human) + np.array(noise[:2]), -1.0, 1.0)
        assert executed == pytest.approx(tuple(expected))


def test_bad_hold_bounds_are_refused():
    with pytest.raises(ValueError):
        NoiseInjector(NoiseConfig(hold_min_s=2.0, hold_max_s=1.0), seed=0)
