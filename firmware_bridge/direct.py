"""The board link without a wire: the same C core and codec, in-process, on a simulated clock.

For running faster than real time the pty and the link's threads cannot be used (they live in
wall-clock time), so this subclass of BoardLink keeps every piece of its logic (arm, clear and
e-stop bookkeeping, handshake checks, telemetry timestamps) and only swaps the transport: bytes
written go straight into the firmware core, and a SimClock listener plays the parts of the
50 Hz sender thread, the receiver thread and the board's own main loop, at simulated time.
The firmware that decides is still the C core that is flashed onto the board.
"""

from __future__ import annotations

import secrets
from typing import Any

from firmware_bridge import messages as m
from firmware_bridge.drivetrain import Plant
from firmware_bridge.link import SEND_PERIOD_S, BoardLink, HandshakeTimeout
from firmware_bridge.native import FirmwareCore
from firmware_bridge.receiver_pins import ReceiverPins


class _CoreWire:
    """What BoardLink writes to: a 'serial port' whose far end is the firmware core."""

    def __init__(self, link: DirectBoardLink) -> None:
        self.link = link

    def write(self, data: bytes) -> int:
        core = self.link.core
        core.feed(data, self.link.now_ms())
        # Answers (PONG, CONFIG_ACK) come back at once, as over a wire with no delay: a request
        # must not wait for simulated time that only passes while the loop sleeps.
        out = core.take_output()
        if out:
            self.link.receive(out)
        return len(data)

    def close(self) -> None:
        pass


class DirectBoardLink(BoardLink):
    """A BoardLink to an in-process firmware core driving `plant`, stepped by a SimClock."""

    def __init__(self, plant: Plant, clock: Any) -> None:
        super().__init__("direct://firmware-core", clock=clock.now)
        self.plant = plant
        self.core = FirmwareCore()
        self.receiver_pins = ReceiverPins(self.core)  # silent until a transmitter is set
        self._next_send = 0.0
        self._tick_offset = 0
        clock.add_listener(self._step)

    def now_ms(self) -> int:
        return int(self.clock() * 1000.0)

    def open(self) -> DirectBoardLink:
        self.core.boot(secrets.randbits(32), self.now_ms(), m.ResetCause.POWER_ON)
        self._tick_offset = self.plant.step(0.0, 1500, 1500)
        self._ser = _CoreWire(self)  # type: ignore[assignment]
        self._send(_hello_request)
        if self.board is None:
            raise HandshakeTimeout("the in-process firmware core did not say HELLO")
        self._connected.set()
        self._running = True
        self._next_send = self.clock()
        return self

    def close(self) -> None:
        self._leave_disarmed(frames=1)  # no wire to lose it on
        self._running = False
        self._connected.clear()
        self._ser = None

    def _step(self, now: float, dt: float) -> None:
        """One step of simulated time: the sender's repeat, the board's loop, the receiver."""
        if not self._running:
            return
        if now >= self._next_send:
            self._write_command()
            self._next_send += SEND_PERIOD_S
            if self._next_send <= now:
                self._next_send = now + SEND_PERIOD_S
        self.receiver_pins.advance(int(now * 1e6))
        ticks = self.plant.step(dt, self.core.steer_us, self.core.throttle_us)
        self.core.set_encoder(ticks - self._tick_offset)
        self.core.tick(self.now_ms())
        out = self.core.take_output()
        if out:
            self.receive(out)

    def set_receiver(self, steer_us: int, throttle_us: int, switch_us: int) -> None:
        """The RC receiver's three pulse widths from its next frame on (the simulator's radio)."""
        self.receiver_pins.set(steer_us, throttle_us, switch_us)

    @property
    def state(self) -> m.State:
        return self.core.state


def _hello_request(seq: int) -> bytes:
    from firmware_bridge.codec import encode_frame

    return encode_frame(m.HelloRequest(), seq)
