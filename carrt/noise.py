"""The paper's noise injection for teleop recording (the DIRL paper).

Why inject noise at all: a human driving well only ever shows the policy the middle of the
track. DIRL perturbs the executed action for half of the collection time with uniform noise in
[-0.3, 0.3], so the human has to recover, and records both the human's action a* (the label)
and the executed one a (what the world model sees the car do).

How the time is shared: time is cut into periods of ``period_s``; inside each period one window
of ``fraction · period_s`` is noisy, at a random offset. That makes the noisy share exactly
``fraction`` over whole periods (not just on average), while the human still cannot predict when
the next noisy stretch starts. Inside a window each value pair is held for a random
``[hold_min_s, hold_max_s]``: a car does not react to 10 Hz white noise, it reacts to a pull that
lasts long enough to put it off its line. The last hold of a window is cut at the window's end.

Everything about period k is drawn from a generator seeded with (seed, k), so ``sample(t)`` is a
pure function of the seed and t: the same seed gives the same noise for any sequence of times,
and the simulator and the car can replay a recording's noise exactly.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from carrt.config import NoiseConfig
from carrt.interfaces import Mode

STEER_LIMITS = (-1.0, 1.0)
THROTTLE_LIMITS = (-1.0, 1.0)


class NoiseSample(NamedTuple):
    """Noise to add to (steering, throttle) now, and whether this instant is in a noisy window."""

    steering: float
    throttle: float
    active: bool


@dataclass(frozen=True)
class _Period:
    start: float  # window start, seconds from the period's start
    end: float  # window end (start + fraction * period)
    hold_starts: list[float]  # each hold's start, seconds from the period's start, ascending
    values: np.ndarray  # (n, 2) steering, throttle noise per hold


def apply(human: Sequence[float], noise: Sequence[float]) -> tuple[float, float]:
    """The executed action a = clip(a* + noise); `noise` may be a NoiseSample or a pair."""
    steer = min(max(float(human[0]) + float(noise[0]), STEER_LIMITS[0]), STEER_LIMITS[1])
    throttle = min(max(float(human[1]) + float(noise[1]), THROTTLE_LIMITS[0]), THROTTLE_LIMITS[1])
    return steer, throttle


class NoiseInjector:
    """Deterministic, seeded noise schedule: ``sample(t)`` for a monotonic time t in seconds."""

    def __init__(self, config: NoiseConfig, seed: int) -> None:
        if config.hold_min_s <= 0 or config.hold_min_s > config.hold_max_s:
            raise ValueError("noise: need 0 < hold_min_s <= hold_max_s")
        if config.period_s <= 0:
            raise ValueError("noise: period_s must be positive")
        self.config = config
        self.seed = int(seed)
        self._cache: dict[int, _Period] = {}

    apply = staticmethod(apply)  # so the loop can hold one object: injector.apply(human, noise)

    def perturbs(self, mode: Mode) -> bool:
        """Whether commands in `mode` get noise: MANUAL always (the paper's recovery data), AUTO
        only with `during_auto` (the policy's own mistakes and recoveries, for the world model).
        Never a stopped or failsafe mode: noise must not move a car that is meant to stand."""
        return mode == Mode.MANUAL or (self.config.during_auto and mode == Mode.AUTO)

    def sample(self, t: float) -> NoiseSample:
        period_s = self.config.period_s
        k = math.floor(t / period_s)
        local = t - k * period_s
        period = self._period(k)
        if not period.start <= local < period.end:
            return NoiseSample(0.0, 0.0, False)
        i = bisect.bisect_right(period.hold_starts, local) - 1
        steer, throttle = period.values[max(i, 0)]
        return NoiseSample(float(steer), float(throttle), True)

    def window(self, k: int) -> tuple[float, float]:
        """Absolute (start, end) of period k's noisy window; start == end when fraction is 0."""
        period = self._period(k)
        base = k * self.config.period_s
        return base + period.start, base + period.end

    def _period(self, k: int) -> _Period:
        period = self._cache.get(k)
        if period is None:
            period = self._draw(k)
            if len(self._cache) >= 4:  # time moves forwards: a few recent periods suffice
                self._cache.pop(next(iter(self._cache)))
            self._cache[k] = period
        return period

    def _draw(self, k: int) -> _Period:
        cfg = self.config
        # Seed material must be non-negative; the modulo keeps negative k (t < 0) distinct.
        rng = np.random.default_rng([self.seed % 2**64, k % 2**64])
        noisy = min(max(cfg.fraction, 0.0), 1.0) * cfg.period_s
        start = float(rng.uniform(0.0, cfg.period_s - noisy)) if noisy < cfg.period_s else 0.0
        end = start + noisy
        count = max(1, math.ceil(noisy / cfg.hold_min_s) + 1)  # enough holds to fill the window
        holds = rng.uniform(cfg.hold_min_s, cfg.hold_max_s, size=count)
        values = rng.uniform(-cfg.amplitude, cfg.amplitude, size=(count, 2))
        hold_starts = (start + np.concatenate(([0.0], np.cumsum(holds[:-1])))).tolist()
        n = bisect.bisect_left(hold_starts, end) if noisy > 0 else 0
        return _Period(start, end, hold_starts[: max(n, 1)], values[: max(n, 1)])
