"""The scripted expert, the human's stand-in: clean laps on every layout at the paper's 10 Hz,
and the paper's noise injection on top of it."""

from __future__ import annotations

import numpy as np
import pytest

from carrt.config import NoiseConfig
from carrt.noise import NoiseInjector
from carrt.sim.expert import ScriptedExpert
from carrt.sim.metrics import TrajectoryRecorder
from carrt.sim.track import LAYOUTS
from carrt.sim.world import SimWorld

CONTROL_DT = 0.1  # 10 Hz: each decision is held for 0.1 s (the world steps at 100 Hz inside)


def _drive(world, expert, *, laps, max_time, injector=None, log=None):
    recorder = TrajectoryRecorder()
    recorder.record(world)
    for _ in range(round(max_time / CONTROL_DT)):
        if world.laps >= laps:
            break
        human = expert.act(world.car)
        action = human
        if injector is not None:
            noise = injector.sample(world.time)
            action = injector.apply(human, noise)
            log.append((human, action, noise))
        info = world.step(CONTROL_DT, *action)
        recorder.record(world, info)
        if info.collision:
            world.reset()
            expert.reset()
    return recorder


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_expert_laps_every_layout_cleanly_at_10_hz(layout, seed):
    world = SimWorld(layout, seed)
    expert = ScriptedExpert(world.track, world.params)
    recorder = _drive(world, expert, laps=5, max_time=120.0)
    m = recorder.metrics(world.track.length)
    print(
        f"\n{layout} seed {seed}: average {m.average_speed:.2f} m/s, top {m.top_speed:.2f} m/s, "
        f"laps {', '.join(f'{t:.1f}' for t in m.lap_times)} s"
    )
    assert world.laps == 5 and world.collisions == 0
    assert m.collisions == 0 and m.interventions == 0
    assert m.completion_ratio == 1.0
    assert len(m.lap_times) == 5
    assert sum(m.lap_times) == pytest.approx(world.time, abs=CONTROL_DT)
    assert max(m.lap_times[1:]) < 10.0, "a flying lap of a ~13 m track"
    assert m.average_speed >= 1.2
    assert m.top_speed <= world.params.top_speed + 1e-6
    assert m.time_for_laps == pytest.approx(world.time)


def test_expert_drives_the_same_way_twice():
    def run():
        world = SimWorld("hard", 1)
        rec = _drive(world, ScriptedExpert(world.track), laps=1, max_time=30.0)
        return rec.x, rec.y, rec.speed

    assert run() == run()


def test_noise_injected_on_the_experts_actions_has_the_papers_statistics():
    world = SimWorld("hard", 0)
    expert = ScriptedExpert(world.track, world.params)
    config = NoiseConfig()
    assert (config.fraction, config.amplitude) == (0.5, 0.3)
    log: list = []
    _drive(world, expert, laps=100, max_time=60.0, injector=NoiseInjector(config, 7), log=log)
    human = np.array([h for h, _, _ in log])
    applied = np.array([a for _, a, _ in log])
    active = np.array([n.active for _, _, n in log])
    drawn = np.array([(n.steering, n.throttle) for _, _, n in log])
    delta = applied - human
    assert len(log) == 600
    assert active.mean() == pytest.approx(0.5, abs=0.02), "noise half of the time"
    assert np.all(delta[~active] == 0.0), "clean stretches execute the expert's action"
    assert np.abs(delta).max() <= config.amplitude + 1e-9
    assert np.all(np.abs(delta) <= np.abs(drawn) + 1e-9), "clipping only ever shrinks it"
    noisy = drawn[active]
    assert np.abs(noisy).max() > 0.25, "the whole range is used"
    assert np.abs(noisy.mean(axis=0)).max() < 0.08
    assert noisy.std(axis=0) == pytest.approx(config.amplitude / np.sqrt(3), abs=0.05)
    # the expert recovers from the pushes instead of crashing
    assert world.collisions == 0 and world.laps >= 3
