"""The firmware's safety rules, checked on the real C core with a fake clock.

Every time below is an explicit millisecond value handed to the core, so the boundaries
(the watchdog, freshness, stall and wheels-stopped times of firmware_bridge/timing.py, used by
name) are tested to the millisecond, including across the 32-bit wrap of the board's clock:
booting disarmed, the link watchdog, decision freshness, the e-stop latch, failsafe and clear,
arming's conditions, the stall cut-out, and the state machine's invariants under random
commands. The outputs under each configuration are in test_firmware_core_config.py, the wire
(frames, telemetry, counters) in test_firmware_core_wire.py.
"""

from __future__ import annotations

import pytest
from firmware_rig import ARM, PROPS, Bench
from hypothesis import given
from hypothesis import strategies as st

from firmware_bridge import messages as m
from firmware_bridge.messages import ArmRefusal, ConfigResult, Reason, State
from firmware_bridge.timing import DECISION_STALE_MS, LINK_TIMEOUT_MS, STALL_MS

ESTOP = m.CommandFlags.ESTOP
CLEAR = m.CommandFlags.CLEAR
NEAR_WRAP = 0xFFFFFF00


def test_boot_is_disarmed_neutral_and_says_hello():
    b = Bench(boot_id=0xDEADBEEF)
    assert (b.core.state, b.core.reason, b.core.arm_refusal) == (
        State.DISARMED,
        Reason.BOOT,
        ArmRefusal.NONE,
    )
    assert b.neutral
    (hello,) = b.frames()
    assert hello.message == m.Hello(
        m.PROTOCOL_HASH, 0xDEADBEEF, *m.FIRMWARE_VERSION, 0, m.ResetCause.POWER_ON
    )
    b.send(m.HelloRequest())
    assert [f.message for f in b.frames()] == [hello.message]


@pytest.mark.parametrize("cause", list(m.ResetCause))
def test_every_hello_of_a_boot_names_its_reset_cause(cause):
    b = Bench()
    b.core.boot(0xB008, b.now, cause)
    b.send(m.HelloRequest())
    hellos = [f.message for f in b.frames(m.Hello)]
    # the bench's own boot's HELLO, never read, went with the reset (as a UART's queue would):
    # the second boot's, then the answer to the request
    assert [(h.boot_id, h.reset_cause) for h in hellos] == [(0xB008, cause)] * 2


def test_a_reset_cause_the_protocol_does_not_know_goes_out_as_unknown():
    b = Bench()
    b.frames()
    b.core.boot(0xB008, b.now, max(m.ResetCause) + 1)
    assert b.frames(m.Hello)[-1].message.reset_cause == m.ResetCause.UNKNOWN


@pytest.mark.parametrize("start", [0, NEAR_WRAP], ids=["t0", "across-wrap"])
def test_link_watchdog_fires_at_exactly_the_link_timeout(start):
    assert LINK_TIMEOUT_MS == 200  # the table's value, as PROTOCOL.md and the README state it
    b = Bench(now=start)
    b.arm()
    b.run(100, throttle=1000)  # last command at b.now
    b.run(LINK_TIMEOUT_MS - 1, every=None)
    assert b.core.state == State.ARMED
    assert b.core.throttle_us == 1550
    b.run(1, every=None)
    assert (b.core.state, b.core.reason) == (State.FAILSAFE, Reason.LINK_TIMEOUT)
    assert b.neutral


def test_only_commands_feed_the_watchdog():
    b = Bench()
    b.arm()
    last = b.now
    for _ in range(20):
        b.send(m.Ping(1))
        b.send(m.HelloRequest())
        b.run(10, every=None)
        if b.now - last >= LINK_TIMEOUT_MS:
            break
    assert (b.core.state, b.core.reason) == (State.FAILSAFE, Reason.LINK_TIMEOUT)


def test_a_late_command_does_not_hide_a_gap_without_ticks():
    b = Bench()
    b.arm()
    b.now += LINK_TIMEOUT_MS + 50  # the main loop hung: no tick ran, then a command arrives
    b.command(flags=ARM)
    assert (b.core.state, b.core.reason) == (State.FAILSAFE, Reason.LINK_TIMEOUT)


@pytest.mark.parametrize("start", [0, NEAR_WRAP], ids=["t0", "across-wrap"])
def test_stale_decision_fails_safe_at_the_freshness_limit_while_frames_keep_coming(start):
    assert DECISION_STALE_MS == 300
    b = Bench(now=start)
    b.arm()
    stuck = b.decision
    b.run(DECISION_STALE_MS - 1, decision_id=stuck)
    assert b.core.state == State.ARMED
    b.run(1, decision_id=stuck)
    assert (b.core.state, b.core.reason) == (State.FAILSAFE, Reason.DECISION_STALE)
    assert b.neutral


def test_freshness_is_measured_from_the_last_change_and_checked_on_commands():
    b = Bench()
    b.arm()
    b.run(100)  # fresh ids
    stuck = b.decision
    t = b.now
    for dt in range(20, DECISION_STALE_MS, 20):  # commands only, no ticks
        b.now = t + dt
        b.command(flags=ARM, decision_id=stuck)
    b.now = t + DECISION_STALE_MS - 1
    b.command(flags=ARM, decision_id=stuck)
    assert b.core.state == State.ARMED
    b.now = t + DECISION_STALE_MS
    b.command(flags=ARM, decision_id=stuck)
    assert (b.core.state, b.core.reason) == (State.FAILSAFE, Reason.DECISION_STALE)


def test_freshness_restarts_at_arming_even_with_an_old_decision_id():
    b = Bench()
    b.run(400, flags=0, decision_id=7)
    b.command(flags=ARM, decision_id=7)
    assert b.core.state == State.ARMED
    b.run(299, decision_id=7)
    assert b.core.state == State.ARMED
    b.run(1, decision_id=7)
    assert (b.core.state, b.core.reason) == (State.FAILSAFE, Reason.DECISION_STALE)


def test_changing_decisions_keep_the_car_armed():
    b = Bench()
    b.arm()
    b.rolling = True
    b.run(3000, throttle=4000, steering=-2500)
    assert b.core.state == State.ARMED
    assert (b.core.steer_us, b.core.throttle_us) == (1375, 1700)


def drive_fast(b: Bench) -> None:
    b.arm()
    b.rolling = True
    b.run(600, throttle=8000)
    assert b.core.throttle_us == 1900


def test_estop_is_immediate_and_latched_through_everything():
    b = Bench()
    drive_fast(b)
    b.command(throttle=8000, flags=ARM | ESTOP)  # no tick after this
    b.rolling = False
    assert (b.core.state, b.core.reason) == (State.ESTOP, Reason.ESTOP_COMMAND)
    assert b.neutral

    latched = (State.ESTOP, Reason.ESTOP_COMMAND)
    b.run(1000, every=None)  # watchdog period passes
    assert (b.core.state, b.core.reason) == latched
    b.run(200, throttle=8000, flags=ARM)  # commands without the flag
    assert (b.core.state, b.core.reason) == latched
    b.command(flags=0)
    b.command(throttle=0, flags=ARM)  # a fresh arm edge
    assert (b.core.state, b.core.arm_refusal) == (State.ESTOP, ArmRefusal.NOT_DISARMED)
    b.send(m.Config(persist=0))
    assert b.frames(m.ConfigAck)[-1].message.result == ConfigResult.ACCEPTED
    b.command(flags=CLEAR | ARM)  # clear with arm still set
    b.command(flags=CLEAR | ESTOP)  # clear with e-stop still set
    assert (b.core.state, b.core.reason) == latched
    assert b.neutral

    b.command(flags=CLEAR)
    assert (b.core.state, b.core.reason) == (State.DISARMED, Reason.CLEARED)
    b.run(100, flags=0)
    assert b.core.state == State.DISARMED
    b.command(flags=ARM)
    assert (b.core.state, b.core.reason) == (State.ARMED, Reason.ARMED_OK)


@pytest.mark.parametrize("from_state", ["disarmed", "failsafe"])
def test_estop_latches_from_any_state(from_state):
    b = Bench()
    if from_state == "failsafe":
        b.arm()
        b.run(300, every=None)
        assert b.core.state == State.FAILSAFE
    b.command(flags=ESTOP)
    assert (b.core.state, b.core.reason) == (State.ESTOP, Reason.ESTOP_COMMAND)


def test_failsafe_needs_clear_then_a_separate_arm():
    b = Bench()
    b.arm()
    b.run(250, every=None)
    assert b.core.state == State.FAILSAFE
    b.run(100, flags=ARM)  # host still holds ARM: no way back
    b.command(flags=ARM | CLEAR)
    assert b.core.state == State.FAILSAFE
    b.command(flags=CLEAR)
    assert (b.core.state, b.core.reason) == (State.DISARMED, Reason.CLEARED)
    b.command(flags=ARM)
    assert (b.core.state, b.core.reason) == (State.ARMED, Reason.ARMED_OK)


def test_host_dropping_arm_disarms():
    b = Bench()
    drive_fast(b)
    b.command(throttle=8000, flags=0)
    assert (b.core.state, b.core.reason) == (State.DISARMED, Reason.HOST_DISARM)
    assert b.neutral


NOT_NEUTRAL = ArmRefusal.THROTTLE_NOT_NEUTRAL


@pytest.mark.parametrize(
    ("throttle", "refusal"),
    [(200, None), (-200, None), (201, NOT_NEUTRAL), (-201, NOT_NEUTRAL), (-32768, NOT_NEUTRAL)],
)
def test_arming_needs_neutral_throttle(throttle, refusal):
    b = Bench()
    b.run(100, flags=0)
    b.command(throttle=throttle, flags=ARM)
    if refusal is None:
        assert (b.core.state, b.core.arm_refusal) == (State.ARMED, ArmRefusal.NONE)
    else:
        assert (b.core.state, b.core.arm_refusal) == (State.DISARMED, refusal)
        assert b.neutral


def test_arming_needs_wheels_stopped_for_100_ms():
    b = Bench()
    b.run(50, flags=0)
    b.command(flags=ARM)  # only 50 ms of observation since boot
    assert b.core.arm_refusal == ArmRefusal.WHEELS_MOVING
    b.run(100, flags=0)
    b.set_encoder(7)
    b.run(1, every=None)  # the tick that sees the wheel move
    b.run(99, flags=0)
    b.command(flags=ARM)
    assert (b.core.state, b.core.arm_refusal) == (State.DISARMED, ArmRefusal.WHEELS_MOVING)
    b.run(1, every=None)
    b.command(flags=0)
    b.command(flags=ARM)
    assert (b.core.state, b.core.arm_refusal) == (State.ARMED, ArmRefusal.NONE)


def test_arm_held_across_a_reboot_needs_a_fresh_edge():
    b = Bench()
    b.run(200, flags=ARM)  # ARM high since before boot
    assert (b.core.state, b.core.arm_refusal) == (State.DISARMED, ArmRefusal.NO_EDGE)
    b.command(flags=0)
    b.command(flags=ARM)
    assert b.core.state == State.ARMED

    b.core.boot(0x2222, b.now)  # the board resets while the host keeps sending ARM
    b.run(300, flags=ARM)
    assert (b.core.state, b.core.reason) == (State.DISARMED, Reason.BOOT)
    assert b.core.arm_refusal == ArmRefusal.NO_EDGE
    b.command(flags=0)
    b.command(flags=ARM)
    assert b.core.state == State.ARMED


def test_stall_fails_safe_500_ms_after_throttle_passes_15_percent():
    b = Bench()
    b.arm()
    armed_at = b.now
    b.command(throttle=10000, flags=ARM)
    b.run(575, throttle=10000)  # applied passes 1500 at the tick armed_at + 76
    assert b.core.state == State.ARMED
    b.run(1, throttle=10000)
    assert b.now == armed_at + 576
    assert (b.core.state, b.core.reason) == (State.FAILSAFE, Reason.STALL)
    assert b.neutral


def test_an_encoder_tick_restarts_the_stall_timer():
    b = Bench()
    b.arm()
    b.command(throttle=10000, flags=ARM)
    b.run(300, throttle=10000)
    b.set_encoder(1)  # seen by the next tick, which restarts the stall time
    b.run(STALL_MS, throttle=10000)
    assert b.core.state == State.ARMED
    b.run(1, throttle=10000)
    assert (b.core.state, b.core.reason) == (State.FAILSAFE, Reason.STALL)


def test_throttle_dipping_below_15_percent_restarts_the_stall_timer():
    b = Bench()
    b.send(m.Config(slew_per_s=1000000))
    b.arm()
    b.command(throttle=10000, flags=ARM)
    b.run(300, throttle=10000)  # above 15 % since the second tick
    b.command(throttle=1000, flags=ARM)  # a dip, undone before the next tick
    b.command(throttle=10000, flags=ARM)
    b.run(STALL_MS, throttle=10000)
    assert b.core.state == State.ARMED
    b.run(1, throttle=10000)
    assert (b.core.state, b.core.reason) == (State.FAILSAFE, Reason.STALL)


@PROPS
@given(
    ops=st.lists(
        st.one_of(
            st.tuples(st.just("cmd"), st.integers(-12000, 12000), st.integers(0, 7)),
            st.tuples(st.just("wait"), st.integers(1, 400), st.booleans()),
        ),
        max_size=30,
    )
)
def test_state_machine_invariants_under_random_commands(ops):
    b = Bench()
    prev_arm = True
    for op in ops:
        before = b.core.state
        if op[0] == "cmd":
            _, throttle, flags = op
            b.command(throttle=throttle, flags=flags)
            arm = bool(flags & ARM)
            if b.core.state == State.ARMED and before != State.ARMED:
                assert before == State.DISARMED and arm and not prev_arm
                assert abs(throttle) <= 200 and not flags & ESTOP
            if flags & ESTOP:
                assert b.core.state == State.ESTOP
            if before == State.ESTOP and b.core.state != State.ESTOP:
                assert flags & CLEAR and not flags & (ARM | ESTOP)
                assert b.core.state == State.DISARMED
            prev_arm = arm
        else:
            b.rolling = op[2]
            b.run(op[1], every=None)
            assert b.core.state in (before, State.FAILSAFE)
        if b.core.state != State.ARMED:
            assert b.neutral
        assert 1000 <= b.core.throttle_us <= 2000 and 1000 <= b.core.steer_us <= 2000
