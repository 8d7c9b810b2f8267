"""The RC receiver's pulse decoder in the firmware's C core, run on the host
with a fake clock: ms-exact boundaries, widths exact to the microsecond, the 32-bit wrap, and a
fuzz of random edge trains against a reference model of the rule fw_rc.h states."""

from __future__ import annotations

import ctypes

from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_bridge.native import load_library

LIB = load_library()
TICKS_PER_US, MIN_W, MAX_W, MIN_P, MAX_P, MIN_RUN, LOSS_MS = 2, 800, 2200, 8000, 30000, 5, 100


class Channel:
    def __init__(self) -> None:
        self.mem = ctypes.create_string_buffer(LIB.fwh_rc_size())
        LIB.fw_rc_init(self.mem)

    def edge(self, level: int, t_us: int) -> None:
        """An edge at t_us microseconds (Timer1 ticks are half of them; ms for the loss rule)."""
        LIB.fw_rc_edge(
            self.mem, level, (t_us * TICKS_PER_US) & 0xFFFFFFFF, (t_us // 1000) & 0xFFFFFFFF
        )

    def pulse(self, start_us: int, width_us: int) -> None:
        self.edge(1, start_us)
        self.edge(0, start_us + width_us)

    def poll(self, now_ms: int) -> None:
        LIB.fw_rc_poll(self.mem, now_ms & 0xFFFFFFFF)

    @property
    def valid(self) -> bool:
        return bool(LIB.fw_rc_valid(self.mem))

    @property
    def width(self) -> int:
        return LIB.fw_rc_width_us(self.mem)


def test_a_receivers_pulse_train_is_valid_after_five_good_pulses_with_its_exact_width():
    ch = Channel()
    for k in range(6):  # the first pulse has no period yet: pulses 2-6 are the five
        assert not ch.valid and ch.width == 0
        ch.pulse(k * 20_000, 1_537)
    assert ch.valid and ch.width == 1_537


def test_a_glitch_on_a_valid_channel_is_dropped_and_the_last_good_width_kept():
    ch = Channel()
    for k in range(6):
        ch.pulse(k * 20_000, 1_500)
    assert ch.valid
    ch.pulse(6 * 20_000, 2_300)  # wider than any servo pulse
    assert ch.valid and ch.width == 1_500
    ch.pulse(6 * 20_000 + 500, 1_900)  # a runt period: not a receiver frame either
    assert ch.valid and ch.width == 1_500
    ch.pulse(7 * 20_000, 1_640)
    assert ch.valid and ch.width == 1_640


def test_before_a_channel_counts_a_bad_pulse_starts_the_run_again():
    ch = Channel()
    for k in range(5):
        ch.pulse(k * 20_000, 1_500)
    ch.pulse(5 * 20_000, 2_300)  # a period of its own: the next pulse's period is fine
    for k in range(6, 10):
        ch.pulse(k * 20_000, 1_500)
        assert not ch.valid
    ch.pulse(10 * 20_000, 1_500)
    assert ch.valid


def test_glitches_that_never_stop_end_the_signal_after_the_loss_time():
    ch = Channel()
    for k in range(6):
        ch.pulse(k * 20_000, 1_500)
    last_ms = (5 * 20_000 + 1_500) // 1000
    for k in range(6, 11):  # only bad pulses from now on, until 200.5 ms
        ch.pulse(k * 20_000, 500)
        ch.poll((k * 20_000 + 500) // 1000)
        assert ch.valid and ch.width == 1_500
    ch.poll(last_ms + LOSS_MS)
    assert ch.valid
    ch.poll(last_ms + LOSS_MS + 1)
    assert not ch.valid and ch.width == 0


def test_widths_and_periods_out_of_range_never_count():
    for width in (799, 2_201, 300, 5_000):
        ch = Channel()
        for k in range(20):
            ch.pulse(k * 20_000, width)
        assert not ch.valid, width
    for period in (7_999, 30_001, 2_000):
        ch = Channel()
        for k in range(20):
            ch.pulse(k * period, 1_500)
        assert not ch.valid, period
    for width in (800, 2_200):  # the boundaries themselves count
        ch = Channel()
        for k in range(6):
            ch.pulse(k * 8_000, width)
        assert ch.valid and ch.width == width


def test_signal_loss_after_exactly_the_loss_time():
    ch = Channel()
    for k in range(6):
        ch.pulse(k * 20_000, 1_500)
    last_ms = (5 * 20_000 + 1_500) // 1000  # the last good pulse ended at 101.5 ms
    ch.poll(last_ms + LOSS_MS)
    assert ch.valid
    ch.poll(last_ms + LOSS_MS + 1)
    assert not ch.valid and ch.width == 0


def test_the_counters_may_wrap():
    ch = Channel()
    start = (1 << 31) - 50_000  # in ticks this crosses 2^32 a few pulses in
    for k in range(10):
        ch.pulse(start + k * 20_000, 1_200)
    assert ch.valid and ch.width == 1_200


def reference(edges: list[tuple[int, int]]) -> list[tuple[bool, int]]:
    """The rule of fw_rc.h, in Python: (valid, width) after each edge."""
    out, high, have_rise, period_ok, rise, run, width = [], False, False, False, 0, 0, 0
    for level, t in edges:
        ticks = t * TICKS_PER_US
        if level:
            period = ticks - rise
            period_ok = have_rise and MIN_P * TICKS_PER_US <= period <= MAX_P * TICKS_PER_US
            if have_rise and not period_ok and run < MIN_RUN:
                run = 0
            rise, have_rise, high = ticks, True, True
        elif high:
            high = False
            w = ticks - rise
            if not MIN_W * TICKS_PER_US <= w <= MAX_W * TICKS_PER_US:
                if run < MIN_RUN:
                    run = 0
            elif period_ok:
                width, run = w // TICKS_PER_US, min(run + 1, MIN_RUN)
        valid = run >= MIN_RUN
        out.append((valid, width if valid else 0))
    return out


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 1), st.integers(1, 40_000)), min_size=1, max_size=80))
def test_random_edge_trains_decode_as_the_rule_says(steps):
    """Random levels and gaps (1 us to 40 ms; repeats of a level are glitches): the C decoder
    and the reference agree after every edge, and a valid width is always in range."""
    edges, t = [], 0
    for level, gap in steps:
        t += gap
        edges.append((level, t))
    ch = Channel()
    for (level, t_us), expected in zip(edges, reference(edges), strict=True):
        ch.edge(level, t_us)
        assert (ch.valid, ch.width) == expected
        assert not ch.valid or MIN_W <= ch.width <= MAX_W
