"""The firmware's outputs under its configuration, checked on the real C core with a fake clock.

The PWM mapping never leaves the configured endpoints (against an independent rewrite of it),
the throttle rises at the slew rate and falls at once, commands are clamped to the configured
limits; a config is accepted exactly when it follows the rules, refused while armed, and a
persisted one survives a reboot while bad storage is ignored. The safety rules are in
test_firmware_core.py.
"""

from __future__ import annotations

from firmware_rig import ARM, PROPS, Bench
from hypothesis import example, given
from hypothesis import strategies as st

from firmware_bridge import messages as m
from firmware_bridge.messages import ConfigResult
from firmware_bridge.native import FirmwareCore


def trunc_div(a: int, b: int) -> int:
    """C's integer division (toward zero)."""
    q = abs(a) // abs(b)
    return q if (a >= 0) == (b > 0) else -q


def pulse(v: int, neg: int, mid: int, pos: int) -> int:
    """The firmware's PWM mapping, written independently for comparison."""
    v = max(-10000, min(10000, v))
    out = mid + trunc_div((pos - mid if v >= 0 else mid - neg) * v, 10000)
    return max(min(neg, pos), min(max(neg, pos), out))


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
