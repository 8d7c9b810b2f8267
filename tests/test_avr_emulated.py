"""Hardware in the loop against the emulated AVR: the flashed binary, not the x86 core.

The firmware ELF (built with the Arduino core by `make firmware`) runs in simavr at 16 MHz
(firmware_bridge/avr_emulator.py). Timing is measured in emulated cycles between a host
frame's delimiter entering the UART and the ARMED LED (D13) going dark, so these numbers are
the board's own, whatever the load on the test machine. Pulse widths are measured on Timer1's
compare outputs. Without the Debian packages (gcc-avr avr-libc arduino-core-avr simavr
libsimavr-dev) every test here fails with one line saying so.
"""

from __future__ import annotations

import random
import statistics
import subprocess
import sys
import time

import pytest
from avr_rig import RawHost, start_emulator

from firmware_bridge import messages as m
from firmware_bridge.avr_emulator import F_CPU, AvrEmulatorError
from firmware_bridge.timing import DECISION_STALE_MS, LINK_TIMEOUT_MS

# timings in emulated or real time: their own pass in make test, not beside CPU-heavy tests
pytestmark = pytest.mark.realtime

ARM = m.CommandFlags.ARM
# The board's clock is millis(), which on a 16 MHz AVR advances once per 1.024 ms timer overflow
# and now and then by 2 to catch up: T millis can be as short as T - 1.024 ms of real time, and a
# check runs each loop() after that. A frame's last byte also reaches loop() a few byte times
# (40 us each) after it entered the UART. So a trip lands in [T - 1.1 ms, T + 2.5 ms).
TRIP_EARLY_MS = 1.1
TRIP_LATE_MS = 2.5


@pytest.fixture
def emulator(tmp_path):
    emu = start_emulator(eeprom_path=tmp_path / "eeprom.bin")
    yield emu
    emu.close()


@pytest.fixture
def host(emulator):
    raw = RawHost(emulator.port)
    # arming needs the wheels seen still for 100 ms since boot
    raw.wait_for(lambda x: isinstance(x, m.Telemetry) and x.mcu_time_ms > 150, 3.0, "TELEMETRY")
    yield raw
    raw.close()


def expected_pulse_us(value: int, neg: int = 1000, mid: int = 1500, pos: int = 2000) -> int:
    """fw_core.c's map_pulse: piecewise linear, C integer division (towards zero)."""
    span = (pos - mid) if value >= 0 else (mid - neg)
    return mid + int(span * value / 10000)


def led_falls_after_frames(events) -> list[float]:
    """For every ARMED LED falling edge: ms of emulated time since the last host frame."""
    delays, last_frame = [], None
    for event in events:
        if event.kind == "F":
            last_frame = event.cycle
        elif event.kind == "L" and event.value == 0 and last_frame is not None:
            delays.append((event.cycle - last_frame) * 1000.0 / F_CPU)
    return delays


def test_handshake_reports_the_protocol_hash(host):
    host.send(m.HelloRequest())
    hello = host.wait_for(lambda x: isinstance(x, m.Hello), what="HELLO")
    assert hello.protocol_hash == m.PROTOCOL_HASH
    assert (hello.fw_major, hello.fw_minor, hello.fw_patch) == m.FIRMWARE_VERSION


def test_pulses_are_within_1us_of_the_commanded_widths(emulator, host):
    assert emulator.pulses_us() == pytest.approx((1500.0, 1500.0), abs=1.0), "neutral at boot"
    host.arm()
    errors = []
    for steering, throttle in ((-10000, 0), (-3333, 1000), (0, -2500), (4567, 0), (10000, 500)):
        host.drive(0.5, steering=steering, throttle=throttle)  # the throttle slews at 2.0/s
        steer_us, throttle_us = emulator.pulses_us()
        errors += [
            steer_us - expected_pulse_us(steering),
            throttle_us - expected_pulse_us(throttle),
        ]
    print(f"pulse error, 10 widths: max |error| {max(map(abs, errors)):.3f} us")
    assert max(map(abs, errors)) <= 1.0, errors

    # 50 Hz: a new pulse every 20 ms of emulated time on both pins. The counts and the clock are
    # two requests, and the emulator runs on between them (far on a loaded machine: a CI run
    # read 53.9 Hz off two unbracketed reads), so each count is bracketed by clock reads and
    # the count must fit the shortest and the longest interval it can have spanned, give or
    # take the one pulse under way at each end. Counted once the host has gone quiet and the
    # link watchdog has tripped: a stop from ARMED starts the next frame early (pwm_sync), one
    # short frame that a count across the trip would add (a fresh clone's run counted 53).
    def bracketed_counts() -> tuple[float, tuple[int, int], float]:
        return emulator.now_s(), emulator.pulse_counts(), emulator.now_s()

    wait_emulated(emulator, LINK_TIMEOUT_MS / 1000 + 0.15)
    assert host.telemetry().state == m.State.FAILSAFE
    start_early, counts_before, start_late = bracketed_counts()
    deadline = time.monotonic() + 20.0
    while emulator.now_s() - start_late < 1.0 and time.monotonic() < deadline:
        time.sleep(0.05)  # one emulated second: 50 pulses, so 5 % off is 2.5 pulses
    end_early, counts_after, end_late = bracketed_counts()
    shortest, longest = end_early - start_late, end_late - start_early
    assert shortest >= 1.0, (shortest, longest)
    for before, after in zip(counts_before, counts_after, strict=True):
        assert 50.0 * shortest - 1 <= after - before <= 50.0 * longest + 1, (
            after - before, shortest, longest,
        )  # fmt: skip


def wait_emulated(emulator, seconds: float, every_20ms=None, wall_timeout_s: float = 10.0):
    """Until `seconds` of emulated time have passed, calling `every_20ms` (wall time) meanwhile:
    the emulator is paced to wall time but falls behind it on a loaded machine, and the
    watchdogs count the board's time."""
    end, give_up = emulator.now_s() + seconds, time.monotonic() + wall_timeout_s
    while emulator.now_s() < end:
        assert time.monotonic() < give_up, f"the emulator ran {seconds} s in {wall_timeout_s} s"
        time.sleep(0.02 if every_20ms else 0.01)
        if every_20ms:
            every_20ms()


def test_link_watchdog_trips_200ms_after_the_last_command(emulator, host):
    delays = []
    for _ in range(20):
        host.arm()
        host.drive(0.1)
        assert host.state() == m.State.ARMED
        emulator.take_events()
        host.command(ARM)  # the last COMMAND before the cable goes quiet
        wait_emulated(emulator, LINK_TIMEOUT_MS / 1000 + 0.15)
        delays += led_falls_after_frames(emulator.take_events())
        telemetry = host.telemetry()
        assert (telemetry.state, telemetry.reason) == (m.State.FAILSAFE, m.Reason.LINK_TIMEOUT)
        assert (telemetry.steer_us, telemetry.throttle_us) == (1500, 1500)
    print(
        f"link watchdog, {len(delays)} cuts, emulated ms: min {min(delays):.3f} "
        f"median {statistics.median(delays):.3f} max {max(delays):.3f}"
    )
    assert len(delays) == 20
    assert all(
        LINK_TIMEOUT_MS - TRIP_EARLY_MS <= d < LINK_TIMEOUT_MS + TRIP_LATE_MS for d in delays
    ), delays


def test_a_stale_decision_trips_300ms_after_it_last_changed(emulator, host):
    delays = []
    for _ in range(5):
        host.arm()
        emulator.take_events()
        host.command(ARM)  # a new decision ...
        # ... then the same one repeated: a hung control loop
        wait_emulated(emulator, DECISION_STALE_MS / 1000 + 0.15,
                      lambda: host.command(ARM, new=False))  # fmt: skip
        events = emulator.take_events()
        first_frame = next(e for e in events if e.kind == "F")
        fall = next(e for e in events if e.kind == "L" and e.value == 0)
        delays.append((fall.cycle - first_frame.cycle) * 1000.0 / F_CPU)
        telemetry = host.telemetry()
        assert (telemetry.state, telemetry.reason) == (m.State.FAILSAFE, m.Reason.DECISION_STALE)
    print(f"decision stale, emulated ms: {', '.join(f'{d:.3f}' for d in delays)}")
    assert all(
        DECISION_STALE_MS - TRIP_EARLY_MS <= d < DECISION_STALE_MS + TRIP_LATE_MS for d in delays
    ), delays


def test_estop_latches_until_clear_then_arm(emulator, host):
    host.arm()
    host.drive(0.2, throttle=2000)
    assert emulator.pulses_us()[1] > 1550, "armed: the throttle pulse follows the command"
    host.command(m.CommandFlags.ESTOP | ARM, throttle=2000)
    host.drive(0.1, throttle=2000)  # ARM held, no CLEAR: the latch holds
    telemetry = host.telemetry()
    assert (telemetry.state, telemetry.reason) == (m.State.ESTOP, m.Reason.ESTOP_COMMAND)
    assert emulator.pulses_us() == pytest.approx((1500.0, 1500.0), abs=1.0)
    host.drive(0.1, flags=m.CommandFlags.CLEAR | ARM)  # CLEAR with ARM still up: ignored
    assert host.state() == m.State.ESTOP
    host.drive(0.1, flags=m.CommandFlags.CLEAR)
    telemetry = host.telemetry()
    assert (telemetry.state, telemetry.reason) == (m.State.DISARMED, m.Reason.CLEARED)
    host.drive(0.1)  # the ARM edge, after the clear
    assert host.state() == m.State.ARMED


def test_config_persists_in_eeprom_across_a_reset(emulator, host):
    config = m.Config(1100, 1520, 1900, 1000, 1480, 2000, 8000, 5000, 20000, 1)
    host.send(config)
    ack = host.wait_for(lambda x: isinstance(x, m.ConfigAck), what="CONFIG_ACK")
    assert (ack.result, ack.persisted) == (m.ConfigResult.ACCEPTED, 1)
    boot_count = int.from_bytes(emulator.eeprom()[:4], "little")
    emulator.reset()
    hello = host.wait_for(lambda x: isinstance(x, m.Hello), what="HELLO after the reset")
    assert hello.config_from_storage == 1
    assert int.from_bytes(emulator.eeprom()[:4], "little") == boot_count + 1
    host.send(m.ConfigRequest())
    stored = host.wait_for(lambda x: isinstance(x, m.Config), what="CONFIG")
    assert stored == config
    time.sleep(0.1)  # a few pulse periods after boot: the stored neutrals are on the pins
    assert emulator.pulses_us() == pytest.approx((1520.0, 1480.0), abs=1.0)


def test_the_hello_names_why_the_board_started(emulator, host):
    """simavr starts the chip with PORF set (a power-on); the emulator's resets set the flag
    their cause sets on the chip; the binary reads MCUSR before its C runtime runs and names the
    cause in every HELLO of that boot."""
    host.send(m.HelloRequest())
    hello = host.wait_for(lambda x: isinstance(x, m.Hello), what="HELLO")
    assert hello.reset_cause == m.ResetCause.POWER_ON
    causes = [m.ResetCause.EXTERNAL, m.ResetCause.WATCHDOG, m.ResetCause.BROWN_OUT,
              m.ResetCause.POWER_ON, m.ResetCause.EXTERNAL]  # fmt: skip
    for cause in causes:
        before = hello.boot_id
        emulator.reset(cause)
        hello = host.wait_for(lambda x: isinstance(x, m.Hello), what=f"HELLO after {cause.name}")
        assert hello.boot_id != before and hello.reset_cause == cause
        host.send(m.HelloRequest())
        again = host.wait_for(lambda x: isinstance(x, m.Hello), what="HELLO on request")
        assert (again.boot_id, again.reset_cause) == (hello.boot_id, cause)
    assert [e.value for e in emulator.take_events() if e.kind == "R"] == [int(c) for c in causes]
    with pytest.raises(ValueError):
        emulator.reset(m.ResetCause.UNKNOWN)  # no reset sets no flag


def test_a_reset_of_the_chip_stops_nothing_outside_it(emulator, host):
    """The receiver's pulses and the wheel encoder go on through a reset (simavr's cancels the
    emulator's timers that drive them): the rebooted board counts both again."""
    emulator.rc_receiver([1500, 1620, 1000])
    emulator.set_encoder_hz(500.0)
    time.sleep(0.3)
    emulator.reset()
    host.wait_for(lambda x: isinstance(x, m.Hello), what="HELLO after the reset")
    time.sleep(0.4)
    tel = host.telemetry()
    assert tel.mcu_time_ms < 600  # the new boot's
    assert tel.flags & m.TelemetryFlags.RC_SIGNAL
    assert (tel.rc_steer_us, tel.rc_throttle_us, tel.rc_switch_us) == pytest.approx(
        (1500, 1620, 1000), abs=1
    )
    assert tel.encoder_ticks >= 0.5 * 500 * tel.mcu_time_ms / 1000


def test_garbage_on_the_uart_neither_arms_nor_stops_the_board(emulator, host):
    rng = random.Random(17)
    before = host.telemetry()
    emulator.take_events()
    for _ in range(20):
        host.serial.write(bytes(rng.randrange(256) for _ in range(200)))
        time.sleep(0.01)
    host.serial.write(b"\x00")  # end whatever frame the noise left open
    host.send(m.Ping(0xC0FFEE))
    pong = host.wait_for(lambda x: isinstance(x, m.Pong), what="PONG after the noise")
    assert pong.nonce == 0xC0FFEE
    after = host.telemetry()
    assert after.state == m.State.DISARMED
    assert not any(e.kind == "L" and e.value == 1 for e in emulator.take_events())
    rejected = lambda t: t.bad_crc + t.bad_length + t.overruns  # noqa: E731
    assert rejected(after) > rejected(before)
    host.arm()
    assert host.state() == m.State.ARMED, "the link works again after the noise"


def test_the_encoder_on_int0_counts_the_driven_edges(emulator, host):
    start = host.telemetry().encoder_ticks
    # The square wave runs between the emulator's handling of the two requests; the host can
    # bracket those instants only (a loaded machine widens the bracket by milliseconds).
    before_on = emulator.now_s()
    emulator.set_encoder_hz(400.0)
    after_on = emulator.now_s()
    time.sleep(0.5)
    before_off = emulator.now_s()
    emulator.set_encoder_hz(0.0)
    after_off = emulator.now_s()
    time.sleep(0.05)
    counted = host.telemetry().encoder_ticks - start
    shortest, longest = before_off - after_on, after_off - before_on
    assert 400.0 * shortest - 2 <= counted <= 400.0 * longest + 2, (counted, shortest, longest)


def test_carrt_check_passes_against_the_emulated_board(emulator):
    from carrt.cli import main

    assert main(["check", "--port", emulator.port]) == 0


def test_a_missing_firmware_file_is_one_line_and_exit_2(tmp_path):
    done = subprocess.run(
        [sys.executable, "-m", "firmware_bridge.avr_board", "--elf", str(tmp_path / "no.elf")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2
    assert done.stderr.strip() == f"avr board: error: firmware {tmp_path / 'no.elf'} not found"


def test_the_avr_board_closes_the_loop_through_the_wheel_model():
    from firmware_bridge.avr_board import AvrBoard
    from firmware_bridge.drivetrain import WheelPlant

    try:
        board = AvrBoard(WheelPlant()).start()
    except AvrEmulatorError as exc:
        pytest.fail(str(exc), pytrace=False)
    host = RawHost(board.port)
    try:
        host.wait_for(lambda x: isinstance(x, m.Telemetry) and x.mcu_time_ms > 150, 3.0)
        host.arm()
        host.drive(1.0, throttle=3000)
        telemetry = host.telemetry()
        assert telemetry.state == m.State.ARMED
        assert telemetry.encoder_ticks > 20, "the wheel model turned the encoder on INT0"
    finally:
        host.close()
        board.stop()


def test_carrt_drive_sim_runs_on_the_emulated_board():
    done = subprocess.run(
        [sys.executable, "-m", "carrt", "drive", "--sim", "--autopilot", "--model", "demo",
         "--duration", "4", "--board", "avr"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert "emulated ATmega328P running the firmware binary" in done.stdout
    (distance,) = [line for line in done.stdout.splitlines() if line.startswith("distance")]
    metres = float(distance.split()[1])
    assert metres > 2.0, f"the car barely moved under the emulated board: {distance}"


def test_the_firmware_size_in_the_docs_is_what_make_firmware_prints():
    """docs/car.md shows `make firmware`'s size lines; they are the built firmware's own."""
    import re
    import subprocess

    from firmware_bridge.avr_emulator import FIRMWARE_ELF, REPO, build

    build((FIRMWARE_ELF,))
    printed = subprocess.run(["avr-size", "-C", "--mcu=atmega328p", str(FIRMWARE_ELF)],
                             capture_output=True, text=True, check=True).stdout  # fmt: skip
    shown = (REPO / "docs" / "car.md").read_text()
    for kind in ("Program", "Data"):
        (line,) = re.findall(rf"^{kind}:\s+\d+ bytes \([\d.]+% Full\)", printed, re.M)
        assert line in shown, f"docs/car.md should show `{line}`"
