"""Safety arbitration (DESIGN §4, §5): every rule for arming, AUTO and the sticks, pure and fast.

Arming needs a pad at neutral and a board that is not latched; AUTO needs a fresh frame and
fresh telemetry, drives the plan (clamped, NaN is neutral, one fallback per missing plan) and
hands over to a stick beyond the deadzone. The e-stop, the board's states and the threads are
in test_arbitration_estop.py.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from arbiter_rig import Rig, pad, why

from carrt.arbitration import ArbiterInputs
from carrt.interfaces import Mode
from carrt.reasons import Why
from firmware_bridge.messages import State


# ----------------------------------------------------------------------------- disarmed, arming
def test_starts_disarmed_and_neutral():
    rig = Rig()
    d = rig.tick(pad(0.5, 0.5))
    assert (d.mode, d.steering, d.throttle, d.source) == (Mode.DISARMED, 0.0, 0.0, "neutral")
    assert why(d.reason) is Why.NOT_ARMED_THEN_AUTO and not d.arm_request


def test_arm_gives_manual_with_the_human_sticks():
    rig = Rig()
    rig.arm()
    d = rig.tick(pad(-0.4, 0.6))
    assert (d.mode, d.source, d.steering, d.throttle) == (Mode.MANUAL, "human", -0.4, 0.6)
    assert d.reason == ""


@pytest.mark.parametrize(
    ("js", "board", "reason"),
    [
        (pad(connected=False, arm=True), State.DISARMED, Why.ARM_NO_JOYSTICK),
        (pad(neutral=False, arm=True), State.DISARMED, Why.ARM_PAD_NEVER_NEUTRAL),
        (pad(0.0, 0.3, arm=True), State.DISARMED, Why.ARM_STICKS_OUT),
        (pad(0.2, 0.0, arm=True), State.DISARMED, Why.ARM_STICKS_OUT),
        (pad(arm=True), State.FAILSAFE, Why.ARM_BOARD_LATCHED),
    ],
)
def test_arming_refused_with_a_reason(js, board, reason):
    rig = Rig()
    d = rig.tick(js, board_state=board)
    assert d.mode == Mode.DISARMED and not d.arm_request
    assert why(d.refused) is reason
    assert (d.steering, d.throttle) == (0.0, 0.0)


def test_stuck_axis_after_reconnect_cannot_arm_until_moved_back():
    rig = Rig()
    assert (
        why(rig.tick(pad(0.0, 1.0, neutral=False, arm=True)).refused) is Why.ARM_PAD_NEVER_NEUTRAL
    )
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
    assert d.mode == Mode.MANUAL and why(d.refused) is Why.AUTO_IN_TELEOP


@pytest.mark.parametrize(
    ("fields", "reason", "measured"),
    [
        ({"frame_age_s": None}, Why.AUTO_NO_FRAME, {}),
        ({"frame_age_s": 0.2}, Why.AUTO_FRAME_OLD, {"age_ms": 200}),
        ({"telemetry_age_s": 0.15}, Why.AUTO_TELEMETRY_OLD, {"age_ms": 150}),
        ({"telemetry_age_s": math.inf}, Why.AUTO_NO_TELEMETRY, {}),
        ({"camera_lost": True}, Why.AUTO_CAMERA_LOST, {}),
    ],
)
def test_auto_needs_a_fresh_frame_and_fresh_telemetry(fields, reason, measured):
    rig = Rig()
    rig.arm()
    d = rig.tick(pad(toggle_auto=True), **fields)
    assert d.mode == Mode.MANUAL and why(d.refused) is reason
    assert d.refused == reason.text(**measured)  # a refusal says how old


def test_auto_refused_with_sticks_out_and_before_arming():
    rig = Rig()
    assert why(rig.tick(pad(toggle_auto=True)).refused) is Why.AUTO_BEFORE_ARM
    rig.arm()
    assert why(rig.tick(pad(0.5, 0.0, toggle_auto=True)).refused) is Why.AUTO_STICKS_OUT


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
    ("fields", "reason", "measured"),
    [
        ({"frame_age_s": None}, Why.NO_FRAME, {}),
        ({"frame_age_s": 0.16}, Why.FRAME_OLDER_THAN, {"limit_ms": 150}),
        ({"frame_age_s": 0.9}, Why.FRAME_OLDER_THAN, {"limit_ms": 150}),  # the same: said once
        ({"telemetry_age_s": 0.11}, Why.TELEMETRY_OLDER_THAN, {"limit_ms": 100}),
    ],
)
def test_stale_inputs_in_auto_give_neutral_with_a_reason(fields, reason, measured):
    rig = Rig()
    rig.auto()
    d = rig.tick(plan_action=(0.5, 0.5), **fields)
    assert d.mode == Mode.AUTO and (d.steering, d.throttle, d.source) == (0.0, 0.0, "neutral")
    assert why(d.reason) is reason and d.reason == reason.text(**measured)
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
    assert d.source == "neutral" and why(d.reason) is Why.PLAN_USED_ALREADY
    d = rig.tick(plan_action=None, fallback_action=None)
    assert d.source == "neutral" and why(d.reason) is Why.NO_PLAN
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
    assert why(d.reason) is Why.POLICY_NOT_FINITE


def test_human_outputs_are_clamped():
    rig = Rig()
    rig.arm()
    d = rig.tick(pad(1.3, -1.2))
    assert (d.steering, d.throttle) == (1.0, -1.0)


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


def test_a_reason_is_its_words_and_its_name():
    """What the person reads is the member's text, unchanged through an f-string (the log
    line), JSON (the live view) and pickle (a copy in another process); code compares the name."""
    import json
    import pickle

    reason = Why.AUTO_FRAME_OLD.text(age_ms=212.4)
    assert reason == "auto refused: camera frame 212 ms old" and f"{reason}" == reason
    assert json.loads(json.dumps({"why": reason})) == {"why": str(reason)}
    again = pickle.loads(pickle.dumps(reason))
    assert again == reason and why(again) is Why.AUTO_FRAME_OLD
    assert Why.NO_PLAN.text() is Why.NO_PLAN.text(), "a fixed reason is made once"
