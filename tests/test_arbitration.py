"""Safety arbitration (DESIGN §4, §5): every rule, pure and fast, plus the e-stop fast path."""

from __future__ import annotations

import math
import threading
from dataclasses import replace

import numpy as np
import pytest

from carrt.arbitration import BOARD_GRACE_S, Arbiter, ArbiterInputs, Decision
from carrt.config import CameraConfig, EncoderConfig
from carrt.interfaces import JoystickEvents, JoystickState, Mode
from firmware_bridge.messages import Reason, State

CAMERA = CameraConfig(max_age_s=0.15)
ENCODER = EncoderConfig(max_age_s=0.1)


def pad(steering=0.0, throttle=0.0, *, connected=True, neutral=True, **edges) -> JoystickState:
    return JoystickState(
        connected=connected,
        steering=steering,
        throttle=throttle,
        neutral_since_connect=neutral,
        events=JoystickEvents(**edges),
    )


class Rig:
    """An arbiter, a clock, and the last inputs; each call to `tick` is one 10 Hz step."""

    def __init__(self, *, allow_auto=True, deadzone=0.0):
        self.estops: list[str] = []
        self.arbiter = Arbiter(
            allow_auto=allow_auto,
            camera=CAMERA,
            encoder=ENCODER,
            deadzone=deadzone,
            on_estop=lambda: self.estops.append(threading.current_thread().name),
        )
        self.now = 100.0
        self.board = State.DISARMED

    def tick(self, js: JoystickState | None = None, **fields) -> Decision:
        self.now += 0.1
        fields.setdefault("board_state", self.board)
        inputs = ArbiterInputs(
            now=self.now,
            joystick=js if js is not None else pad(),
            frame_age_s=fields.pop("frame_age_s", 0.03),
            camera_lost=fields.pop("camera_lost", False),
            telemetry_age_s=fields.pop("telemetry_age_s", 0.01),
            **fields,
        )
        return self.arbiter.step(inputs)

    def arm(self) -> Decision:
        decision = self.tick(pad(arm=True))
        assert decision.mode == Mode.MANUAL and decision.arm_request, decision
        self.board = State.ARMED
        return decision

    def auto(self) -> Decision:
        self.arm()
        decision = self.tick(pad(toggle_auto=True), plan_action=(0.1, 0.4))
        assert decision.mode == Mode.AUTO, decision
        return decision


# ----------------------------------------------------------------------------- disarmed, arming
def test_starts_disarmed_and_neutral():
    rig = Rig()
    d = rig.tick(pad(0.5, 0.5))
    assert (d.mode, d.steering, d.throttle, d.source) == (Mode.DISARMED, 0.0, 0.0, "neutral")
    assert d.reason and not d.arm_request


def test_arm_gives_manual_with_the_human_sticks():
    rig = Rig()
    rig.arm()
    d = rig.tick(pad(-0.4, 0.6))
    assert (d.mode, d.source, d.steering, d.throttle) == (Mode.MANUAL, "human", -0.4, 0.6)
    assert d.reason == ""


@pytest.mark.parametrize(
    ("js", "board", "words"),
    [
        (pad(connected=False, arm=True), State.DISARMED, "no joystick"),
        (pad(neutral=False, arm=True), State.DISARMED, "neutral"),
        (pad(0.0, 0.3, arm=True), State.DISARMED, "sticks not at neutral"),
        (pad(0.2, 0.0, arm=True), State.DISARMED, "sticks not at neutral"),
        (pad(arm=True), State.FAILSAFE, "clear first"),
    ],
)
def test_arming_refused_with_a_reason(js, board, words):
    rig = Rig()
    d = rig.tick(js, board_state=board)
    assert d.mode == Mode.DISARMED and not d.arm_request
    assert words in d.refused
    assert (d.steering, d.throttle) == (0.0, 0.0)


def test_stuck_axis_after_reconnect_cannot_arm_until_moved_back():
    rig = Rig()
    assert "neutral" in rig.tick(pad(0.0, 1.0, neutral=False, arm=True)).refused
    assert rig.tick(pad(arm=True)).mode == Mode.MANUAL  # pad reported neutral: now it may


def test_deadzone_margin_for_sources_without_one():
    rig = Rig(deadzone=0.1)
    assert rig.tick(pad(0.05, -0.08, arm=True)).mode == Mode.MANUAL


def test_arm_edge_while_driving_disarms():
    rig = Rig()
    rig.arm()
    d = rig.tick(pad(0.3, 0.3, arm=True))
    assert d.mode == Mode.DISARMED and d.disarm_request
    assert (d.steering, d.throttle) == (0.0, 0.0)
    rig.auto()
    d = rig.tick(pad(arm=True))
    assert d.mode == Mode.DISARMED and d.disarm_request


# ----------------------------------------------------------------------------- auto, override
def test_teleop_never_enters_auto():
    rig = Rig(allow_auto=False)
    rig.arm()
    d = rig.tick(pad(toggle_auto=True), plan_action=(0.1, 0.1))
    assert d.mode == Mode.MANUAL and "teleop" in d.refused


@pytest.mark.parametrize(
    ("fields", "words"),
    [
        ({"frame_age_s": None}, "no camera frame"),
        ({"frame_age_s": 0.2}, "camera frame 200 ms old"),
        ({"telemetry_age_s": 0.15}, "telemetry 150 ms old"),
        ({"telemetry_age_s": math.inf}, "no telemetry"),
        ({"camera_lost": True}, "camera lost"),
    ],
)
def test_auto_needs_a_fresh_frame_and_fresh_telemetry(fields, words):
    rig = Rig()
    rig.arm()
    d = rig.tick(pad(toggle_auto=True), **fields)
    assert d.mode == Mode.MANUAL and words in d.refused


def test_auto_refused_with_sticks_out_and_before_arming():
    rig = Rig()
    assert "arm first" in rig.tick(pad(toggle_auto=True)).refused
    rig.arm()
    assert "release the sticks" in rig.tick(pad(0.5, 0.0, toggle_auto=True)).refused


def test_auto_drives_the_plan_and_toggle_returns_to_manual():
    rig = Rig()
    d = rig.auto()
    assert (d.source, d.steering, d.throttle) == ("policy", 0.1, 0.4)
    d = rig.tick(pad(0.2, 0.3, toggle_auto=False), plan_action=(0.5, 0.5))
    assert d.mode == Mode.MANUAL and d.override  # sticks moved: that is an intervention
    rig.tick(pad(toggle_auto=True), plan_action=(0.1, 0.1))
    d = rig.tick(pad(toggle_auto=True), plan_action=(0.1, 0.1))
    assert d.mode == Mode.MANUAL and not d.override  # a deliberate switch, not an intervention
    assert rig.arbiter.interventions == 1


def test_stick_beyond_deadzone_in_auto_hands_over_and_counts():
    rig = Rig()
    rig.auto()
    d = rig.tick(pad(0.0, 0.0), plan_action=(0.2, 0.5))
    assert d.mode == Mode.AUTO and not d.override
    d = rig.tick(pad(-0.6, 0.2), plan_action=(0.2, 0.5))
    assert (d.mode, d.source, d.steering, d.throttle) == (Mode.MANUAL, "human", -0.6, 0.2)
    assert d.override and rig.arbiter.interventions == 1
    d = rig.tick(pad(-0.6, 0.2), plan_action=(0.2, 0.5))
    assert d.mode == Mode.MANUAL and not d.override  # the edge is reported once
    for expected in (2, 3):
        rig.tick(pad(toggle_auto=True), plan_action=(0.1, 0.1))
        assert rig.tick(pad(0.0, -0.5), plan_action=(0.1, 0.1)).override
        assert rig.arbiter.interventions == expected


def test_override_respects_the_deadzone_margin():
    rig = Rig(deadzone=0.1)
    rig.auto()
    assert rig.tick(pad(0.08, 0.0), plan_action=(0.0, 0.3)).mode == Mode.AUTO
    assert rig.tick(pad(0.12, 0.0), plan_action=(0.0, 0.3)).override


@pytest.mark.parametrize(
    ("fields", "words"),
    [
        ({"frame_age_s": None}, "no camera frame"),
        ({"frame_age_s": 0.16}, "camera frame 160 ms old"),
        ({"telemetry_age_s": 0.11}, "telemetry 110 ms old"),
    ],
)
def test_stale_inputs_in_auto_give_neutral_with_a_reason(fields, words):
    rig = Rig()
    rig.auto()
    d = rig.tick(plan_action=(0.5, 0.5), **fields)
    assert d.mode == Mode.AUTO and (d.steering, d.throttle, d.source) == (0.0, 0.0, "neutral")
    assert words in d.reason
    d = rig.tick(plan_action=(0.5, 0.5))
    assert d.source == "policy" and d.reason == ""


def test_fresh_enough_is_fresh():
    rig = Rig()
    rig.auto()
    d = rig.tick(plan_action=(0.5, 0.5), frame_age_s=0.15, telemetry_age_s=0.1)
    assert d.source == "policy"


def test_fallback_used_once_per_missing_plan():
    rig = Rig()
    rig.auto()
    d = rig.tick(plan_action=None, fallback_action=(0.3, 0.6))
    assert (d.source, d.steering, d.throttle) == ("plan-fallback", 0.3, 0.6)
    d = rig.tick(plan_action=None, fallback_action=(0.35, 0.6))  # loop offers it again: no
    assert d.source == "neutral" and "used already" in d.reason
    d = rig.tick(plan_action=None, fallback_action=None)
    assert d.source == "neutral" and d.reason == "no plan this tick"
    assert rig.tick(plan_action=(0.1, 0.2)).source == "policy"
    d = rig.tick(plan_action=None, fallback_action=(0.2, 0.2))  # a new plan re-arms the fallback
    assert d.source == "plan-fallback"


def test_policy_outputs_are_clamped_and_nan_is_neutral():
    rig = Rig()
    rig.auto()
    d = rig.tick(plan_action=(1.7, -3.0))
    assert (d.steering, d.throttle) == (1.0, -1.0)
    d = rig.tick(plan_action=(float("nan"), 0.5))
    assert (d.steering, d.throttle, d.source) == (0.0, 0.0, "neutral")
    assert "finite" in d.reason


def test_human_outputs_are_clamped():
    rig = Rig()
    rig.arm()
    d = rig.tick(pad(1.3, -1.2))
    assert (d.steering, d.throttle) == (1.0, -1.0)


# ----------------------------------------------------------------------------- e-stop
def test_estop_button_latches_and_survives_everything_but_clear():
    rig = Rig()
    rig.arm()
    d = rig.tick(pad(0.5, 0.5, estop=True))
    assert d.mode == Mode.ESTOP and d.estop and (d.steering, d.throttle) == (0.0, 0.0)
    assert rig.estops == ["MainThread"] and "e-stop button" in rig.arbiter.estop_reason
    rig.board = State.ESTOP
    for js in (
        pad(arm=True),
        pad(toggle_auto=True),
        pad(0.8, 0.8),
        pad(connected=False),
        pad(neutral=False, arm=True),
    ):
        d = rig.tick(js, plan_action=(0.4, 0.4), fallback_action=(0.4, 0.4))
        assert d.mode == Mode.ESTOP and (d.steering, d.throttle) == (0.0, 0.0)
        assert not d.arm_request and not d.estop  # the latch edge was reported once
    for board in State:
        assert rig.tick(board_state=board).mode == Mode.ESTOP
    assert rig.estops == ["MainThread"]  # once per latch, however often it is re-asserted
    d = rig.tick(pad(clear=True))
    assert d.mode == Mode.DISARMED and d.clear_request and not d.arm_request


@pytest.mark.parametrize(
    ("js", "words"),
    [(pad(connected=False, clear=True), "no joystick"), (pad(0.0, 0.4, clear=True), "neutral")],
)
def test_clear_refused_without_a_pad_or_with_sticks_out(js, words):
    rig = Rig()
    rig.arbiter.estop("test")
    d = rig.tick(js)
    assert d.mode == Mode.ESTOP and not d.clear_request and words in d.refused


def test_clear_then_a_separate_arm_never_straight_to_driving():
    rig = Rig()
    rig.arm()
    rig.tick(pad(estop=True))
    rig.board = State.ESTOP
    d = rig.tick(pad(arm=True))
    assert d.mode == Mode.ESTOP and "clear first" in d.refused
    d = rig.tick(pad(clear=True, arm=True))
    assert d.mode == Mode.DISARMED and d.clear_request and not d.arm_request
    assert "separate press" in d.refused
    d = rig.tick(pad(arm=True))  # telemetry has not caught up with the clear yet
    assert d.mode == Mode.DISARMED and "waiting for the board" in d.refused
    rig.board = State.DISARMED
    assert rig.tick(pad(arm=True)).mode == Mode.MANUAL


def test_board_still_in_estop_long_after_a_clear_relatches():
    rig = Rig()
    rig.arbiter.estop("test")
    rig.board = State.ESTOP
    assert rig.tick(pad(clear=True)).mode == Mode.DISARMED
    ticks = 0
    while rig.tick().mode == Mode.DISARMED:
        ticks += 1
        assert ticks < 100
    assert ticks * 0.1 == pytest.approx(BOARD_GRACE_S, abs=0.15)
    assert "did not leave e-stop" in rig.arbiter.estop_reason
    assert len(rig.estops) == 2


def test_joystick_disconnected_while_driving_estops():
    for mode in ("manual", "auto"):
        rig = Rig()
        rig.auto() if mode == "auto" else rig.arm()
        d = rig.tick(pad(connected=False), plan_action=(0.2, 0.2))
        assert d.mode == Mode.ESTOP and d.estop
        assert rig.arbiter.estop_reason == "joystick disconnected" and len(rig.estops) == 1


def test_no_pad_at_start_is_disarmed_not_estop():
    rig = Rig()
    d = rig.tick(pad(connected=False, neutral=False))
    assert d.mode == Mode.DISARMED and d.reason == "no joystick connected"
    assert rig.estops == []


def test_board_estop_latches_host_estop():
    rig = Rig()
    rig.arm()
    d = rig.tick(pad(0.3, 0.3), board_state=State.ESTOP)
    assert d.mode == Mode.ESTOP and "board" in rig.arbiter.estop_reason and rig.estops


def test_camera_lost_estops_in_auto_only():
    rig = Rig()
    rig.arm()
    assert rig.tick(pad(0.2, 0.2), camera_lost=True).mode == Mode.MANUAL
    rig = Rig()
    rig.auto()
    d = rig.tick(camera_lost=True, plan_action=(0.2, 0.2))
    assert d.mode == Mode.ESTOP and rig.arbiter.estop_reason == "camera lost"


# ----------------------------------------------------------------------------- the board
def test_board_failsafe_disarms_with_its_reason_and_needs_clear_then_arm():
    rig = Rig()
    rig.auto()
    rig.board = State.FAILSAFE
    d = rig.tick(plan_action=(0.3, 0.3), board_reason=Reason.LINK_TIMEOUT)
    assert d.mode == Mode.DISARMED and d.disarm_request and "link timeout" in d.reason
    assert rig.estops == []
    d = rig.tick(pad(arm=True), board_reason=Reason.LINK_TIMEOUT)
    assert d.mode == Mode.DISARMED and "clear first" in d.refused
    d = rig.tick(pad(clear=True))
    assert d.clear_request and d.mode == Mode.DISARMED
    rig.board = State.DISARMED
    assert rig.tick(pad(arm=True)).mode == Mode.MANUAL


def test_board_failsafe_without_a_reason_from_the_loop():
    rig = Rig()
    rig.arm()
    d = rig.tick(board_state=State.FAILSAFE)
    assert d.mode == Mode.DISARMED and d.reason == "board failsafe: clear, then arm"


def test_clear_when_nothing_is_latched_is_refused():
    rig = Rig()
    d = rig.tick(pad(clear=True))
    assert not d.clear_request and "nothing to clear" in d.refused


def test_board_that_never_arms_or_disarms_later_takes_the_host_down():
    rig = Rig()
    assert rig.tick(pad(arm=True)).mode == Mode.MANUAL  # board stays DISARMED (refused)
    modes = [rig.tick().mode for _ in range(15)]
    assert modes[0] == Mode.MANUAL and modes[-1] == Mode.DISARMED
    assert "did not arm" in rig.tick().reason
    rig = Rig()
    rig.arm()
    rig.tick()
    d = rig.tick(board_state=State.DISARMED)  # e.g. the board rebooted
    assert d.mode == Mode.DISARMED and d.disarm_request and "board disarmed" in d.reason


# ----------------------------------------------------------------------------- threads
def test_estop_from_another_thread_latches_once_while_step_runs():
    rig = Rig()
    rig.auto()
    stop = threading.Event()
    decisions: list[Decision] = []

    def loop():
        while not stop.is_set():
            decisions.append(rig.tick(plan_action=(0.3, 0.5)))

    looper = threading.Thread(target=loop, name="loop")
    looper.start()
    try:
        while len(decisions) < 200:
            threading.Event().wait(0.001)
        callers = [
            threading.Thread(target=rig.arbiter.estop, name=f"pad{i}", args=("pad",))
            for i in range(4)
        ]
        for thread in callers:
            thread.start()
        for thread in callers:
            thread.join()
        n = len(decisions)
        while len(decisions) < n + 200:
            threading.Event().wait(0.001)
    finally:
        stop.set()
        looper.join()
    assert len(rig.estops) == 1 and rig.estops[0].startswith("pad")  # the caller's thread
    first = next(i for i, d in enumerate(decisions) if d.mode == Mode.ESTOP)
    assert all(d.mode == Mode.ESTOP for d in decisions[first:])
    assert all(d.throttle == 0.0 and d.steering == 0.0 for d in decisions[first:])
    assert [i for i, d in enumerate(decisions) if d.estop] == [first]
    assert all(d.source == "policy" for d in decisions[:first])


def test_estop_fast_path_then_button_edge_is_one_latch():
    rig = Rig()
    rig.arm()
    rig.arbiter.estop()  # the joystick's reader thread, before the loop polls the pad
    assert rig.arbiter.mode == Mode.ESTOP and len(rig.estops) == 1
    d = rig.tick(pad(estop=True))
    assert d.estop and d.mode == Mode.ESTOP and len(rig.estops) == 1
    assert "joystick" in rig.arbiter.estop_reason
    rig.tick(pad(clear=True))
    rig.arbiter.estop("again")
    assert len(rig.estops) == 2  # a new latch after a clear calls through again


def test_inputs_are_plain_values():
    inputs = ArbiterInputs(
        now=0.0,
        joystick=pad(),
        frame_age_s=None,
        camera_lost=False,
        telemetry_age_s=math.inf,
        board_state=State.DISARMED,
    )
    assert replace(inputs, now=1.0).now == 1.0 and inputs.plan_action is None


def test_a_braking_policy_reaches_the_board_command_negative(tmp_path):
    """Negative throttle (brake/reverse) from an ONNX policy survives predict, the arbiter in
    AUTO and the link's fixed-point command; the board then caps it at config max_reverse."""
    from onnx_models import build_policy

    from carrt.policy import OnnxPolicy
    from firmware_bridge.link import _to_fixed
    from firmware_bridge.messages import SCALE

    policy = OnnxPolicy(
        build_policy(tmp_path / "brake.onnx", throttle=(-0.6, 0.0), throttle_clip=None)
    )
    mu = policy.predict(np.full((96, 96, 3), 9, np.uint8), 0.0).mu
    rig = Rig()
    rig.auto()
    d = rig.tick(plan_action=(float(mu[0, 0]), float(mu[0, 1])))
    assert d.source == "policy" and d.throttle == pytest.approx(-0.6)
    assert _to_fixed(d.throttle) == -round(0.6 * SCALE)
