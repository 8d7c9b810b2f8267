"""The RC receiver's rules in the firmware's C core, on the host with a fake clock: the switch
e-stop, the take-over in AUTO, MANUAL from the receiver, the loss failsafe and the arming checks,
each at its exact pulse or millisecond. The same binary's timing on the emulated ATmega328P is in
test_avr_receiver.py."""

from __future__ import annotations

import random

import pytest

from firmware_bridge import messages as m
from firmware_bridge.messages import ArmRefusal, Controls, Reason, State
from firmware_bridge.native import (
    RC_SETTLE_US,
    RC_STEERING,
    RC_SWITCH,
    RC_THROTTLE,
    RC_TICKS_PER_US,
)
from firmware_bridge.timing import RC_LOSS_MS
from tests.firmware_rig import ARM, Bench

AUTO = m.CommandFlags.AUTO
CLEAR = m.CommandFlags.CLEAR
FRAME_US = 20_000
SLOT_US = {RC_STEERING: 0, RC_THROTTLE: 2_500, RC_SWITCH: 5_000}  # channels one after another


class RadioBench(Bench):
    """A bench whose board has a receiver wired: three channels of pulses every 20 ms, run in
    microseconds, with the core ticked every millisecond in between and told the time (as a
    board's loop() pass does) every millisecond and RC_SETTLE_US after each falling edge."""

    def __init__(self, controls: Controls = Controls.RECEIVER, **config) -> None:
        super().__init__()
        self.us = self.now * 1000
        self.widths = {RC_STEERING: 1500, RC_THROTTLE: 1500, RC_SWITCH: 1000}
        self.on = True  # the transmitter is on
        self.frame_start = 0  # of the latest frame sent
        self.next_frame = 0
        self.last_fall: dict[int, int] = {}
        # (us, channel, level) of the next frame; level -1: a loop() pass that tells the time
        self.edges: list[tuple[int, int, int]] = []
        if controls is not None:
            self.configure(controls=int(controls), **config)

    def configure(self, **fields) -> m.ConfigAck:
        self.send(m.Config(**fields))
        acks = self.frames(m.ConfigAck)
        assert acks and acks[-1].message.result == m.ConfigResult.ACCEPTED
        return acks[-1].message

    def _schedule(self) -> None:
        """The edges of the frame starting at self.frame_start (none while switched off)."""
        if self.on:
            for ch, slot in SLOT_US.items():
                rise = self.frame_start + slot
                self.edges += [(rise, ch, 1), (rise + self.widths[ch], ch, 0)]
        self.edges.sort()

    def edge(self, us: int, channel: int, level: int) -> None:
        if level < 0:
            self.settle(us)
            return
        self.core.rc_edge(channel, level, us * RC_TICKS_PER_US, us // 1000)
        if not level:
            self.last_fall[channel] = us
            self.edges.append((us + RC_SETTLE_US, channel, -1))
            self.edges.sort()

    def settle(self, us: int) -> None:
        self.core.rc_settle(us * RC_TICKS_PER_US, us // 1000)

    def advance(self, ms: int, *, every: int | None = 20, watch=None, **command) -> None:
        """Run ms milliseconds: receiver frames, core ticks, and a command every `every` ms.
        `watch(bench)` is called after every edge and tick (to catch the first moment)."""
        command.setdefault("flags", ARM)
        end = self.us + ms * 1000
        while self.us < end:
            if self.us >= self.next_frame:
                self.frame_start = self.next_frame
                self.next_frame += FRAME_US
                self._schedule()
            next_ms = (self.us // 1000 + 1) * 1000
            if self.edges and self.edges[0][0] < next_ms:
                t, ch, level = self.edges.pop(0)
                self.us = t
                self.edge(t, ch, level)
            else:
                self.us = next_ms
                self.now = next_ms // 1000
                if every and self.now % every == 0:
                    self.command(**command)
                self.settle(self.us)
                self.core.tick(self.now)
            if watch:
                watch(self)

    def arm(self, throttle: int = 0, flags: int = 0) -> None:
        self.advance(120, flags=flags)  # wheels still, ARM low, the receiver acquired
        self.command(throttle=throttle, flags=ARM | flags)
        assert self.core.state == State.ARMED, self.core.arm_refusal

    def outputs(self) -> tuple[int, int]:
        return self.core.steer_us, self.core.throttle_us

    def telemetry(self) -> m.Telemetry:
        return self.frames(m.Telemetry)[-1].message


def test_without_a_receiver_configured_its_pins_are_read_but_rule_nothing():
    bench = RadioBench(controls=Controls.PAD)
    bench.widths[RC_SWITCH] = 2000  # the switch in its e-stop position
    bench.widths[RC_STEERING] = 1900
    bench.arm()
    bench.advance(200, steering=-5000)
    assert bench.core.state == State.ARMED and not bench.core.rc_drives
    assert bench.core.steer_us == 1250  # the host's command, not the stick
    t = bench.telemetry()
    assert (t.rc_steer_us, t.rc_switch_us) == (1900, 2000)  # for `carrt check`/calibrate
    assert t.flags & m.TelemetryFlags.RC_SIGNAL and not t.flags & m.TelemetryFlags.RC_DRIVES


def test_in_manual_the_receivers_pulses_reach_the_outputs_exactly():
    bench = RadioBench()
    bench.arm()
    assert bench.core.rc_drives  # RECEIVER and no AUTO flag: MANUAL from the receiver
    for steer, throttle in ((1234, 1500), (1900, 1620), (1100, 1377)):
        bench.widths.update({RC_STEERING: steer, RC_THROTTLE: throttle})
        bench.advance(40, steering=8000, throttle=9000)  # the host's command is not used
        assert bench.outputs() == (steer, throttle)
    t = bench.telemetry()
    assert t.flags & m.TelemetryFlags.RC_DRIVES
    assert (t.steer_us, t.throttle_us, t.rc_steer_us, t.rc_throttle_us) == (1100, 1377, 1100, 1377)


def test_the_receiver_is_clamped_like_a_command():
    bench = RadioBench()
    bench.configure(
        controls=int(Controls.RECEIVER), steer_left_us=1200, steer_right_us=1800, max_forward=5000
    )
    bench.arm()
    bench.widths.update({RC_STEERING: 2100, RC_THROTTLE: 2100})
    bench.advance(40)
    assert bench.outputs() == (1800, 1750)  # the endpoint; half of forward travel


def _first(bench: RadioBench, predicate):
    seen: list[int] = []

    def watch(b: RadioBench) -> None:
        if not seen and predicate(b):
            seen.append(b.us)

    return seen, watch


@pytest.mark.parametrize("offset", [60, 61])
def test_in_auto_a_stick_past_the_deadzone_takes_over_as_that_pulse_counts(offset):
    bench = RadioBench()
    bench.arm(flags=AUTO)
    bench.advance(100, flags=ARM | AUTO, steering=3000, throttle=2000)
    assert not bench.core.rc_drives and bench.core.steer_us == 1650  # the policy drives
    syncs = bench.core.pwm_syncs
    bench.widths[RC_STEERING] = 1500 + offset  # the deadzone is 60 us
    first_frame = bench.next_frame  # the first frame that carries the new width
    seen, watch = _first(bench, lambda b: b.core.rc_drives)
    bench.advance(60, flags=ARM | AUTO, steering=3000, throttle=2000, watch=watch)
    if offset == 60:
        assert not seen and bench.core.steer_us == 1650
        return
    # once the first pulse past it has ended and its line stayed quiet for the settle time
    assert seen == [first_frame + 1561 + RC_SETTLE_US]
    assert bench.outputs() == (1561, 1500)
    assert bench.core.pwm_syncs == syncs + 1  # the new widths go out at once, not in 20 ms
    assert bench.telemetry().flags & m.TelemetryFlags.RC_DRIVES


def test_a_take_over_holds_whatever_the_host_does_until_its_auto_edge():
    bench = RadioBench()
    bench.arm(flags=AUTO)
    bench.widths[RC_THROTTLE] = 1700
    bench.advance(40, flags=ARM | AUTO)
    assert bench.core.rc_drives and bench.outputs() == (1500, 1700)
    bench.widths[RC_THROTTLE] = 1500  # the stick let go: the person still drives
    bench.advance(1000, every=None)  # and the host is silent for a second
    assert bench.core.state == State.ARMED and bench.core.rc_drives
    bench.advance(40, flags=ARM)  # the host back, in MANUAL: still the receiver
    assert bench.core.rc_drives
    bench.advance(40, flags=ARM | AUTO, steering=-10000)  # AUTO's 0 -> 1 edge
    assert not bench.core.rc_drives and bench.core.steer_us == 1000
    bench.advance(300, every=None)  # the policy drives again: the host's watchdog is back
    assert (bench.core.state, bench.core.reason) == (State.FAILSAFE, Reason.LINK_TIMEOUT)


def test_the_switch_latches_estop_at_its_pulse_and_only_clear_then_arm_leaves_it():
    bench = RadioBench()
    bench.arm()
    bench.widths[RC_THROTTLE] = 1800
    bench.advance(40)
    bench.widths[RC_SWITCH] = 1699  # short of the threshold
    bench.advance(40)
    assert bench.core.state == State.ARMED
    bench.widths[RC_SWITCH] = 1700
    syncs = bench.core.pwm_syncs
    first_frame = bench.next_frame
    seen, watch = _first(bench, lambda b: b.core.state == State.ESTOP)
    bench.advance(40, watch=watch)
    assert seen == [first_frame + SLOT_US[RC_SWITCH] + 1700 + RC_SETTLE_US]  # that pulse, settled
    assert bench.core.reason == Reason.RC_SWITCH and bench.outputs() == (1500, 1500)
    assert bench.core.pwm_syncs == syncs + 1
    bench.advance(40, flags=CLEAR)  # cleared with the switch still at e-stop: latched again
    assert bench.core.state == State.ESTOP
    bench.widths[RC_SWITCH] = 1000
    bench.widths[RC_THROTTLE] = 1500
    bench.advance(40, flags=0)
    assert bench.core.state == State.ESTOP  # the switch going back clears nothing by itself
    bench.advance(40, flags=CLEAR)
    assert bench.core.state == State.DISARMED
    bench.command(flags=ARM)
    assert bench.core.state == State.ARMED


def test_receiver_loss_is_a_failsafe_after_exactly_the_loss_time():
    bench = RadioBench()
    bench.arm()
    bench.advance(50)
    bench.on = False  # the transmitter switched off after the frame in flight
    seen, watch = _first(bench, lambda b: b.core.state != State.ARMED)
    bench.advance(300, watch=watch)
    first_lost_ms = min(bench.last_fall.values()) // 1000  # the steering channel's last pulse
    assert (bench.core.state, bench.core.reason) == (State.FAILSAFE, Reason.RC_LOST)
    assert seen[0] == (first_lost_ms + RC_LOSS_MS + 1) * 1000  # at +100 ms still valid
    assert bench.outputs() == (1500, 1500)


def test_arming_needs_the_receivers_signal_and_its_throttle_at_neutral():
    bench = RadioBench()
    bench.on = False
    bench.advance(120, flags=0)
    bench.command(flags=ARM)
    assert bench.core.arm_refusal == ArmRefusal.RC_NO_SIGNAL
    bench.on = True
    bench.widths[RC_THROTTLE] = 1561
    bench.advance(120, flags=0)
    bench.command(flags=ARM)
    assert bench.core.arm_refusal == ArmRefusal.RC_NOT_NEUTRAL
    bench.widths[RC_THROTTLE] = 1560
    bench.advance(60, flags=0)
    bench.command(flags=ARM)
    assert bench.core.state == State.ARMED


@pytest.mark.parametrize("seed", range(5))
def test_nothing_arms_or_moves_from_receiver_noise(seed):
    """Random edges on every receiver pin for 3 s (the host never arms): the board stays
    DISARMED with neutral outputs; and an arm request amid the noise is refused."""
    rng = random.Random(seed)
    bench = RadioBench()
    us = 0
    for _ in range(3000):
        us += rng.randint(1, 3000)
        bench.edge(us, rng.randrange(3), rng.randint(0, 1))
        bench.now = us // 1000
        bench.settle(us)
        bench.core.tick(bench.now)
        if rng.random() < 0.02:
            bench.command(flags=0, steering=rng.randint(-10000, 10000))
        assert bench.core.state != State.ARMED and bench.outputs() == (1500, 1500)
    bench.command(flags=ARM)
    assert bench.core.state != State.ARMED


def test_a_pulse_counts_once_its_line_has_been_quiet_for_the_settle_time():
    """The board asks the core whether a pulse is due (rc_settle_due) before it does the work
    of telling it the time: due from exactly the settle time after the falling edge."""
    bench = RadioBench(controls=Controls.PAD)
    bench.advance(200, flags=0)
    assert bench.core.rc_width_us(RC_STEERING) == 1500 and bench.us == 200_000
    bench.on = False  # the bench's frames stop: this one by hand
    bench.core.rc_edge(RC_STEERING, 1, 200_000 * RC_TICKS_PER_US, 200)
    fall = 200_000 + 1_640
    bench.core.rc_edge(RC_STEERING, 0, fall * RC_TICKS_PER_US, fall // 1000)
    early = (fall + RC_SETTLE_US - 1) * RC_TICKS_PER_US
    assert not bench.core.rc_settle_due(early)
    bench.core.rc_settle(early, fall // 1000)
    assert bench.core.rc_width_us(RC_STEERING) == 1500
    due = (fall + RC_SETTLE_US) * RC_TICKS_PER_US
    assert bench.core.rc_settle_due(due)
    bench.core.rc_settle(due, fall // 1000)
    assert bench.core.rc_width_us(RC_STEERING) == 1640
    assert not bench.core.rc_settle_due(due + 1)  # counted once


def _cut_short(bench: RadioBench, channel: int, at_us: int, quiet_us: int) -> None:
    """Noise on the channel's line: its pulse of the next frame ends at_us after the rise, the
    line then rises again quiet_us later and falls 40 us after that (a burst's first glitch);
    the frame's other edges as usual."""
    bench.advance(20 - bench.now % 20, every=None)  # to the start of a frame
    assert bench.us == bench.next_frame
    bench.frame_start = bench.next_frame
    bench.next_frame += FRAME_US
    bench._schedule()
    rise = bench.frame_start + SLOT_US[channel]
    bench.edges.remove((rise + bench.widths[channel], channel, 0))
    fall = rise + at_us
    bench.edges += [(fall, channel, 0), (fall + quiet_us, channel, 1),
                    (fall + quiet_us + 40, channel, 0)]  # fmt: skip
    bench.edges.sort()


@pytest.mark.parametrize("quiet_us", [RC_SETTLE_US - 1, RC_SETTLE_US])
def test_a_pulse_that_noise_cuts_short_never_reaches_the_outputs(quiet_us):
    """Receiver driving at 1700 us; a glitch ends the steering pulse at 1200 us and the line is
    busy again within the settle time: that pulse is dropped (the outputs keep 1700). With the
    line quiet for the settle time, the same edges are a 1200 us pulse, as they would be for
    any decoder."""
    bench = RadioBench()
    bench.arm()
    bench.widths[RC_STEERING] = 1700
    bench.advance(120)
    assert bench.core.rc_drives and bench.outputs() == (1700, 1500)
    _cut_short(bench, RC_STEERING, 1200, quiet_us)
    seen: list[int] = []
    bench.advance(60, watch=lambda b: seen.append(b.core.steer_us))
    if quiet_us < RC_SETTLE_US:
        assert set(seen) == {1700}
        assert bench.core.state == State.ARMED
    else:
        assert 1200 in seen


@pytest.mark.parametrize("host_drives", [False, True])
def test_lost_receiver_edges_make_their_channels_invalid_at_once(host_drives):
    """The board's edge queue overflowed on the switch channel: from that moment it has no valid
    signal (ARMED: FAILSAFE, neutral outputs), whoever drives; it counts again only after a new
    run of five good pulses (the first after the loss has no period)."""
    bench = RadioBench()
    flags = AUTO if host_drives else 0
    bench.arm(flags=flags)
    bench.widths[RC_STEERING] = 1500 if host_drives else 1620
    bench.advance(100 - bench.now % 20, flags=ARM | flags, steering=2000)  # to a frame's start
    assert bench.core.rc_drives != host_drives
    assert bench.outputs() == ((1600, 1500) if host_drives else (1620, 1500))
    syncs = bench.core.pwm_syncs
    bench.core.rc_overflow(0, bench.now)  # no channel named: nothing happens
    assert bench.core.state == State.ARMED
    bench.core.rc_overflow(1 << RC_SWITCH, bench.now)
    assert (bench.core.state, bench.core.reason) == (State.FAILSAFE, Reason.RC_LOST)
    assert bench.outputs() == (1500, 1500) and bench.core.pwm_syncs == syncs + 1
    assert bench.core.rc_width_us(RC_SWITCH) == 0
    assert bench.core.rc_width_us(RC_STEERING) == bench.widths[RC_STEERING]  # not lost
    for frame in range(1, 7):  # the switch's next pulses: the first has no period
        bench.advance(20, flags=0)
        assert bench.core.rc_width_us(RC_SWITCH) == (1000 if frame == 6 else 0), frame
    bench.widths[RC_STEERING] = 1500
    bench.advance(40, flags=0)
    bench.command(flags=CLEAR)
    bench.command(flags=ARM | flags)
    assert bench.core.state == State.ARMED


def test_the_receivers_config_fields_are_checked():
    bench = RadioBench(controls=None)
    for bad in ({"controls": 3}, {"rc_deadzone_us": 5}, {"rc_deadzone_us": 501},
                {"rc_estop_us": 2300}, {"rc_steer_center_us": 700}):  # fmt: skip
        bench.send(m.Config(**bad))
        assert bench.frames(m.ConfigAck)[-1].message.result == m.ConfigResult.REJECTED_INVALID
