"""The scripted expert as the safety driver: it takes over from a policy before a collision,
the arbiter records that as an intervention (override, a* = the expert's sticks), and the
policy gets the car back once it is safe."""

from __future__ import annotations

import numpy as np
from e2e_rig import CliRun
from onnx_models import build_policy

from carrt.clock import SimClock
from carrt.episodes.reader import list_episodes, read_episode
from carrt.interfaces import Mode
from carrt.sim.expert import ScriptedExpert
from carrt.sim.lookahead import collision_ahead
from carrt.sim.pilot import INTERVENE_HOLD_S, SimPilot
from carrt.sim.plant import SimPlant
from carrt.sim.world import SimWorld


def test_pilot_takes_the_sticks_when_a_crash_is_near_and_hands_back_later():
    world = SimWorld("empty")
    plant = SimPlant(world)
    clock = SimClock()
    pilot = SimPilot(
        plant, clock, expert=ScriptedExpert(world.track, world.params), engage_auto=True,
        intervene=True,
    )  # fmt: skip
    reference = ScriptedExpert(world.track, world.params)
    pilot.mode_source = lambda: Mode.AUTO
    assert not collision_ahead(world)
    assert (pilot.poll().steering, pilot.poll().throttle) == (0.0, 0.0), "the policy drives"
    # straight on at speed off the end of the bottom straight: the fence is coming
    for _ in range(200):
        world.step(0.01, 0.0, 1.0)
        if collision_ahead(world):
            break
    assert collision_ahead(world) and not world.collided
    sticks = pilot.poll()
    assert (sticks.steering, sticks.throttle) == reference.act(world.car), "the expert's sticks"
    assert pilot.log.interventions == 1
    pilot.mode_source = lambda: Mode.MANUAL  # the arbiter saw the sticks move
    assert not pilot.poll().events.toggle_auto, "it holds on"
    clock.advance(INTERVENE_HOLD_S + 0.1)
    world.reset(s=2.0)  # safe now
    released = pilot.poll()
    assert (released.steering, released.throttle) == (0.0, 0.0)
    assert released.events.toggle_auto, "and hands back to the policy"


def _drive(tmp_path, name, *extra):
    model = build_policy(tmp_path / "crash.onnx", steering=0.0, throttle=(0.8, 0.0))
    out = tmp_path / name
    code = CliRun(
        ["drive", "--sim", "--autopilot", "--model", str(model), "--record", "--layout", "easy",
         "--duration", "25", "--out", str(out), *extra]
    ).result(timeout_s=120)  # fmt: skip
    assert code == 0
    return [read_episode(p) for p in list_episodes(out)]


def test_intervention_mode_records_expert_labels_and_prevents_crashes(tmp_path):
    # A policy that drives straight on: without help it hits the fence at every bend.
    alone = _drive(tmp_path, "alone")
    helped = _drive(tmp_path, "helped", "--expert-intervene")
    crashes_alone = sum(int(ep.steps["collision"].any()) for ep in alone)
    crashes_helped = sum(int(ep.steps["collision"].any()) for ep in helped)
    assert crashes_alone >= 3
    assert crashes_helped <= crashes_alone // 3
    steps = np.concatenate([ep.steps for ep in helped])
    override = steps["override"].astype(bool)
    assert override.sum() >= 2, "several takeovers"
    manual = steps["mode"] == Mode.MANUAL
    assert (steps["mode"] == Mode.AUTO).any(), "the policy got the car back in between"
    # a* is the expert's sticks, and it is what the car executed (no noise in drive mode)
    human, executed = steps["human_action"], steps["executed_action"]
    assert np.allclose(human[override], executed[override])
    assert (np.abs(human[override]).sum(axis=1) > 0).all()
    taken = manual & (np.abs(human).sum(axis=1) > 0)
    assert np.allclose(human[taken], executed[taken])
    assert taken.sum() >= 10 * override.sum() // 2, "it drives for a while after each takeover"


def test_a_noisy_demonstrator_is_as_noisy_when_it_takes_over():
    """The robustness setting's imperfect person (σ on every command) keeps its σ when it takes
    over from the policy: the study's take-overs must not be cleaner than its demonstrations."""
    world = SimWorld("empty")
    plant = SimPlant(world)
    reference = ScriptedExpert(world.track, world.params)
    pilots = {
        sigma: SimPilot(
            plant,
            SimClock(),
            expert=ScriptedExpert(world.track, world.params),
            engage_auto=True,
            intervene=True,
            expert_noise=sigma,
        )
        for sigma in (0.0, 1.0)
    }
    for _ in range(200):  # straight at the fence, as above
        world.step(0.01, 0.0, 1.0)
        if collision_ahead(world):
            break
    assert collision_ahead(world)
    deviations = {}
    for sigma, pilot in pilots.items():
        pilot.mode_source = lambda: Mode.AUTO
        sticks = pilot.poll()
        assert pilot.log.interventions == 1, "it took over"
        pilot.mode_source = lambda: Mode.MANUAL
        polls = [sticks, *(pilot.poll() for _ in range(50))]
        expert = np.array(reference.act(world.car))
        deviations[sigma] = np.array([(p.steering, p.throttle) for p in polls]) - expert
    assert np.abs(deviations[0.0]).max() == 0.0, "σ 0: exactly the expert's sticks"
    spread = deviations[1.0].std(axis=0)
    assert (spread > 0.3).all(), f"σ 1: the take-over sticks carry the noise ({spread})"
