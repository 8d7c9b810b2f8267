"""BoardLink's receiving half: frames in from the receiver thread (or the in-process core),
telemetry timestamped, HELLOs checked, answers handed to the thread that asked, and the
arming/clearing requests followed on the board's telemetry.

A mixin of BoardLink (firmware_bridge/link.py), which owns the state these methods read: the
decoder, counters, locks, waiters and the arm/clear bookkeeping. It lives in its own file so each
half of the link reads on one screen; it is not meant to be used alone.
"""

from __future__ import annotations

import contextlib
import time
from typing import Any

import serial

from firmware_bridge import messages as m
from firmware_bridge.codec import encode_frame
from firmware_bridge.link_types import (
    BoardInfo,
    HandshakeTimeout,
    LinkError,
    PortUnavailable,
    ProtocolMismatch,
    TelemetrySample,
    open_port,
)
from firmware_bridge.timing import HELLO_RETRY_S, RECONNECT_RETRY_S


class ReceivePath:
    def _receive_loop(self) -> None:
        while self._running:
            ser = self._ser
            if ser is None:
                self._reconnect()
                continue
            try:
                data = ser.read(max(1, ser.in_waiting))
            except (serial.SerialException, OSError, TypeError):
                self._drop_connection()
                continue
            if data:
                self._dispatch_bytes(data)

    def _drop_connection(self) -> None:
        """The cable is gone: stop writing, forget any arm request, wait for it to return."""
        self._connected.clear()
        with self._state_lock:
            self._want_arm = False
            self._clear_pending = False
        with self._write_lock:
            if self._ser is not None:
                with contextlib.suppress(serial.SerialException, OSError):
                    self._ser.close()
                self._ser = None
        self.counters.disconnects += 1

    def _reconnect(self) -> None:
        time.sleep(RECONNECT_RETRY_S)
        if not self._running:
            return
        try:
            ser = open_port(self.port, self.baud)
        except PortUnavailable:
            return
        try:
            self._handshake(ser)
        except ProtocolMismatch as exc:
            ser.close()
            self.error = exc
            self._running = False
            return
        except (LinkError, serial.SerialException, OSError):
            ser.close()
            return
        with self._write_lock:
            self._ser = ser
        self.counters.reconnects += 1
        self._connected.set()

    def _handshake(self, ser: serial.Serial) -> None:
        """Flush stale bytes, ask for HELLO until it comes, check the protocol and boot id."""
        ser.reset_input_buffer()
        self._decoder.discard_partial()
        deadline = self.clock() + self.handshake_timeout_s
        next_request = 0.0
        while self.clock() < deadline:
            if self.clock() >= next_request:
                ser.write(b"\x00" + encode_frame(m.HelloRequest(), self._next_seq()))
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
                "shipped with this carrt (see README, 'Flashing the firmware')"
            )
        info = BoardInfo(
            protocol_hash=hello.protocol_hash,
            boot_id=hello.boot_id,
            firmware_version=(hello.fw_major, hello.fw_minor, hello.fw_patch),
            config_from_storage=bool(hello.config_from_storage),
        )
        previous, self.board = self.board, info
        if previous is not None and previous.boot_id != info.boot_id:
            self.counters.reboots_detected += 1
            with self._state_lock:
                self._want_arm = False
            if self.on_reboot is not None:
                self.on_reboot(info)

    def receive(self, data: bytes) -> None:
        """Bytes from the board, from whichever transport carried them (the receiver thread's
        serial port, or the in-process core of firmware_bridge/direct.py)."""
        self._dispatch_bytes(data)

    def _dispatch_bytes(self, data: bytes) -> None:
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
            self._telemetry = sample
            self._telemetry_times.append(now)
            self._watch_arming(message)
            if self.on_telemetry is not None:
                self.on_telemetry(sample)
        elif isinstance(message, m.Hello):
            try:
                self._accept_hello(message)  # unprompted: the board rebooted on its own
            except ProtocolMismatch as exc:
                self.error = exc
                self.estop()
        elif isinstance(message, m.Pong):
            self._resolve((m.Pong.TYPE, message.nonce), message)
        elif isinstance(message, m.Config):
            self._resolve((m.Config.TYPE, 0), message)
        elif isinstance(message, m.ConfigAck):
            self._resolve((m.ConfigAck.TYPE, message.config_seq), message)

    def _watch_arming(self, tel: m.Telemetry) -> None:
        """Follow the board: a finished clear stops the CLEAR flag, and once the board has
        left ARMED on its own, re-arming must be a new, explicit request."""
        with self._state_lock:
            left_latch = tel.state not in (m.State.ESTOP, m.State.FAILSAFE)
            sent = self._clear_sent_seq
            if (
                self._clear_pending
                and left_latch
                and sent is not None
                and _seq_reached(tel.last_seq, sent)
            ):
                self._clear_pending = False
            sent = self._arm_sent_seq
            if self._want_arm and sent is not None and _seq_reached(tel.last_seq, sent):
                if not left_latch:
                    self._want_arm = False
                elif tel.state == m.State.DISARMED and tel.arm_refusal:
                    self._want_arm = False  # refused: a new press must make a new edge
                    self.last_arm_refusal = m.ArmRefusal(tel.arm_refusal)

    def _resolve(self, key: tuple[int, int], message: Any) -> None:
        waiter = self._waiters.get(key)
        if waiter is not None:
            waiter[1].append(message)
            waiter[0].set()


def _seq_reached(current: int, target: int) -> bool:
    """True when u16 sequence `current` is at or past `target` (wrap-aware)."""
    return ((current - target) & 0xFFFF) < 0x8000
