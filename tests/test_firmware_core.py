"""The firmware's safety rules, checked on the real C core with a fake clock.

Every time below is an explicit millisecond value handed to the core, so the boundaries
(the watchdog, freshness, stall and wheels-stopped times of firmware_bridge/timing.py, used by
name) are tested to the millisecond, including across the 32-bit wrap of the board's clock.
"""

from __future__ import annotations

import pytest
from cobs import cobs
from hypothesis import example, given, settings
from hypothesis import strategies as st

from firmware_bridge import codec
from firmware_bridge import messages as m
from firmware_bridge.messages import ArmRefusal, ConfigResult, Reason, State
from firmware_bridge.native import FirmwareCore
from firmware_bridge.timing import DECISION_STALE_MS, LINK_TIMEOUT_MS, STALL_MS

ESTOP = m.CommandFlags.ESTOP
ARM = m.CommandFlags.ARM
CLEAR = m.CommandFlags.CLEAR
NEAR_WRAP = 0xFFFFFF00
PROPS = settings(max_examples=200, deadline=None, derandomize=True)


def trunc_div(a: int, b: int) -> int:
    """C's integer division (toward zero)."""
    q = abs(a) // abs(b)
    return q if (a >= 0) == (b > 0) else -q


def pulse(v: int, neg: int, mid: int, pos: int) -> int:
    """The firmware's PWM mapping, written independently for comparison."""
    v = max(-10000, min(10000, v))
    out = mid + trunc_div((pos - mid if v >= 0 else mid - neg) * v, 10000)
    return max(min(neg, pos), min(max(neg, pos), out))


class Bench:
    """One board on the bench: the C core, a fake clock, and the host's side of the wire."""

    def __init__(self, *, now: int = 0, boot_id: int = 0xB007) -> None:
        self.core = FirmwareCore()
        self.now = now
        self.seq = 0
        self.decision = 0
        self.encoder = 0
        self.rolling = False  # wheels turning: the encoder advances every millisecond
        self.decoder = codec.FrameDecoder()
        self.core.boot(boot_id, now)

    def send(self, message: object) -> None:
        self.core.feed(codec.encode_frame(message, self.seq), self.now)
        self.seq = (self.seq + 1) & 0xFFFF

    def command(self, steering=0, throttle=0, flags=0, decision_id=None) -> None:
        if decision_id is None:
            self.decision += 1
            decision_id = self.decision
        self.send(m.Command(steering, throttle, decision_id & 0xFFFFFFFF, flags))

    def set_encoder(self, ticks: int) -> None:
        self.encoder = ticks
        self.core.set_encoder(ticks)

    def run(self, ms: int, *, every: int | None = 20, **command) -> None:
        """Tick every millisecond for ms; a command goes out every `every` ms (None: silence)."""
        command.setdefault("flags", ARM)
        for i in range(1, ms + 1):
            self.now += 1
            if self.rolling:
                self.set_encoder(self.encoder + 1)
            if every and i % every == 0:
                self.command(**command)
            self.core.tick(self.now)

    def arm(self, throttle: int = 0) -> None:
        self.run(100, flags=0)  # wheels observed still for 100 ms, ARM low
        self.command(throttle=throttle, flags=ARM)
        assert self.core.state == State.ARMED, self.core.arm_refusal

    def frames(self, cls: type | None = None) -> list:
        got = self.decoder.feed(self.core.take_output())
        return [f for f in got if cls is None or isinstance(f.message, cls)]

    @property
    def neutral(self) -> bool:
        return (self.core.steer_us, self.core.throttle_us) == (1500, 1500)


def test_boot_is_disarmed_neutral_and_says_hello():
    b = Bench(boot_id=0xDEADBEEF)
    assert (b.core.state, b.core.reason, b.core.arm_refusal) == (
        State.DISARMED,
        Reason.BOOT,
        ArmRefusal.NONE,
    )
    assert b.neutral
    (hello,) = b.frames()
    assert hello.message == m.Hello(m.PROTOCOL_HASH, 0xDEADBEEF, *m.FIRMWARE_VERSION, 0)
    b.send(m.HelloRequest())
    assert [f.message for f in b.frames()] == [hello.message]


def test_pong_echoes_nonce_and_board_time():
    b = Bench(now=1234)
    b.frames()
    b.send(m.Ping(0xCAFEF00D))
    (pong,) = b.frames()
    assert pong.message == m.Pong(0xCAFEF00D, 1234)


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


def test_throttle_rises_at_the_slew_rate_and_falls_at_once():
    b = Bench()
    b.arm()
    b.rolling = True
    b.command(throttle=10000, flags=ARM)
    for k in range(1, 600):
        b.run(1, every=1, throttle=10000)
        assert b.core.throttle_us == 1500 + 500 * min(10000, 20 * k) // 10000, k
    b.command(throttle=2000, flags=ARM)
    assert b.core.throttle_us == 1600  # before any tick
    b.command(throttle=-5000, flags=ARM)
    assert b.core.throttle_us == 1500  # sign change: through zero at once
    for k in range(1, 300):
        b.run(1, every=1, throttle=-5000)
        assert b.core.throttle_us == 1500 - min(250, k), k


def test_slow_slew_rates_advance_at_1_ms_ticks():
    b = Bench()
    forward_only = m.Config(
        throttle_reverse_us=1000, throttle_neutral_us=1000, slew_per_s=150, persist=0
    )
    b.send(forward_only)
    assert b.frames(m.ConfigAck)[-1].message.result == ConfigResult.ACCEPTED
    b.arm()
    b.rolling = True
    start = b.now
    for _ in range(2000):
        b.run(1, every=1, throttle=10000)
        applied = 150 * (b.now - start) // 1000
        assert b.core.throttle_us == 1000 + applied // 10


def test_commanded_throttle_is_clamped_to_the_configured_limits():
    b = Bench()
    b.send(m.Config(max_forward=5000, max_reverse=2000, slew_per_s=1000000))
    b.arm()
    b.rolling = True
    b.run(40, throttle=10000)
    assert b.core.throttle_us == 1750
    b.run(40, throttle=-10000)
    assert b.core.throttle_us == 1400


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


@st.composite
def valid_configs(draw):
    us = st.integers(800, 2200)
    left, right = draw(st.lists(us, min_size=2, max_size=2, unique=True))
    center = draw(st.integers(min(left, right), max(left, right)))
    forward = draw(us)
    neutral = draw(us.filter(lambda v: v != forward))
    lo, hi = (800, neutral) if forward > neutral else (neutral, 2200)
    reverse = draw(st.integers(lo, hi))
    limit = st.integers(0, 10000)
    slew = st.integers(100, 1000000)
    return m.Config(
        left, center, right, reverse, neutral, forward, *draw(st.tuples(limit, limit, slew)), 0
    )


def is_valid(c: m.Config) -> bool:
    pulses = [getattr(c, f) for f in ("steer_left_us", "steer_center_us", "steer_right_us")]
    pulses += [c.throttle_reverse_us, c.throttle_neutral_us, c.throttle_forward_us]
    return (
        all(800 <= p <= 2200 for p in pulses)
        and c.steer_left_us != c.steer_right_us
        and min(c.steer_left_us, c.steer_right_us)
        <= c.steer_center_us
        <= max(c.steer_left_us, c.steer_right_us)
        and c.throttle_forward_us != c.throttle_neutral_us
        and min(c.throttle_reverse_us, c.throttle_forward_us)
        <= c.throttle_neutral_us
        <= max(c.throttle_reverse_us, c.throttle_forward_us)
        and c.max_forward <= 10000
        and c.max_reverse <= 10000
        and 100 <= c.slew_per_s <= 1000000
    )


commands = st.lists(st.tuples(st.integers(-32768, 32767), st.integers(-32768, 32767)), max_size=8)


@PROPS
@given(config=valid_configs(), cmds=commands)
def test_pwm_never_leaves_the_endpoints(config, cmds):
    b = Bench()
    b.send(config)
    assert b.frames(m.ConfigAck)[-1].message.result == ConfigResult.ACCEPTED
    steer_ep = sorted((config.steer_left_us, config.steer_right_us))
    throttle_ep = sorted((config.throttle_reverse_us, config.throttle_forward_us))
    assert (b.core.steer_us, b.core.throttle_us) == (
        config.steer_center_us,
        config.throttle_neutral_us,
    )
    b.arm()
    b.rolling = True
    for steering, throttle in [*cmds, (-10000, -10000), (10000, 10000)]:
        b.command(steering, throttle, ARM)
        for _ in range(3):
            b.run(7, steering=steering, throttle=throttle, every=7)
            assert steer_ep[0] <= b.core.steer_us <= steer_ep[1]
            assert throttle_ep[0] <= b.core.throttle_us <= throttle_ep[1]
        neg, mid, pos = config.steer_left_us, config.steer_center_us, config.steer_right_us
        assert b.core.steer_us == pulse(steering, neg, mid, pos)
    assert b.core.steer_us == config.steer_right_us


@PROPS
@given(
    config=st.builds(
        m.Config,
        *[st.integers(700, 2300)] * 6,
        st.integers(0, 10500),
        st.integers(0, 10500),
        st.integers(0, 1100000),
        st.integers(0, 1),
    )
    | valid_configs()
)
@example(m.Config(max_forward=10001))
@example(m.Config(max_reverse=10001))
@example(m.Config(max_forward=10000, max_reverse=10000, slew_per_s=100))
@example(m.Config(slew_per_s=99))
@example(m.Config(slew_per_s=1000001))
@example(m.Config(2200, 2200, 800, 800, 800, 2200, 0, 0, 1000000, 0))
@example(m.Config(throttle_reverse_us=1600, throttle_neutral_us=1600, throttle_forward_us=1600))
@example(m.Config(steer_left_us=799))
@example(m.Config(throttle_forward_us=2201))
def test_config_validation_matches_the_rules(config):
    b = Bench()
    b.send(config)
    ack = b.frames(m.ConfigAck)[-1].message
    expected = ConfigResult.ACCEPTED if is_valid(config) else ConfigResult.REJECTED_INVALID
    assert ack.result == expected
    b.send(m.ConfigRequest())
    reported = b.frames(m.Config)[-1].message
    assert reported == (config if is_valid(config) else m.Config())


def test_config_is_rejected_while_armed():
    b = Bench()
    b.arm()
    b.send(m.Config(steer_center_us=1600, persist=1))
    ack = b.frames(m.ConfigAck)[-1]
    assert ack.message == m.ConfigAck(b.seq - 1, ConfigResult.REJECTED_ARMED, 0)
    b.send(m.ConfigRequest())
    assert b.frames(m.Config)[-1].message == m.Config()
    assert b.core.storage == FirmwareCore().storage  # nothing written


def test_persisted_config_survives_a_reboot_and_bad_storage_is_ignored():
    b = Bench()
    stored = m.Config(1900, 1450, 1100, 1000, 1200, 2000, 8000, 3000, 5000, 1)
    b.send(stored)
    assert b.frames(m.ConfigAck)[-1].message == m.ConfigAck(0, ConfigResult.ACCEPTED, 1)
    assert (b.core.steer_us, b.core.throttle_us) == (1450, 1200)
    blob = b.core.storage

    b.core.boot(77, b.now)
    assert b.frames(m.Hello)[-1].message.config_from_storage == 1
    assert (b.core.steer_us, b.core.throttle_us) == (1450, 1200)
    b.send(m.ConfigRequest())
    assert b.frames(m.Config)[-1].message == stored
    b.run(20, every=None)
    flags = b.frames(m.Telemetry)[-1].message.flags
    assert flags & m.TelemetryFlags.CONFIG_FROM_STORAGE

    b.send(m.Config(steer_center_us=1510, persist=0))  # applied, not stored
    b.send(m.ConfigRequest())
    assert b.frames(m.Config)[-1].message == m.Config(steer_center_us=1510, persist=0)

    for bad in (
        b"\xff" * len(blob),
        b"\x00" * len(blob),
        blob[:5] + bytes([blob[5] ^ 1]) + blob[6:],
    ):
        fresh = Bench()
        fresh.core.storage = bad
        fresh.core.boot(1, 0)
        assert fresh.frames(m.Hello)[-1].message.config_from_storage == 0
        assert fresh.neutral
    fresh.core.storage = blob
    fresh.core.boot(2, 0)
    assert fresh.frames(m.Hello)[-1].message.config_from_storage == 1


def test_telemetry_every_20_ms_without_drift_and_with_every_field():
    b = Bench(now=5)
    b.frames()
    b.core.tick(5)
    times = [f.message.mcu_time_ms for f in b.frames(m.Telemetry)]
    for t in range(5, 1000, 7):  # irregular ticks
        b.now = t
        b.core.tick(t)
    times += [f.message.mcu_time_ms for f in b.frames(m.Telemetry)]
    assert len(times) == 50
    assert all(t - 5 - 20 * i < 7 for i, t in enumerate(times))
    b.now = 5000  # far behind: one frame, then resync
    b.core.tick(5000)
    b.run(40, every=None)
    assert [f.message.mcu_time_ms for f in b.frames(m.Telemetry)] == [5000, 5020, 5040]

    b.set_encoder(-12345)
    b.run(120, flags=0)  # wheels still again for more than 100 ms
    b.command(steering=100, throttle=50, flags=ARM, decision_id=0xABCDEF01)
    b.run(20, every=None)
    frames = b.frames()
    tel = frames[-1].message
    assert tel == m.Telemetry(
        mcu_time_ms=b.now,
        encoder_ticks=-12345,
        steer_us=1505,
        throttle_us=1502,
        state=State.ARMED,
        reason=Reason.ARMED_OK,
        arm_refusal=ArmRefusal.NONE,
        flags=m.TelemetryFlags.LINK_OK,
        last_seq=b.seq - 1,
        decision_id=0xABCDEF01,
    )
    seqs = [f.seq for f in frames]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    b.run(200, every=None)
    assert not b.frames(m.Telemetry)[-1].message.flags & m.TelemetryFlags.LINK_OK


def test_telemetry_across_the_clock_wrap():
    b = Bench(now=0xFFFFFFF0)
    b.run(100, every=None)
    times = [f.message.mcu_time_ms for f in b.frames(m.Telemetry)]
    assert times == [0xFFFFFFF1] + [(0xFFFFFFF0 + 20 * i) & 0xFFFFFFFF for i in range(1, 6)]


def test_bad_frames_are_counted_and_dropped():
    b = Bench()
    good = codec.encode_frame(m.Ping(5), 1)
    body = cobs.decode(good[:-1])
    bad_crc = cobs.encode(body[:-1] + bytes([body[-1] ^ 0x55])) + b"\x00"
    short = codec.frame_bytes(m.Ping.TYPE, 2, b"\x01\x02\x03")
    unknown = codec.frame_bytes(0x7F, 3, b"")
    b.core.feed(b"\x00\x00" + bad_crc + short + unknown + b"\x05\x01\x00" + b"\x01" * 100, 0)
    b.core.feed(b"\x00\x00\x00" + good, 0)
    assert b.core.counters == {"bad_crc": 1, "bad_length": 3, "overruns": 1, "tx_dropped": 0}
    assert [f.message for f in b.frames(m.Pong)] == [m.Pong(5, 0)]


chunks = st.one_of(
    st.binary(max_size=80),
    st.builds(codec.encode_frame, st.builds(m.Ping, st.integers(0, 2**32 - 1)), st.integers(0, 9)),
    st.builds(lambda p: codec.frame_bytes(0x10, 0, p), st.binary(max_size=12)),
    st.just(b"\x00"),
)


@settings(max_examples=150, deadline=None, derandomize=True)
@given(parts=st.lists(chunks, max_size=12), split=st.integers(1, 40))
def test_any_byte_stream_is_counted_like_the_python_decoder(parts, split):
    stream = b"".join(parts)
    b = Bench()
    for i in range(0, len(stream), split):
        b.core.feed(stream[i : i + split], i)
        b.core.tick(i)
    ref = codec.FrameDecoder()
    ref.feed(stream)
    counters = b.core.counters
    assert (counters["bad_crc"], counters["bad_length"], counters["overruns"]) == (
        ref.bad_crc,
        ref.bad_length,
        ref.overruns,
    )


@pytest.mark.parametrize("n", [64, 65, 66, 200])
def test_the_receive_buffer_holds_exactly_one_maximal_encoded_frame(n):
    stream = b"\x01" * n + b"\x00" + codec.encode_frame(m.Ping(9), 3)
    b = Bench()
    b.core.feed(stream, 0)
    ref = codec.FrameDecoder()
    assert [f.message for f in ref.feed(stream)] == [m.Ping(9)]
    assert b.core.counters["overruns"] == ref.overruns == (1 if n > 65 else 0)
    assert b.core.counters["bad_crc"] + b.core.counters["bad_length"] == (0 if n > 65 else 1)
    assert [f.message for f in b.frames(m.Pong)] == [m.Pong(9, 0)]


def test_counters_saturate():
    b = Bench()
    body = cobs.decode(codec.encode_frame(m.Ping(0), 0)[:-1])
    bad_crc = cobs.encode(body[:-1] + bytes([body[-1] ^ 1])) + b"\x00"
    b.core.feed(b"\x01\x00" * 70000 + bad_crc * 70000 + (b"\x01" * 70 + b"\x00") * 70000, 0)
    assert b.core.counters == {
        "bad_crc": 0xFFFF,
        "bad_length": 0xFFFF,
        "overruns": 0xFFFF,
        "tx_dropped": 0,
    }


def test_tx_overflow_drops_whole_frames():
    b = Bench()
    b.run(10000, every=None)  # 500 telemetry frames, nobody reading
    assert b.core.counters["tx_dropped"] > 0
    out = b.core.take_output()
    assert len(out) <= 8192 and out.endswith(b"\x00")
    assert all(b.decoder.feed(out)) and b.decoder.rejected == 0


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
