"""The RC receiver's pulse decoder in the firmware's C core, run on the host
with a fake clock: ms-exact boundaries, widths exact to the microsecond, the settle time, a
restart after lost edges, the 32-bit wrap, and a fuzz of random edge trains against a reference
model of the rule fw_rc.h states."""

from __future__ import annotations

import ctypes

from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_bridge.native import RC_SETTLE_US, load_library

LIB = load_library()
TICKS_PER_US, MIN_W, MAX_W, MIN_P, MAX_P, MIN_RUN, LOSS_MS = 2, 800, 2200, 8000, 30000, 5, 100
SETTLE = RC_SETTLE_US


class Channel:
    def __init__(self) -> None:
        self.mem = ctypes.create_string_buffer(LIB.fwh_rc_size())
        LIB.fw_rc_init(self.mem)

    def edge(self, level: int, t_us: int) -> None:
        """An edge at t_us microseconds (Timer1 ticks are half of them; ms for the loss rule)."""
        LIB.fw_rc_edge(
            self.mem, level, (t_us * TICKS_PER_US) & 0xFFFFFFFF, (t_us // 1000) & 0xFFFFFFFF
        )

    def settle(self, t_us: int) -> bool:
        """The time, every edge before it handed over: True when a pulse counted."""
        return bool(LIB.fw_rc_settle(self.mem, (t_us * TICKS_PER_US) & 0xFFFFFFFF))

    def pulse(self, start_us: int, width_us: int) -> None:
        """A pulse, and the line quiet for the settle time after it."""
        self.edge(1, start_us)
        self.edge(0, start_us + width_us)
        self.settle(start_us + width_us + SETTLE)

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


def test_the_settle_time_is_the_cores_own():
    assert LIB.fwh_rc_settle_us() == RC_SETTLE_US


def test_a_pulse_counts_once_its_line_has_been_quiet_for_the_settle_time():
    ch = Channel()
    for k in range(6):
        ch.pulse(k * 20_000, 1_500)
    assert ch.valid and ch.width == 1_500
    ch.edge(1, 6 * 20_000)
    ch.edge(0, 6 * 20_000 + 1_800)
    assert not ch.settle(6 * 20_000 + 1_800 + SETTLE - 1) and ch.width == 1_500
    assert ch.settle(6 * 20_000 + 1_800 + SETTLE) and ch.width == 1_800
    assert not ch.settle(6 * 20_000 + 1_800 + SETTLE + 1)  # once
    # the next rising edge counts a pulse that settled before it, without a settle call
    ch.edge(1, 7 * 20_000)
    ch.edge(0, 7 * 20_000 + 1_200)
    ch.edge(1, 8 * 20_000)
    assert ch.width == 1_200


def test_a_pulse_that_more_edges_follow_within_the_settle_time_is_a_bad_one():
    ch = Channel()
    for k in range(6):
        ch.pulse(k * 20_000, 1_500)
    for i, quiet in enumerate((3, 90, SETTLE - 1)):  # a glitch right after the pulse's end
        start = (6 + i) * 20_000
        ch.edge(1, start)
        ch.edge(0, start + 1_100)
        ch.edge(1, start + 1_100 + quiet)
        ch.edge(0, start + 1_100 + quiet + 20)
        assert not ch.settle(start + 1_100 + quiet + 20 + SETTLE)
        assert ch.valid and ch.width == 1_500, quiet
    ch = Channel()  # before the channel counts, such a pulse starts the run again
    for k in range(4):
        ch.pulse(k * 20_000, 1_500)
    ch.edge(1, 4 * 20_000)
    ch.edge(0, 4 * 20_000 + 1_500)
    ch.edge(1, 4 * 20_000 + 1_600)
    ch.edge(0, 4 * 20_000 + 1_620)
    for k in range(5, 9):  # the glitch's rise gives the first of them a period
        ch.pulse(k * 20_000, 1_500)
        assert not ch.valid
    ch.pulse(9 * 20_000, 1_500)
    assert ch.valid


def test_a_restart_after_lost_edges_needs_a_whole_new_run():
    ch = Channel()
    for k in range(6):
        ch.pulse(k * 20_000, 1_500)
    ch.edge(1, 6 * 20_000)
    LIB.fw_rc_restart(ch.mem)  # the falling edge of this pulse was lost
    assert not ch.valid and ch.width == 0
    ch.edge(0, 6 * 20_000 + 1_700)  # the next edge: no rising edge known, nothing to time
    assert not ch.settle(6 * 20_000 + 1_700 + SETTLE)
    for k in range(7, 12):  # the first has no period; four more make four of five
        ch.pulse(k * 20_000, 1_500)
        assert not ch.valid, k
    ch.pulse(12 * 20_000, 1_500)
    assert ch.valid and ch.width == 1_500


def test_the_counters_may_wrap():
    ch = Channel()
    start = (1 << 31) - 50_000  # in ticks this crosses 2^32 a few pulses in
    for k in range(10):
        ch.pulse(start + k * 20_000, 1_200)
    assert ch.valid and ch.width == 1_200


def reference(events: list[tuple[int, int]]) -> list[tuple[bool, int]]:
    """The rule of fw_rc.h, in Python: (valid, width) after each event, an event a rising (1)
    or falling (0) edge or the time told (2)."""
    out, high, have_rise, period_ok, rise, run, width = [], False, False, False, 0, 0, 0
    settling, fall = None, 0
    for kind, t in events:
        ticks = t * TICKS_PER_US
        settled = settling is not None and ticks - fall >= SETTLE * TICKS_PER_US
        if settled and kind != 0:  # the time told, or the next rising edge
            width, run, settling = settling, min(run + 1, MIN_RUN), None
        if kind == 1:
            if settling is not None:  # more edges within the settle time: a bad pulse
                settling = None
                if run < MIN_RUN:
                    run = 0
            period = ticks - rise
            period_ok = have_rise and MIN_P * TICKS_PER_US <= period <= MAX_P * TICKS_PER_US
            if have_rise and not period_ok and run < MIN_RUN:
                run = 0
            rise, have_rise, high = ticks, True, True
        elif kind == 0 and high:
            high = False
            w = ticks - rise
            if not MIN_W * TICKS_PER_US <= w <= MAX_W * TICKS_PER_US:
                if run < MIN_RUN:
                    run = 0
            elif period_ok:
                settling, fall = w // TICKS_PER_US, ticks
        valid = run >= MIN_RUN
        out.append((valid, width if valid else 0))
    return out


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 2), st.integers(1, 40_000)), min_size=1, max_size=80))
def test_random_edge_trains_decode_as_the_rule_says(steps):
    """Random levels and gaps (1 us to 40 ms; repeats of a level are glitches) with the time
    told now and then: the C decoder and the reference agree after every event, and a valid
    width is always in range."""
    events, t = [], 0
    for kind, gap in steps:
        t += gap
        events.append((kind, t))
    ch = Channel()
    for (kind, t_us), expected in zip(events, reference(events), strict=True):
        if kind == 2:
            ch.settle(t_us)
        else:
            ch.edge(kind, t_us)
        assert (ch.valid, ch.width) == expected
        assert not ch.valid or MIN_W <= ch.width <= MAX_W
