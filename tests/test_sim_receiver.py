"""The car's RC transmitter as the person's controls, end to end on the simulator: the stand-in
radio's pulses go into the board's receiver pins (the C core), the board rules on them, and the
host reads the receiver back from TELEMETRY through the same Joystick contract as the pad."""

from __future__ import annotations

import numpy as np
import pytest
from e2e_rig import CliRun
from onnx_models import build_policy

from carrt import config as car_config
from carrt.clock import SimClock
from carrt.config import ReceiverConfig
from carrt.episodes.reader import list_episodes, read_episode
from carrt.interfaces import Mode
from carrt.receiver import ReceiverControls, stick
from firmware_bridge import messages as m
from firmware_bridge.direct import DirectBoardLink
from firmware_bridge.drivetrain import WheelPlant


def test_a_pulse_maps_onto_the_stick_with_the_boards_deadzone():
    assert stick(1560, 1000, 1500, 2000, 60) == 0.0  # inside the deadzone: the board's too
    assert stick(1561, 1000, 1500, 2000, 60) == pytest.approx(1 / 440)
    assert stick(2000, 1000, 1500, 2000, 60) == 1.0
    assert stick(1000, 1000, 1500, 2000, 60) == -1.0
    assert stick(1000, 2000, 1500, 1000, 60) == 1.0  # a reversed channel
    assert stick(2150, 1000, 1500, 2000, 60) == 1.0  # past the endpoint: clipped


class Bench:
    """A board (the C core, in-process) with a receiver on its pins, and the host's reading."""

    def __init__(self, *, allow_auto: bool = False) -> None:
        self.clock = SimClock(step_s=0.002)
        self.link = DirectBoardLink(WheelPlant(), self.clock).open()
        self.config = ReceiverConfig(controls="receiver")
        car = car_config.CarConfig(receiver=self.config)
        assert self.link.send_config(car_config.board_config(car)).result == 0
        self.controls = ReceiverControls(
            self.link, self.config, self.clock.now, allow_auto=allow_auto
        )

    def radio(self, steer_us: int, throttle_us: int, switch_us: int = 1000) -> None:
        self.link.set_receiver(steer_us, throttle_us, switch_us)

    def run(self, seconds: float):
        """Advance in 10 Hz ticks, polling the controls as the loop does; every state seen."""
        states = []
        for _ in range(round(seconds / 0.1)):
            self.clock.advance(0.1)
            states.append(self.controls.poll())
        return states


def test_no_receiver_signal_is_a_disconnected_controller():
    bench = Bench()
    assert not any(s.connected for s in bench.run(0.5))


def test_the_sticks_and_the_switch_read_back_from_the_board():
    bench = Bench()
    bench.radio(1500, 1500)
    states = bench.run(0.5)
    assert states[-1].connected and states[-1].neutral_since_connect
    assert (states[-1].steering, states[-1].throttle) == (0.0, 0.0)
    bench.radio(1780, 1280)
    last = bench.run(0.3)[-1]
    assert last.steering == pytest.approx((280 - 60) / 440)
    assert last.throttle == pytest.approx(-(220 - 60) / 440)
    bench.radio(1500, 1500, 1900)  # the switch to its e-stop position
    states = bench.run(0.3)
    assert sum(s.events.estop for s in states) == 1
    assert bench.link.board_state == m.State.ESTOP  # the board latched it by itself
    bench.radio(1500, 1500, 1000)
    states = bench.run(0.3)
    assert sum(s.events.clear for s in states) == 1


def test_arming_is_steering_held_full_right_then_let_go():
    bench = Bench()
    bench.radio(1500, 1500)
    bench.run(0.5)
    bench.radio(2000, 1500)
    held = bench.run(0.9)  # not long enough
    bench.radio(1500, 1500)
    assert not any(s.events.arm for s in held + bench.run(0.3))
    bench.radio(2000, 1500)
    held = bench.run(1.2)
    assert not any(s.events.arm for s in held), "not while the stick is still over"
    bench.radio(1500, 1500)
    assert sum(s.events.arm for s in bench.run(0.3)) == 1


@pytest.mark.parametrize("allow_auto", [False, True])
def test_letting_go_after_the_receiver_drove_gives_the_wheels_back_only_in_drive(allow_auto):
    bench = Bench(allow_auto=allow_auto)
    bench.radio(1500, 1500)
    bench.run(0.5)
    bench.link.set_command(0.0, 0.0)
    bench.link.request_arm()  # the arm edge goes out with the next command
    bench.run(0.2)
    assert bench.link.board_state == m.State.ARMED
    bench.radio(1700, 1650)  # the person drives (MANUAL from the receiver)
    assert not any(s.events.toggle_auto for s in bench.run(1.0))
    bench.radio(1500, 1500)  # and lets go
    toggles = sum(s.events.toggle_auto for s in bench.run(1.0))
    assert toggles == (1 if allow_auto else 0)


def _episodes(out):
    return [read_episode(p) for p in list_episodes(out)]


def test_teleop_with_only_the_receiver_records_the_persons_commands(tmp_path):
    out = tmp_path / "teleop"
    code = CliRun(
        ["teleop", "--sim", "--expert", "auto", "--record", "--layout", "easy", "--duration",
         "20", "--out", str(out), "--set", "receiver.controls=receiver"]
    ).result(timeout_s=120)  # fmt: skip
    assert code == 0
    steps = np.concatenate([ep.steps for ep in _episodes(out)])
    manual = steps["mode"] == Mode.MANUAL
    assert manual.sum() >= 100, "driven by the transmitter for most of the run"
    human = steps["human_action"][manual]
    assert (np.abs(human[:, 1]) > 0.1).mean() > 0.5, "the person's throttle, read back"
    assert (np.abs(human[:, 0]) > 0.05).any(), "and their steering"
    # the board drove the sticks straight through: no noise was added, none is recorded
    assert not steps["noise"].any()
    assert np.allclose(human, steps["executed_action"][manual])


def test_drive_counts_receiver_takeovers_as_interventions_with_their_labels(tmp_path):
    model = build_policy(tmp_path / "crash.onnx", steering=0.0, throttle=(0.8, 0.0))
    out = tmp_path / "drive"
    run = CliRun(
        ["drive", "--sim", "--autopilot", "--expert-intervene", "--model", str(model), "--record",
         "--layout", "easy", "--duration", "25", "--out", str(out),
         "--set", "receiver.controls=receiver"]
    )  # fmt: skip
    assert run.result(timeout_s=120) == 0
    steps = np.concatenate([ep.steps for ep in _episodes(out)])
    override = steps["override"].astype(bool)
    assert override.sum() >= 2, "the expert took over through the transmitter, more than once"
    assert (steps["mode"] == Mode.AUTO).any(), "and gave the car back by letting go"
    human = steps["human_action"]
    assert (np.abs(human[override]).sum(axis=1) > 0).all(), "a take-over's label: the sticks"
    assert sum(int(ep.steps["collision"].any()) for ep in _episodes(out)) <= 1
