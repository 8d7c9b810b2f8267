"""The emulated AVR as a drop-in for the virtual board: the real binary drives a plant.

VirtualBoard (virtual.py) runs the x86 build of the core; AvrBoard runs the flashed ELF in the
emulator (avr_emulator.py) and closes the loop the same way: it reads the pulse widths the
emulated Timer1 produces, steps the plant (the wheel model, or the simulator's car) with them,
and drives the encoder pin at the rate the plant's wheel turns. So `carrt drive --sim --board
avr` and `carrt check --port <pty>` exercise the binary a car would run.

Run from the command line with ``python -m firmware_bridge.avr_board``: it prints the port path
and runs until interrupted.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import time

from firmware_bridge.avr_emulator import AvrEmulator, AvrEmulatorError
from firmware_bridge.drivetrain import Plant, WheelPlant

STEP_S = 0.01  # the plant follows the pulses at 100 Hz (they change at 50 Hz at most)


class AvrBoard:
    """An emulated board plus a plant, stepped by a background thread."""

    LABEL = "emulated ATmega328P running the firmware binary"  # carrt's start-up line

    def __init__(
        self,
        plant: Plant | None = None,
        *,
        elf: str | os.PathLike | None = None,
        eeprom_path: str | os.PathLike | None = None,
        port_path: str | os.PathLike | None = None,
    ) -> None:
        self.plant = plant if plant is not None else WheelPlant()
        self.emulator = AvrEmulator(elf, eeprom_path=eeprom_path, port_path=port_path)
        self.port = self.emulator.port
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._receiver: list[int] | None = None

    def set_receiver(self, steer_us: int, throttle_us: int, switch_us: int) -> None:
        """Pulse trains on the emulated receiver pins (D4-D6), each change from its next pulse."""
        widths = [int(steer_us), int(throttle_us), int(switch_us)]
        if self._receiver is None:
            self.emulator.rc_receiver(widths)
        else:
            for ch, width in enumerate(widths):
                if self._receiver[ch] != width:
                    self.emulator.rc_train(ch, width)
        self._receiver = widths

    def step(self, dt_s: float, ticks_before: int) -> int:
        """Advance the plant under the pulses on the pins; set the encoder rate to match."""
        steer_us, throttle_us = self.emulator.pulses_us()
        if steer_us == 0.0:  # no pulse yet (booting): the servo and ESC hold still
            steer_us = throttle_us = 1500.0
        ticks = self.plant.step(dt_s, round(steer_us), round(throttle_us))
        self.emulator.set_encoder_hz(abs(ticks - ticks_before) / dt_s if dt_s > 0 else 0.0)
        return ticks

    def _run(self) -> None:
        last = time.monotonic()
        ticks = self.plant.step(0.0, 1500, 1500)
        while not self._stop.wait(STEP_S):
            now = time.monotonic()
            try:
                ticks = self.step(now - last, ticks)
            except AvrEmulatorError:
                return  # the emulator went away (stop() or a crash the host will notice)
            last = now

    def start(self) -> AvrBoard:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="avr-board", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self.emulator.close()

    def __enter__(self) -> AvrBoard:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m firmware_bridge.avr_board",
        description="Run the carrt firmware binary on an emulated ATmega328P behind a pty.",
    )
    parser.add_argument("--elf", help="firmware ELF (default: build it with make firmware)")
    parser.add_argument("--port-path", help="stable path for the port symlink (default: temp)")
    parser.add_argument("--eeprom", help="file that keeps the board's EEPROM between runs")
    parser.add_argument("--ticks-per-metre", type=float, default=200.0)
    args = parser.parse_args(argv)
    if args.elf is not None and not os.path.isfile(args.elf):
        print(f"avr board: error: firmware {args.elf} not found", file=sys.stderr)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        board = AvrBoard(
            WheelPlant(ticks_per_metre=args.ticks_per_metre),
            elf=args.elf,
            eeprom_path=args.eeprom,
            port_path=args.port_path,
        )
    except (AvrEmulatorError, OSError) as exc:
        print(f"avr board: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    print(f"emulated AVR ready on {board.port}; Ctrl-C to stop", flush=True)
    with board:
        stop.wait()
    print("emulated AVR stopped", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
