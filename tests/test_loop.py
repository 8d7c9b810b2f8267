"""The control loop built directly, on the simulated clock, without a pty: the simulated car is
the plant of the real C firmware core in-process (DirectBoardLink), the camera renders it, and a
scripted pad presses the buttons. Plus a replay of recorded steps through the arbiter."""

from __future__ import annotations

import json

import numpy as np
import pytest
from e2e_rig import CliRun

from carrt.arbitration import Arbiter, ArbiterInputs
from carrt.clock import SimClock
from carrt.config import CarConfig, load
from carrt.episodes.reader import list_episodes, read_episode
from carrt.episodes.writer import EpisodeWriter
from carrt.interfaces import JoystickEvents, JoystickState, Mode
from carrt.loop import SECTIONS, ControlLoop, LoopParts
from carrt.sim.camera import SimCamera
from carrt.sim.plant import SimPlant
from carrt.sim.render import Renderer
from carrt.sim.world import SimWorld
from firmware_bridge import messages as m
from firmware_bridge.direct import DirectBoardLink


class ScriptedPad:
    """Sticks and button presses by tick number: arm at 5, drive a few metres straight (the
    fence is not far: a car pushed against it makes the board fail safe on a stall), disarm."""

    def __init__(self) -> None:
        self.polls = 0

    def start(self, on_estop) -> None:
        pass

    def stop(self) -> None:
        pass

    def poll(self) -> JoystickState:
        k, self.polls = self.polls, self.polls + 1
        sticks = (0.0, 0.3) if 8 <= k < 22 else (0.0, 0.0)
        events = JoystickEvents(arm=k in (5, 40), lap=k == 20)
        return JoystickState(True, *sticks, neutral_since_connect=True, events=events)


@pytest.fixture
def built(tmp_path):
    config = load(None, ["pwm.max_forward=1.0"])
    plant = SimPlant(SimWorld(layout="empty", seed=0))
    clock = SimClock(step_s=0.002)
    link = DirectBoardLink(plant, clock).open()
    camera = SimCamera(plant, Renderer(plant.world.track), clock, realtime=False)
    camera.start()
    writer = EpisodeWriter(tmp_path / "eps")
    parts = LoopParts(clock=clock, camera=camera, link=link, joystick=ScriptedPad(), sink=writer)
    loop = ControlLoop(parts, config, allow_auto=False, record=True, max_steps=50)
    yield loop, plant, tmp_path / "eps"
    camera.stop()
    writer.close()
    link.close()


def test_a_tick_senses_decides_actuates_and_records(built):
    loop, _, eps = built
    summary = loop.run()
    loop.parts.sink.flush()
    assert summary.steps == 50 and summary.overruns == 0
    assert summary.max_tick_lateness_ms == pytest.approx(0.0, abs=1e-6), "the simulated clock"
    assert all(summary.sections_ms[name][0] > 0 for name in SECTIONS), summary.sections_ms
    assert summary.episodes == 1 and summary.laps == 0
    (path,) = list_episodes(eps)
    ep = read_episode(path)
    assert ep.end_reason == "disarmed"
    modes = ep.steps["mode"]
    assert (modes[:-1] == Mode.MANUAL).all() and modes[-1] == Mode.DISARMED, (
        "the episode begins when the board is armed and ends with the disarm's step"
    )
    sticks = np.isclose(ep.steps["human_action"][:, 1], 0.3)
    assert sticks.sum() >= 10
    np.testing.assert_allclose(ep.steps["executed_action"][sticks], [[0.0, 0.3]] * sticks.sum())
    assert ep.steps["lap"].sum() == 1 and ep.steps["speed_mps"].max() > 0.3
    assert loop.parts.link.board_state == m.State.DISARMED
    assert loop.live.mode == Mode.DISARMED and loop.live.episodes == 1


def test_recorded_steps_replay_through_the_arbiter(tmp_path):
    """An expert recording (noise injection on): fed back through a fresh arbiter with the
    recorded sticks, every MANUAL step's decision is the recorded person's command, and what
    was executed differs from it only by the recorded noise."""
    out = tmp_path / "rec"
    code = CliRun(
        ["teleop", "--sim", "--expert", "auto", "--record", "--layout", "easy", "--episodes", "1",
         "--out", str(out), "--set", "noise.period_s=2.0"]
    ).result(timeout_s=120)  # fmt: skip
    assert code == 0
    (path,) = list_episodes(out)
    steps = read_episode(path).steps
    config = CarConfig()
    arbiter = Arbiter(allow_auto=False, camera=config.camera, encoder=config.encoder)
    arm = JoystickState(True, 0.0, 0.0, True, JoystickEvents(arm=True))
    arbiter.step(_inputs(0.0, arm, m.State.DISARMED))
    replayed = 0
    for k, rec in enumerate(steps):
        if rec["mode"] != Mode.MANUAL:
            continue
        sticks = JoystickState(True, *map(float, rec["human_action"]), True, JoystickEvents())
        decision = arbiter.step(_inputs(0.1 * (k + 1), sticks, m.State.ARMED))
        assert decision.mode == Mode.MANUAL
        assert (decision.steering, decision.throttle) == pytest.approx(tuple(rec["human_action"]))
        delta = np.abs(np.asarray(rec["executed_action"]) - rec["human_action"])
        assert (delta <= 0.3 + 1e-6).all() and (delta.max() < 1e-6 or rec["noise"])
        replayed += 1
    assert replayed > 50 and steps["noise"].any()
    assert json.loads((out / "sim_metrics.json").read_text())["laps"] == 1


def _inputs(now: float, joystick: JoystickState, board: m.State) -> ArbiterInputs:
    return ArbiterInputs(
        now=now, joystick=joystick, frame_age_s=0.01, camera_lost=False, telemetry_age_s=0.01,
        board_state=board,
    )  # fmt: skip


def test_both_links_are_boards_to_the_loop(built):
    """The Board contract (carrt/interfaces.py): the serial link and the in-process one."""
    from carrt.interfaces import Board
    from firmware_bridge.link import BoardLink

    loop, _, _ = built
    assert isinstance(loop.parts.link, Board)
    members = [n for n in dir(Board) if not n.startswith("_")] + ["counters", "error"]
    link = BoardLink("/dev/null/none")  # not opened: the contract is its shape
    assert all(hasattr(link, name) for name in members), members
