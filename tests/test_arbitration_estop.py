"""Safety arbitration (DESIGN §4, §5): the e-stop latch, the board's own states, and the e-stop
fast path from other threads.

The e-stop latches and survives everything but a clear at neutral followed by a separate arm;
a lost pad or camera while driving e-stops; the board's failsafe and e-stop reach the host, and
a board that never arms, disarms or leaves e-stop takes the host down. The rules for arming and
AUTO are in test_arbitration.py.
"""

from __future__ import annotations

import threading
from dataclasses import replace

import pytest
from arbiter_rig import Rig, pad, why

from carrt.arbitration import BOARD_GRACE_S, Decision
from carrt.interfaces import Mode
from carrt.reasons import Why
from firmware_bridge.messages import Reason, State


# ----------------------------------------------------------------------------- e-stop
def test_estop_button_latches_and_survives_everything_but_clear():
    rig = Rig()
    rig.arm()
    d = rig.tick(pad(0.5, 0.5, estop=True))
    assert d.mode == Mode.ESTOP and d.estop and (d.steering, d.throttle) == (0.0, 0.0)
    assert rig.estops == ["MainThread"] and why(rig.arbiter.estop_reason) is Why.ESTOP_BUTTON
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
    ("js", "reason"),
    [
        (pad(connected=False, clear=True), Why.CLEAR_NO_JOYSTICK),
        (pad(0.0, 0.4, clear=True), Why.CLEAR_STICKS_OUT),
    ],
)
def test_clear_refused_without_a_pad_or_with_sticks_out(js, reason):
    rig = Rig()
    rig.arbiter.estop("test")
    d = rig.tick(js)
    assert d.mode == Mode.ESTOP and not d.clear_request and why(d.refused) is reason


def test_clear_then_a_separate_arm_never_straight_to_driving():
    rig = Rig()
    rig.arm()
    rig.tick(pad(estop=True))
    rig.board = State.ESTOP
    d = rig.tick(pad(arm=True))
    assert d.mode == Mode.ESTOP and why(d.refused) is Why.ARM_WHILE_LATCHED
    d = rig.tick(pad(clear=True, arm=True))
    assert d.mode == Mode.DISARMED and d.clear_request and not d.arm_request
    assert why(d.refused) is Why.ARM_AFTER_CLEAR
    d = rig.tick(pad(arm=True))  # telemetry has not caught up with the clear yet
    assert d.mode == Mode.DISARMED and why(d.refused) is Why.ARM_BOARD_CATCHING_UP
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
    assert why(rig.arbiter.estop_reason) is Why.BOARD_KEPT_ESTOP
    assert len(rig.estops) == 2


def test_joystick_disconnected_while_driving_estops():
    for mode in ("manual", "auto"):
        rig = Rig()
        rig.auto() if mode == "auto" else rig.arm()
        d = rig.tick(pad(connected=False), plan_action=(0.2, 0.2))
        assert d.mode == Mode.ESTOP and d.estop
        assert why(rig.arbiter.estop_reason) is Why.JOYSTICK_DISCONNECTED
        assert len(rig.estops) == 1


def test_no_pad_at_start_is_disarmed_not_estop():
    rig = Rig()
    d = rig.tick(pad(connected=False, neutral=False))
    assert d.mode == Mode.DISARMED and why(d.reason) is Why.NO_JOYSTICK
    assert rig.estops == []


def test_board_estop_latches_host_estop():
    rig = Rig()
    rig.arm()
    d = rig.tick(pad(0.3, 0.3), board_state=State.ESTOP)
    assert d.mode == Mode.ESTOP and why(rig.arbiter.estop_reason) is Why.BOARD_ESTOP and rig.estops


def test_camera_lost_estops_in_auto_only():
    rig = Rig()
    rig.arm()
    assert rig.tick(pad(0.2, 0.2), camera_lost=True).mode == Mode.MANUAL
    rig = Rig()
    rig.auto()
    d = rig.tick(camera_lost=True, plan_action=(0.2, 0.2))
    assert d.mode == Mode.ESTOP and why(rig.arbiter.estop_reason) is Why.CAMERA_LOST


# ----------------------------------------------------------------------------- the board
def test_board_failsafe_disarms_with_its_reason_and_needs_clear_then_arm():
    rig = Rig()
    rig.auto()
    rig.board = State.FAILSAFE
    d = rig.tick(plan_action=(0.3, 0.3), board_reason=Reason.LINK_TIMEOUT)
    assert d.mode == Mode.DISARMED and d.disarm_request
    assert why(d.reason) is Why.BOARD_FAILSAFE_BECAUSE_HELD
    assert d.reason == Why.BOARD_FAILSAFE_BECAUSE_HELD.text(because="link timeout")
    assert rig.estops == []
    d = rig.tick(pad(arm=True), board_reason=Reason.LINK_TIMEOUT)
    assert d.mode == Mode.DISARMED and why(d.refused) is Why.ARM_BOARD_LATCHED
    d = rig.tick(pad(clear=True))
    assert d.clear_request and d.mode == Mode.DISARMED
    rig.board = State.DISARMED
    assert rig.tick(pad(arm=True)).mode == Mode.MANUAL


def test_board_failsafe_without_a_reason_from_the_loop():
    rig = Rig()
    rig.arm()
    d = rig.tick(board_state=State.FAILSAFE)
    assert d.mode == Mode.DISARMED and why(d.reason) is Why.BOARD_FAILSAFE_HELD


def test_clear_when_nothing_is_latched_is_refused():
    rig = Rig()
    d = rig.tick(pad(clear=True))
    assert not d.clear_request and why(d.refused) is Why.NOTHING_TO_CLEAR


def test_board_that_never_arms_or_disarms_later_takes_the_host_down():
    rig = Rig()
    assert rig.tick(pad(arm=True)).mode == Mode.MANUAL  # board stays DISARMED (refused)
    modes = [rig.tick().mode for _ in range(15)]
    assert modes[0] == Mode.MANUAL and modes[-1] == Mode.DISARMED
    assert why(rig.tick().reason) is Why.BOARD_DID_NOT_ARM
    rig = Rig()
    rig.arm()
    rig.tick()
    d = rig.tick(board_state=State.DISARMED)  # e.g. the board rebooted
    assert d.mode == Mode.DISARMED and d.disarm_request and why(d.reason) is Why.BOARD_DISARMED


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
    assert why(rig.arbiter.estop_reason) is Why.PAD_ESTOP
    rig.tick(pad(clear=True))
    rig.arbiter.estop("again")
    assert len(rig.estops) == 2  # a new latch after a clear calls through again


# ----------------------------------------------------------------------------- a rebooted board
REBOOTED = "board rebooted (brown-out; boot id 00000001 → 00000002): ..."


def test_a_reboot_disarms_with_its_line_and_keeps_it_until_the_next_arm():
    rig = Rig()
    rig.auto()
    gone = replace(pad(), connected=False, through_board=True)  # its receiver re-validating
    d = rig.tick(gone, board_rebooted=REBOOTED, board_state=State.DISARMED)
    assert (d.mode, d.disarm_request, d.reason) == (Mode.DISARMED, True, REBOOTED)
    assert why(d.reason) is Why.BOARD_REBOOTED
    assert (d.steering, d.throttle) == (0.0, 0.0)
    d = rig.tick(gone, board_state=State.DISARMED)
    assert d.mode == Mode.DISARMED and d.reason == REBOOTED, "not 'no joystick connected'"
    rig.board = State.DISARMED
    assert rig.tick(pad(arm=True)).mode == Mode.MANUAL
    rig.tick(pad(arm=True))  # disarmed by the person: the reboot is no longer the reason
    assert why(rig.tick(pad()).reason) is Why.DISARMED_BY_HUMAN


def test_controls_read_through_a_silent_board_disarm_and_a_pulled_pad_estops():
    rig = Rig()
    rig.auto()
    through = replace(pad(), connected=False, through_board=True)
    d = rig.tick(through, telemetry_age_s=0.3)
    assert d.mode == Mode.DISARMED and why(d.reason) is Why.BOARD_SILENT
    rig = Rig()
    rig.auto()
    d = rig.tick(through, telemetry_age_s=0.01)  # the board talks: the receiver itself is gone
    assert d.mode == Mode.ESTOP and why(rig.arbiter.estop_reason) is Why.RECEIVER_LOST
    rig = Rig()
    rig.auto()
    d = rig.tick(pad(connected=False), telemetry_age_s=0.3)  # a pad: the dead-man, always
    assert d.mode == Mode.ESTOP
