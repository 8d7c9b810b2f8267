"""The real firmware binary on an emulated ATmega328P: build it, start it, ask it what it did.

Why: the x86 build of the C core (virtual.py) checks the logic, but not what is flashed: the
Arduino core, Timer1's pulses, the UART at 250000 baud, the encoder interrupt, EEPROM, 16-bit
int arithmetic. `make firmware` builds the sketch into build/firmware/carrt_fw.elf; the emulator
(firmware/emulator/carrt_avr_emu.c, built into build/emulator/ against simavr) runs that ELF at
16 MHz, paced to wall time, its UART bridged to a pty that the host opens like /dev/ttyACM0.

This module builds both on first use (make, in a source checkout) and speaks the emulator's
line protocol on its stdin/stdout: emulated time, pulse widths measured on OC1A/OC1B, the ARMED
LED's edges and frame arrivals with their cycle stamps, the encoder rate, a reset that keeps
EEPROM and sets its cause's reset flag. Every time it reports is emulated time, so the tests
measure the board's watchdog with the board's own clock, not the test machine's scheduling.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path

from firmware_bridge.messages import ResetCause
from firmware_bridge.port_lock import PortLock
from firmware_bridge.receiver_pins import FRAME_US, SLOT_US

F_CPU = 16_000_000
CYCLES_PER_US = F_CPU // 1_000_000
REPO = Path(__file__).resolve().parents[1]
FIRMWARE_ELF = REPO / "build" / "firmware" / "carrt_fw.elf"
EMULATOR = REPO / "build" / "emulator" / "carrt_avr_emu"
DEBIAN_PACKAGES = "gcc-avr avr-libc arduino-core-avr simavr libsimavr-dev"
ARDUINO_CORE = Path("/usr/share/arduino/hardware/arduino/avr/cores/arduino")
SIMAVR_HEADER = Path("/usr/include/simavr/sim_avr.h")
READY_TIMEOUT_S = 10.0


class AvrEmulatorError(RuntimeError):
    """The emulated board cannot run here (tools missing, build failed, emulator died)."""


def missing_tools() -> list[str]:
    """What this machine lacks to build and emulate the firmware (empty when all is there)."""
    missing = [
        tool for tool in ("avr-gcc", "avr-g++", "avr-size", "make", "gcc") if not shutil.which(tool)
    ]
    if not ARDUINO_CORE.is_dir():
        missing.append(str(ARDUINO_CORE))
    if not SIMAVR_HEADER.exists():
        missing.append(str(SIMAVR_HEADER))
    return missing


def build(targets: tuple[Path, ...] = (FIRMWARE_ELF, EMULATOR)) -> None:
    """Build the firmware ELF and the emulator with make (no-op when current).

    A lock file serialises builds, so several test processes can ask at once.
    """
    missing = missing_tools()
    if missing:
        raise AvrEmulatorError(
            f"the emulated AVR needs {', '.join(missing)}: apt-get install {DEBIAN_PACKAGES}"
        )
    if not (REPO / "Makefile").exists():
        raise AvrEmulatorError(
            f"the emulated AVR is built from a source checkout; {REPO} is not one"
        )
    lock_path = REPO / "build" / ".avr-build.lock"
    lock_path.parent.mkdir(parents=True, exist_ok=True)
    with open(lock_path, "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        names = [str(t.relative_to(REPO)) for t in targets]
        done = subprocess.run(
            ["make", "-s", "-C", str(REPO), *names], capture_output=True, text=True, check=False
        )
    if done.returncode != 0:
        lines = (done.stderr or done.stdout).strip().splitlines() or ["(no output)"]
        raise AvrEmulatorError(f"building the emulated AVR failed: {lines[-1]}")


@dataclass(frozen=True)
class Event:
    """Something the emulator saw, stamped with the emulated cycle it happened at.

    kind: "L" ARMED LED level (value 0/1), "F" a host frame's 0x00 delimiter entered the UART,
    "A"/"B" steering/ESC pulse width changed (value in cycles), "R" emulated reset (value: its
    messages.ResetCause), "W" a receiver channel's (value) first pulse with a new width ended,
    "O" its train stopped, "N"/"E" the first / last edge of a burst on that channel (rc_burst).
    """

    kind: str
    value: int
    cycle: int

    @property
    def t_s(self) -> float:
        return self.cycle / F_CPU


@dataclass(frozen=True)
class BusyPin:
    """Cycles a busy pin was high in a measuring interval, how often, and the longest stretch."""

    total: int
    count: int
    longest: int


class AvrEmulator:
    """One emulated board: the process, its pty and its control channel (thread-safe)."""

    def __init__(
        self,
        elf: str | os.PathLike | None = None,
        *,
        eeprom_path: str | os.PathLike | None = None,
        port_path: str | os.PathLike | None = None,
    ) -> None:
        if elf is None:
            build()
            elf = FIRMWARE_ELF
        else:
            build((EMULATOR,))
        elf = Path(elf)
        if not elf.is_file():
            raise AvrEmulatorError(f"firmware {elf} not found (make firmware builds it)")
        self.elf = elf
        self._own_dir: tempfile.TemporaryDirectory | None = None
        if port_path is None:
            self._own_dir = tempfile.TemporaryDirectory(prefix="carrt-avr-")
            port_path = Path(self._own_dir.name) / "ttyAVR0"
        self._port_lock = PortLock(port_path)  # a second board on this path stops here
        args = [str(EMULATOR), str(elf), "--link", str(port_path)]
        if eeprom_path is not None:
            args += ["--eeprom", str(eeprom_path)]
        self._lock = threading.Lock()
        # stderr goes to a file, not a pipe: nobody reads it while the emulator runs, and a full
        # pipe would stall the emulated CPU
        self._stderr = tempfile.TemporaryFile(mode="w+")  # noqa: SIM115 (closed in close())
        self._proc = subprocess.Popen(
            args,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._stderr,
            text=True,
            bufsize=1,
        )
        try:
            self.port = self._wait_ready()
        except BaseException:
            self._port_lock.release()
            raise

    def _wait_ready(self) -> str:
        timer = threading.Timer(READY_TIMEOUT_S, self._proc.kill)
        timer.start()
        try:
            assert self._proc.stdout is not None
            for line in self._proc.stdout:  # simavr prints what it loaded first
                if line.startswith("ready "):
                    return line.split(" ", 1)[1].strip()
        finally:
            timer.cancel()
        self._proc.wait()
        self._stderr.seek(0)
        err = self._stderr.read().strip().splitlines()
        raise AvrEmulatorError(
            f"the AVR emulator did not start: {err[-1] if err else 'no ready line'}"
        )

    # ----------------------------------------------------------------- control channel
    def ask(self, command: str) -> str:
        """Send one control command, return its reply line (without the newline)."""
        with self._lock:
            if self._proc.poll() is not None:
                raise AvrEmulatorError(f"the AVR emulator exited ({self._proc.returncode})")
            assert self._proc.stdin is not None and self._proc.stdout is not None
            self._proc.stdin.write(command + "\n")
            self._proc.stdin.flush()
            reply = self._proc.stdout.readline()
        if not reply:
            raise AvrEmulatorError("the AVR emulator closed its control channel")
        if reply.startswith("error"):
            raise AvrEmulatorError(reply.strip())
        return reply.rstrip("\n")

    def cycle(self) -> int:
        """The emulated cycle counter (16 per microsecond)."""
        return int(self.ask("time").split()[1])

    def now_s(self) -> float:
        return self.cycle() / F_CPU

    def lag_s(self) -> float:
        """How far emulated time trails wall time right now (0 when the emulator keeps up)."""
        return int(self.ask("time").split()[2]) / 1e6

    def pulses_us(self) -> tuple[float, float]:
        """Width of the last complete steering and ESC pulses, in microseconds (0: none yet)."""
        _, a, _, b, _ = self.ask("pulses").split()
        return int(a) / CYCLES_PER_US, int(b) / CYCLES_PER_US

    def pulse_counts(self) -> tuple[int, int]:
        _, _, a, _, b = self.ask("pulses").split()
        return int(a), int(b)

    def busy(self) -> tuple[BusyPin, BusyPin, BusyPin]:
        """CPU time in fw_core_rx (D12), fw_core_tick (D11) and handing receiver edges to the
        core (D8) since the last call."""
        v = [int(x) for x in self.ask("busy").split()[1:]]
        return BusyPin(*v[0:3]), BusyPin(*v[3:6]), BusyPin(*v[6:9])

    def take_events(self) -> list[Event]:
        """The events since the last call (the emulator keeps up to 16384 in between)."""
        fields = self.ask("events").split()
        if int(fields[1]) > 0:
            raise AvrEmulatorError(f"the emulator dropped {fields[1]} events: read them sooner")
        events = []
        for token in fields[2:]:
            value, cycle = token[1:].split("@")
            events.append(Event(token[0], int(value), int(cycle)))
        return events

    def set_encoder_hz(self, rising_edges_per_s: float) -> None:
        """Drive PD2 (INT0) with a square wave of this many rising edges per second."""
        self.ask(f"encoder {max(0.0, rising_edges_per_s):.3f}")

    def rc_train(
        self, channel: int, width_us: float, period_us: float = 20_000.0, phase_us: float = 0.0
    ) -> None:
        """Drive a receiver pin (0 steering D4, 1 throttle D5, 2 switch D6) with pulses of
        width_us every period_us, the first after phase_us. A running train takes a new width
        at its next pulse and logs a W event (value: channel) at that pulse's falling edge."""
        self.ask(f"rc {int(channel)} {width_us:.3f} {period_us:.3f} {phase_us:.3f}")

    def rc_receiver(self, widths) -> None:
        """A receiver on D4-D6: the three channels' trains at these widths, one after another in
        every 20 ms frame (the layout receiver_pins.py plays into the virtual boards)."""
        for ch, width in enumerate(widths):
            self.rc_train(ch, width, FRAME_US, SLOT_US[ch])

    def rc_off(self, channel: int) -> None:
        """Stop a receiver train after the pulse in flight (an O event at its falling edge)."""
        self.ask(f"rc {int(channel)} off")

    def rc_noise(self, channel: int, mean_gap_us: float, seed: int) -> None:
        """Random edges on a receiver pin, 1 .. 2 * mean_gap_us apart."""
        self.ask(f"rc {int(channel)} noise {mean_gap_us:.3f} {int(seed)}")

    def rc_burst(
        self,
        channel: int,
        edges: int,
        gap_min_us: float,
        gap_max_us: float,
        seed: int,
        delay_us: float = 0.0,
        *,
        after_fall_of: int | None = None,
    ) -> None:
        """Glitches on a receiver pin on top of whatever drives it (a train, noise, the idle
        level): delay_us from now, or from the next falling edge of the train on channel
        `after_fall_of` (then delay_us may be negative: a burst around that edge), the line
        flips `edges` times (rounded up to even: it ends at the level it would have had),
        gap_min_us .. gap_max_us apart; N and E events (value: channel) at its first and last
        edge."""
        anchor = "" if after_fall_of is None else f" {int(after_fall_of)}"
        self.ask(
            f"rc {int(channel)} burst {int(edges)} {gap_min_us:.3f} {gap_max_us:.3f} "
            f"{int(seed)} {delay_us:.3f}{anchor}"
        )

    def reset(self, cause: ResetCause = ResetCause.EXTERNAL) -> None:
        """Reset the board: RAM and registers start over, EEPROM is kept, and MCUSR holds the
        flag this cause sets on the chip (EXTERNAL: the reset button or DTR; WATCHDOG: the
        watchdog ran out; BROWN_OUT, POWER_ON), so its next HELLO names it."""
        words = {
            ResetCause.EXTERNAL: "external",
            ResetCause.WATCHDOG: "watchdog",
            ResetCause.BROWN_OUT: "brown-out",
            ResetCause.POWER_ON: "power-on",
        }
        if cause not in words:
            raise ValueError(f"no reset sets the flags of {ResetCause(cause).name}")
        self.ask(f"reset {words[ResetCause(cause)]}")

    def eeprom(self) -> bytes:
        """The first 64 bytes of EEPROM (boot counter at 0, config blob at 8)."""
        return bytes.fromhex(self.ask("eeprom").split()[1])

    # ----------------------------------------------------------------- lifecycle
    def close(self) -> None:
        """Stop the emulator (it saves EEPROM to its file, if it has one)."""
        if self._proc.poll() is None:
            try:
                self.ask("quit")
                self._proc.wait(timeout=5.0)
            except (AvrEmulatorError, OSError, subprocess.TimeoutExpired):
                self._proc.kill()
                self._proc.wait()
        for stream in (self._proc.stdin, self._proc.stdout, self._stderr):
            if stream is not None:
                stream.close()
        self._port_lock.release()
        if self._own_dir is not None:
            self._own_dir.cleanup()
            self._own_dir = None

    def __enter__(self) -> AvrEmulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
