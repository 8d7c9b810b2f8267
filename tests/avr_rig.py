"""A raw host for the emulated AVR: frames written to its pty by hand, answers read back.

The HIL tests against the emulated board (test_avr_emulated.py) need exact control over when
each COMMAND is sent and when the link goes quiet, which BoardLink's 50 Hz sender hides; so
they speak the protocol directly with the same codec the link uses.
"""

from __future__ import annotations

import time

import pytest
import serial

from firmware_bridge import messages as m
from firmware_bridge.avr_emulator import AvrEmulator, AvrEmulatorError
from firmware_bridge.codec import FrameDecoder, encode_frame


def start_emulator(**kwargs) -> AvrEmulator:
    """An emulated board, or a test failure naming what to install (never a skip)."""
    try:
        return AvrEmulator(**kwargs)
    except AvrEmulatorError as exc:
        pytest.fail(str(exc), pytrace=False)


class RawHost:
    """The host end of the pty: send messages, collect every frame the board sends."""

    def __init__(self, port: str) -> None:
        self.serial = serial.Serial(port, 250000, timeout=0)
        self.decoder = FrameDecoder()
        self.seq = 0
        self.decision = 1
        self.received: list = []

    def send(self, message) -> None:
        self.seq = (self.seq + 1) & 0xFFFF
        self.serial.write(encode_frame(message, self.seq))

    def command(self, flags: int = 0, steering: int = 0, throttle: int = 0, *, new: bool = True):
        """One COMMAND; a new decision id each time unless new=False (a hung control loop)."""
        if new:
            self.decision += 1
        self.send(m.Command(steering, throttle, self.decision, flags))

    def drive(self, seconds: float, flags: int = m.CommandFlags.ARM, **kwargs) -> None:
        """Commands every 20 ms, like the link's sender thread."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.command(flags, **kwargs)
            self.poll()
            time.sleep(0.02)

    def poll(self) -> list:
        frames = self.decoder.feed(self.serial.read(4096))
        self.received.extend(f.message for f in frames)
        return frames

    def wait_for(self, predicate, timeout_s: float = 2.0, what: str = "a reply"):
        """The first received message (from now on) that satisfies predicate."""
        self.received.clear()
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            self.poll()
            for message in self.received:
                if predicate(message):
                    return message
            self.received.clear()
            time.sleep(0.005)
        raise AssertionError(f"no {what} from the emulated board within {timeout_s} s")

    def drain(self) -> None:
        """Forget whatever the board sent so far (telemetry piles up while a test sleeps)."""
        self.serial.read(1 << 16)
        self.decoder.discard_partial()
        self.received.clear()

    def telemetry(self, timeout_s: float = 1.0) -> m.Telemetry:
        """A TELEMETRY frame sent after this call."""
        self.drain()
        return self.wait_for(lambda x: isinstance(x, m.Telemetry), timeout_s, "TELEMETRY")

    def state(self) -> m.State:
        return m.State(self.telemetry().state)

    def arm(self) -> None:
        """Clear, then raise ARM: the 0 -> 1 edge in separate frames that arming needs."""
        self.command(m.CommandFlags.CLEAR)
        time.sleep(0.02)
        self.drive(0.06)

    def close(self) -> None:
        self.serial.close()
