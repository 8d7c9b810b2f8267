"""The first hour of a new user with no car (issue 58, item 8), each point as it was met: the
live view's example runs at the speed of life, a parked car names the key that arms it, a
forgotten --model is one line, and a lap count beside no lap times explains itself."""

from __future__ import annotations

import types

import pytest
from arbiter_rig import CAMERA, ENCODER, pad

from carrt.arbitration import Arbiter, ArbiterInputs, arm_hint
from carrt.cli import main
from carrt.config import CarConfig
from carrt.joystick import PygameJoystick
from carrt.loop import ControlLoop, LoopParts
from carrt.reasons import Why
from carrt.sim.keyboard import CONTROLS, KeyboardPad
from carrt.sim.metrics import SimMetrics, format_metrics
from firmware_bridge.link_types import LinkCounters
from firmware_bridge.messages import State


def test_drive_without_model_is_one_line_and_exit_2(capsys):
    assert main(["drive", "--sim"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("carrt drive: error: --model"), err
    assert "usage:" not in err


def test_a_live_view_runs_the_simulator_in_real_time(capsys):
    """The README's example, `carrt drive --sim --autopilot --model demo --view 8090`, on a
    free port: without the view it runs on the simulated clock (tests/test_rigs.py)."""
    argv = ["drive", "--sim", "--autopilot", "--model", "demo", "--view", "0", "--duration", "1"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "in real time, virtual board on" in out, out
    assert "simulated clock" not in out


def parked_reason(controls, *, allow_auto=True) -> str:
    arbiter = Arbiter(allow_auto=allow_auto, camera=CAMERA, encoder=ENCODER, controls=controls)
    decision = arbiter.step(
        ArbiterInputs(
            now=100.0,
            joystick=pad(),
            frame_age_s=0.03,
            camera_lost=False,
            telemetry_age_s=0.01,
            board_state=State.DISARMED,
        )
    )
    return decision.reason


def test_the_keyboard_window_names_its_keys_for_arm_and_auto():
    assert KeyboardPad.controls is CONTROLS
    reason = parked_reason(CONTROLS)
    assert reason.why is Why.NOT_ARMED_THEN_AUTO
    assert reason == "not armed yet: press Enter to arm (sticks at neutral), then Tab for AUTO"
    teleop = parked_reason(CONTROLS, allow_auto=False)
    assert teleop.why is Why.NOT_ARMED and "Tab" not in teleop, "teleop has no AUTO"


@pytest.mark.parametrize(
    ("preset", "arm", "auto"), [("xbox", "Start", "Y"), ("ps4", "Options", "triangle")]
)
def test_a_pad_names_its_buttons_from_its_preset(preset, arm, auto):
    config = CarConfig().joystick
    joystick = PygameJoystick(type(config)(**{**vars(config), "preset": preset}))
    assert joystick.controls["arm"] == arm and joystick.controls["auto"] == auto
    assert f"press {arm} to arm" in parked_reason(joystick.controls)
    moved = type(config)(**{**vars(config), "preset": preset, "arm_button": 0})
    assert PygameJoystick(moved).controls["arm"] in ("A", "cross"), "an override is named too"


def test_the_loop_hands_the_joysticks_keys_to_the_arbiter():
    link = types.SimpleNamespace(estop=lambda: None, counters=LinkCounters())  # a Board's part
    joystick = types.SimpleNamespace(controls={"arm": "the red key", "auto": "the blue key"})
    parts = LoopParts(clock=None, camera=None, link=link, joystick=joystick)
    loop = ControlLoop(parts, CarConfig(), allow_auto=True, record=False)
    assert loop.arbiter._why == arm_hint(joystick.controls, allow_auto=True)
    assert "press the red key to arm" in loop.arbiter._why
    bare = ControlLoop(
        LoopParts(clock=None, camera=None, link=link, joystick=object()),
        CarConfig(),
        allow_auto=False,
        record=False,
    )
    assert "press the arm button to arm" in bare.arbiter._why


def _metrics(laps: int, lap_times: tuple[float, ...]) -> str:
    m = SimMetrics(1.0, 2.0, 1.0, lap_times, laps, 1, 0, None, 10.0, 10.0)
    return next(line for line in format_metrics(m).splitlines() if line.startswith("laps"))


def test_laps_without_clean_ones_say_why_there_are_no_times():
    assert _metrics(3, ()) == (
        "laps             3 (no clean lap: every lap had a collision or take-over)"
    )
    assert _metrics(3, (12.0, 12.5)) == (
        "laps             3 (2 clean, without a collision or take-over: 12.00, 12.50 s)"
    )
    assert _metrics(2, (12.0, 12.5)) == "laps             2 (all clean, lap times 12.00, 12.50 s)"
    assert _metrics(0, ()) == "laps             0"
