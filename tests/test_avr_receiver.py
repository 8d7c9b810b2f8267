"""The RC receiver on the flashed binary: the emulated ATmega328P's receiver pins driven with
pulse trains (valid, noisy, out of range, too short, missing, under bursts of glitches), timed
in emulated cycles.

The timing trials are bench/bench_avr_receiver.py's (`make bench` runs 100 of each and records the
distributions for the README); here a smaller number of each asserts the bounds: a take-over in
AUTO and the switch's e-stop reach the pins within one pulse period (20 ms) of the receiver
pulse that carries them, with the host running and with its process stopped; the steady
passthrough is within 2 us of the receiver's width; the loss failsafe comes at RC_LOSS_MS. The
same rules, ms-exact on the C core with a fake clock, are in test_firmware_core_receiver.py.
"""

from __future__ import annotations

import random
import time

import numpy as np
import pytest
from avr_rig import RawHost, start_emulator
from e2e_rig import CliRun

from bench.bench_avr_receiver import (
    ALL_LINES,
    BURST_TOLERANCE_US,
    RUN_WIDTHS,
    TAKE_OVER_WIDTHS,
    Rig,
    burst_summary,
    burst_trials,
    signal_loss,
    summary,
    switch_estop,
    take_over,
)
from carrt.episodes.reader import list_episodes, read_episode
from carrt.interfaces import Mode
from firmware_bridge import messages as m
from firmware_bridge.timing import RC_LOSS_MS

# timings in emulated or real time: their own pass in make test, not beside CPU-heavy tests
pytestmark = pytest.mark.realtime

TRIALS = 12
PERIOD_MS = 20.0
# The loss rule counts from the last pulse's end as stamped by the loop() pass that read it (the
# board's 1 ms clock, read once a pass) and is checked once a pass, the LED following in the same
# pass: after RC_LOSS_MS, plus the clock's 1 ms, plus up to two passes, the one that stamps the
# pulse late and the one that finds the loss late (each under 1 ms: a COMMAND decoded, ~9,300
# cycles, and a TELEMETRY sent, ~6,000, at 16 MHz). So (RC_LOSS_MS, RC_LOSS_MS + 3 ms]; a CI run
# saw 102.16 ms, the issue-66 tester up to 103.0 on the binary before.
LOSS_LATE_MS = 3.0
# the steadied width is the median of the last five receiver pulses: one more to be sure
SETTLE_FRAMES = 6


@pytest.fixture
def rig(tmp_path):
    emu = start_emulator(eeprom_path=tmp_path / "eeprom.bin")
    rig = Rig(emu)
    yield rig
    rig.close()
    emu.close()


def test_take_over_estop_and_loss_timing_on_the_flashed_binary(rig):
    rng = random.Random(61)
    results = {
        "running": [take_over(rig, rng, frozen=False) for _ in range(TRIALS)],
        "frozen": [take_over(rig, rng, frozen=True) for _ in range(TRIALS)],
        "estop": [switch_estop(rig, rng) for _ in range(TRIALS)],
        "loss": [signal_loss(rig, rng) for _ in range(TRIALS)],
    }
    table = summary(results)
    for name in ("running", "frozen"):
        assert table[name]["latency_ms_max"] <= PERIOD_MS, table[name]
        assert table[name]["steady_width_error_us_max"] <= 2.0, table[name]
    # with the host stopped the person still drives, past the host's 200 ms watchdog
    assert table["frozen"]["still_armed"] == TRIALS
    assert table["estop"]["latency_ms_max"] <= PERIOD_MS, table["estop"]
    assert table["loss"]["latency_ms_min"] > RC_LOSS_MS, table["loss"]
    assert table["loss"]["latency_ms_max"] <= RC_LOSS_MS + LOSS_LATE_MS, table["loss"]


BURSTS_PER_CASE = 3


def test_noise_bursts_on_each_line_never_put_a_wrong_width_on_the_outputs(rig):
    """Bursts of glitches 20-90 us apart and a few us apart on each receiver line and on all
    three at once, and storms on all three, each around the falling edge of one of the
    receiver's pulses, while the receiver drives (a take-over) and while the host does: every
    output pulse after each is the command on the pins or neutral, never a third width. (The
    firmware of before put widths up to 500 us off on the servo and the ESC in 9 of 48 such
    bursts: an edge that found its queue full was dropped, and the next edge stamped it late.)
    A storm is more than the board's edge queue holds: it rejects the receiver (FAILSAFE)
    rather than time a pulse across the edges it lost; the bursts on one line of 20-90 us, as
    a tester saw on the switch line, are measured and rejected pulse by pulse: the car drives on."""
    table = burst_summary(burst_trials(rig, random.Random(66), BURSTS_PER_CASE))
    assert sum(row["bursts"] for row in table.values()) == 2 * 9 * BURSTS_PER_CASE
    assert all(row["wrong"] == 0 for row in table.values()), table
    for who in ("rx", "host"):
        assert table[f"{who}_storm_all"]["neutral"] == BURSTS_PER_CASE, table
        for line in ("steering", "throttle", "switch"):
            assert table[f"{who}_sparse_{line}"]["neutral"] == 0, table


def test_a_long_storm_on_every_line_fails_safe_and_the_board_runs_on(tmp_path):
    """300 ms of edges 2-6 us apart on all three receiver lines while the receiver drives: the
    board goes FAILSAFE (its signal lost, neutral outputs, never a wrong width) within one pulse
    period, keeps sending TELEMETRY at 50 Hz throughout, and counts the receiver again once the
    storm is over."""
    emu = start_emulator(eeprom_path=tmp_path / "eeprom.bin")
    host = RawHost(emu.port)
    try:
        host.wait_for(lambda x: isinstance(x, m.Telemetry) and x.mcu_time_ms > 150, 3.0, "HELLO")
        host.send(m.Config(controls=int(m.Controls.RECEIVER)))
        host.wait_for(lambda x: isinstance(x, m.ConfigAck), what="CONFIG_ACK")
        emu.rc_receiver(RUN_WIDTHS.values())
        time.sleep(0.3)
        host.drive(0.15, flags=0)
        host.drive(0.15)  # MANUAL from the receiver
        for ch, width in TAKE_OVER_WIDTHS.items():
            emu.rc_train(ch, width)
        time.sleep(0.2)
        assert emu.pulses_us() == pytest.approx(
            (TAKE_OVER_WIDTHS[0], TAKE_OVER_WIDTHS[1]), abs=BURST_TOLERANCE_US
        )
        host.drain()
        emu.take_events()
        for ch in ALL_LINES:
            emu.rc_burst(ch, 75_000, 2.0, 6.0, seed=ch + 7)
        events: list = []
        deadline = time.monotonic() + 10.0
        while sum(e.kind == "E" for e in events) < len(ALL_LINES):
            assert time.monotonic() < deadline, "the storm did not end"
            time.sleep(0.02)
            host.poll()
            events += emu.take_events()
        start = next(e.cycle for e in events if e.kind == "N")
        end = max(e.cycle for e in events if e.kind == "E")
        assert (end - start) / 16_000 > 250.0  # emulated ms of storm
        led_off = next(e.cycle for e in events if e.kind == "L" and e.value == 0)
        assert (led_off - start) / 16_000 < PERIOD_MS
        for e in events:
            if e.kind in "AB":
                want = TAKE_OVER_WIDTHS[0 if e.kind == "A" else 1]
                assert min(abs(e.value / 16 - want), abs(e.value / 16 - 1500)) <= 3.0, e
        tel = [x for x in host.received if isinstance(x, m.Telemetry)]
        in_storm = [t for t in tel if start / 16_000 <= t.mcu_time_ms <= end / 16_000]
        assert len(in_storm) >= 0.9 * (end - start) / 16_000 / 20  # every 20 ms, or nearly
        assert in_storm[-1].state == m.State.FAILSAFE and in_storm[-1].reason == m.Reason.RC_LOST
        time.sleep(0.2)
        tel = host.telemetry()
        assert tel.flags & m.TelemetryFlags.RC_SIGNAL
        assert (tel.rc_steer_us, tel.rc_throttle_us) == pytest.approx((1700, 1430), abs=1)
    finally:
        host.close()
        emu.close()


@pytest.fixture
def raw(tmp_path):
    emu = start_emulator(eeprom_path=tmp_path / "eeprom.bin")
    host = RawHost(emu.port)
    host.wait_for(lambda x: isinstance(x, m.Telemetry) and x.mcu_time_ms > 150, 3.0, "TELEMETRY")
    host.send(m.Config(controls=int(m.Controls.RECEIVER)))
    ack = host.wait_for(lambda x: isinstance(x, m.ConfigAck), what="CONFIG_ACK")
    assert ack.result == m.ConfigResult.ACCEPTED
    yield emu, host
    host.close()
    emu.close()


def _arm_attempt(emu, host) -> m.Telemetry:
    """Commands with ARM low, then an ARM edge; the telemetry after it (outputs checked)."""
    host.drive(0.15, flags=0)
    emu.take_events()
    host.drive(0.15, flags=m.CommandFlags.ARM)
    assert not any(e.kind == "L" and e.value == 1 for e in emu.take_events()), "armed"
    assert emu.pulses_us() == pytest.approx((1500.0, 1500.0), abs=1.0)
    return [x for x in host.received if isinstance(x, m.Telemetry)][-1]


@pytest.mark.parametrize(
    "signal",
    ["noise", "too wide", "too short", "too fast", "missing"],
)
def test_nothing_arms_from_a_receiver_without_a_valid_signal(raw, signal):
    emu, host = raw
    if signal == "too wide":
        emu.rc_receiver([2400] * 3)
    elif signal == "too short":
        emu.rc_receiver([500] * 3)
    for ch in RUN_WIDTHS:
        if signal == "noise":
            emu.rc_noise(ch, 700.0, seed=ch + 1)
        elif signal == "too fast":
            emu.rc_train(ch, 1500, 5_000, 300 * ch)
    time.sleep(0.3)
    tel = _arm_attempt(emu, host)
    assert tel.state == m.State.DISARMED
    assert tel.arm_refusal == m.ArmRefusal.RC_NO_SIGNAL
    assert not tel.flags & m.TelemetryFlags.RC_SIGNAL
    assert (tel.rc_steer_us, tel.rc_throttle_us, tel.rc_switch_us) == (0, 0, 0)


def test_a_valid_receiver_is_reported_and_then_arming_works(raw):
    emu, host = raw
    emu.rc_receiver([RUN_WIDTHS[0] + 37, RUN_WIDTHS[1], RUN_WIDTHS[2]])
    time.sleep(0.3)
    host.drive(0.15, flags=0)
    tel = [x for x in host.received if isinstance(x, m.Telemetry)][-1]
    assert tel.flags & m.TelemetryFlags.RC_SIGNAL
    # each edge is stamped when its interrupt starts, a few cycles later or sooner than the
    # other's: a width reads to the microsecond, give or take one (the passthrough spec: 2)
    widths = (tel.rc_steer_us, tel.rc_throttle_us, tel.rc_switch_us)
    assert widths == pytest.approx((1537, 1500, 1000), abs=1)
    host.drive(0.15, flags=m.CommandFlags.ARM)
    tel = [x for x in host.received if isinstance(x, m.Telemetry)][-1]
    assert tel.state == m.State.ARMED  # MANUAL from the receiver: its steering on the pin
    assert tel.flags & m.TelemetryFlags.RC_DRIVES
    # the passthrough spec is for the steadied width: wait for SETTLE_FRAMES output frames in
    # emulated time (a loaded machine runs the emulator slower than the wall clock, and the
    # first pulse after the take-over is the raw measured width)
    first = emu.pulse_counts()[0]
    deadline = time.monotonic() + 10.0
    while emu.pulse_counts()[0] < first + SETTLE_FRAMES:
        assert time.monotonic() < deadline, "the steering output stopped pulsing"
        time.sleep(0.02)
    assert emu.pulses_us()[0] == pytest.approx(1537.0, abs=2.0)


def test_the_simulator_drives_through_the_emulated_receivers_pins(tmp_path):
    """`--board avr` with the transmitter as the controls: the scripted expert's sticks become
    pulse trains on the emulated D4-D6, the binary passes them to the servo and ESC, and the
    host records them read back from TELEMETRY (real time)."""
    out = tmp_path / "out"
    code = CliRun(
        ["teleop", "--sim", "--board", "avr", "--expert", "auto", "--record", "--duration", "12",
         "--out", str(out), "--set", "receiver.controls=receiver"]
    ).result(timeout_s=120)  # fmt: skip
    assert code == 0
    steps = np.concatenate([read_episode(p).steps for p in list_episodes(out)])
    manual = steps["mode"] == Mode.MANUAL
    assert manual.sum() >= 50
    assert (steps["human_action"][manual][:, 1] > 0.1).mean() > 0.5, "driven from the radio"
    assert steps["speed_mps"].max() > 1.0, "and the car moved"
