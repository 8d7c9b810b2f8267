"""The link's receiving half: what arrives from the board, and the thread that reads it.

A `Receiver` is a part the BoardLink (firmware_bridge/link.py) creates and holds. It owns what
only the receiving side touches: the frame decoder, the latest telemetry sample and its arrival
times, the board's identity from its HELLO, the requests waiting for an answer, and the receiver
thread with its reconnection. What the link must act on it reports through `LinkEvents`, the
link's side of the contract: the port came back or was lost, telemetry arrived (the link follows
its arm and clear requests on it), the board rebooted, or the board speaks another protocol.
The receiver never writes commands and never touches the arm state: those are the link's.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

import serial

from firmware_bridge import messages as m
from firmware_bridge.codec import FrameDecoder, encode_frame
from firmware_bridge.link_types import (
    BoardInfo,
    HandshakeTimeout,
    LinkCounters,
    LinkError,
    PortUnavailable,
    ProtocolMismatch,
    TelemetrySample,
    open_port,
)
from firmware_bridge.timing import HELLO_RETRY_S, RECONNECT_RETRY_S


class LinkEvents(Protocol):
    """What the receiver tells the link that holds it (each called from the receiver's thread,
    or from whichever thread fed it bytes)."""

    def port_back(self, ser: serial.Serial) -> None:
        """The port reopened and the board said HELLO again: count it, write commands to it."""

    def port_lost(self) -> None:
        """The port errored (the cable is gone): stop writing, forget any arm request, count
        it; the receiver reopens the port when it comes back."""

    def telemetry_arrived(self, sample: TelemetrySample) -> None:
        """A telemetry frame, timestamped on arrival."""

    def board_rebooted(self, info: BoardInfo) -> None:
        """A HELLO with a new boot id: the board restarted, disarmed."""

    def board_mismatched(self, error: ProtocolMismatch) -> None:
        """An unprompted HELLO in another protocol: the board was reflashed under us."""

    def gave_up(self, error: LinkError) -> None:
        """Reconnection found a board in another protocol: the receiver has stopped."""


class Receiver:
    """Decodes what the board sends, keeps the latest telemetry, answers waiting requests, and
    (once started) reads the port on its own thread, reopening it when it goes away."""

    def __init__(
        self,
        events: LinkEvents,
        *,
        port: str,
        baud: int,
        handshake_timeout_s: float,
        clock: Callable[[], float],
        counters: LinkCounters,
        next_seq: Callable[[], int],
    ) -> None:
        self.events = events
        self.port = port
        self.baud = baud
        self.handshake_timeout_s = handshake_timeout_s
        self.clock = clock
        self.counters = counters
        self.next_seq = next_seq
        self.board: BoardInfo | None = None
        self.telemetry: TelemetrySample | None = None
        self.telemetry_times: collections.deque[float] = collections.deque(maxlen=100)
        self._decoder = FrameDecoder()
        self._waiters: dict[tuple[int, int], tuple[threading.Event, list[Any]]] = {}
        self._ser: serial.Serial | None = None
        self._running = False
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ the thread
    def start(self, ser: serial.Serial) -> None:
        """Read `ser` (already handshaken) on the receiver thread until `stop`."""
        self._ser = ser
        self._running = True
        self._thread = threading.Thread(target=self._loop, name="link-rx", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
        self._ser = None

    @property
    def running(self) -> bool:
        return self._running

    def _loop(self) -> None:
        while self._running:
            ser = self._ser
            if ser is None:
                self._reconnect()
                continue
            try:
                data = ser.read(max(1, ser.in_waiting))
            except (serial.SerialException, OSError, TypeError):
                self._ser = None
                self.events.port_lost()
                continue
            if data:
                self.feed(data)

    def _reconnect(self) -> None:
        time.sleep(RECONNECT_RETRY_S)
        if not self._running:
            return
        try:
            ser = open_port(self.port, self.baud)
        except PortUnavailable:
            return
        try:
            self.handshake(ser)
        except ProtocolMismatch as exc:
            ser.close()
            self.events.gave_up(exc)
            self._running = False
            return
        except (LinkError, serial.SerialException, OSError):
            ser.close()
            return
        self._ser = ser
        self.events.port_back(ser)

    # ------------------------------------------------------------------ the handshake
    def handshake(self, ser: serial.Serial) -> None:
        """Flush stale bytes, ask for HELLO until it comes, check the protocol and boot id."""
        ser.reset_input_buffer()
        self._decoder.discard_partial()
        deadline = self.clock() + self.handshake_timeout_s
        next_request = 0.0
        while self.clock() < deadline:
            if self.clock() >= next_request:
                ser.write(b"\x00" + encode_frame(m.HelloRequest(), self.next_seq()))
                next_request = self.clock() + HELLO_RETRY_S
            data = ser.read(max(1, ser.in_waiting))
            for frame in self._decoder.feed(data):
                if isinstance(frame.message, m.Hello):
                    self._accept_hello(frame.message)
                    return
                self._dispatch_frame(frame)
        raise HandshakeTimeout(
            f"no HELLO from the board on {self.port} within {self.handshake_timeout_s:.1f} s "
            "(wrong port or baud, or firmware not flashed?)"
        )

    def _accept_hello(self, hello: m.Hello) -> None:
        if hello.protocol_hash != m.PROTOCOL_HASH:
            version = f"{hello.fw_major}.{hello.fw_minor}.{hello.fw_patch}"
            raise ProtocolMismatch(
                f"board on {self.port} speaks protocol {hello.protocol_hash:08x} (firmware "
                f"{version}) but this carrt speaks {m.PROTOCOL_HASH:08x}: flash the firmware "
                "shipped with this carrt (docs/car.md#flashing-the-firmware)"
            )
        info = BoardInfo(
            protocol_hash=hello.protocol_hash,
            boot_id=hello.boot_id,
            firmware_version=(hello.fw_major, hello.fw_minor, hello.fw_patch),
            config_from_storage=bool(hello.config_from_storage),
            reset_cause=(
                m.ResetCause(hello.reset_cause)
                if hello.reset_cause in {c.value for c in m.ResetCause}
                else m.ResetCause.UNKNOWN
            ),
        )
        previous, self.board = self.board, info
        if previous is not None and previous.boot_id != info.boot_id:
            self.counters.reboots_detected += 1
            self.events.board_rebooted(info)

    # ------------------------------------------------------------------ what arrives
    def feed(self, data: bytes) -> None:
        """Bytes from the board, from whichever transport carried them (the receiver thread's
        serial port, or the in-process core of firmware_bridge/direct.py)."""
        for frame in self._decoder.feed(data):
            self._dispatch_frame(frame)
        self.counters.bad_crc = self._decoder.bad_crc
        self.counters.bad_length = self._decoder.bad_length
        self.counters.overruns = self._decoder.overruns

    def _dispatch_frame(self, frame: Any) -> None:
        now = self.clock()
        self.counters.frames_received += 1
        message = frame.message
        if isinstance(message, m.Telemetry):
            sample = TelemetrySample(message, now)
            self.telemetry = sample
            self.telemetry_times.append(now)
            self.events.telemetry_arrived(sample)
        elif isinstance(message, m.Hello):
            try:
                self._accept_hello(message)  # unprompted: the board rebooted on its own
            except ProtocolMismatch as exc:
                self.events.board_mismatched(exc)
        elif isinstance(message, m.Pong):
            self._resolve((m.Pong.TYPE, message.nonce), message)
        elif isinstance(message, m.Config):
            self._resolve((m.Config.TYPE, 0), message)
        elif isinstance(message, m.ConfigAck):
            self._resolve((m.ConfigAck.TYPE, message.config_seq), message)

    def wait_until_still(self, still_s: float = 0.15, timeout_s: float = 5.0) -> None:
        """Wait until the encoder has not moved for `still_s` (the board refuses to arm before).

        The board checks 100 ms of stillness itself; waiting a little longer here means the
        arm request that follows is not refused for a tick that was still in flight.
        Stillness is measured between telemetry frames (their receive times), not on the host's
        clock: on a busy machine no new frame may arrive for a while, and an old frame's ticks
        are no evidence that the wheels stopped since.
        """
        deadline = self.clock() + timeout_s
        last_ticks: int | None = None
        since = 0.0
        while self.clock() < deadline:
            sample = self.telemetry
            if sample is not None:
                ticks = sample.telemetry.encoder_ticks
                if ticks != last_ticks:
                    last_ticks, since = ticks, sample.received_at
                elif sample.received_at - since >= still_s:
                    return
            time.sleep(0.005)
        raise LinkError(f"wheels still turning after {timeout_s:.1f} s (encoder keeps ticking)")

    # ------------------------------------------------------------------ answers to requests
    def expect(self, key: tuple[int, int]) -> tuple[threading.Event, list[Any]]:
        """Register interest in the answer `key` (type, nonce or sequence) before asking: the
        event is set and the answer put in the list when it arrives. `forget` it after."""
        waiter: tuple[threading.Event, list[Any]] = (threading.Event(), [])
        self._waiters[key] = waiter
        return waiter

    def forget(self, key: tuple[int, int]) -> None:
        self._waiters.pop(key, None)

    def _resolve(self, key: tuple[int, int], message: Any) -> None:
        waiter = self._waiters.get(key)
        if waiter is not None:
            waiter[1].append(message)
            waiter[0].set()
