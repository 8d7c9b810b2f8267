"""The host end of the serial link: one object that owns the port, the handshake and the threads.

Why threads: the board's watchdog must hear a COMMAND every 200 ms whatever the 10 Hz control
loop is doing, so a sender thread repeats the latest decision at 50 Hz; a hung loop still trips
the board because the decision id stops changing (300 ms freshness check on the board). An
e-stop is written at once from the caller's thread instead of waiting for the next send tick.
A receiver thread timestamps telemetry on arrival so its age is a measurement, and it owns
reconnection: when the cable is pulled the port errors, the link reopens it when it comes back,
re-handshakes, and drops any arm request so the car stays stopped until it is armed again.
The receiving half (handshake, reconnection, dispatch of what arrives) is in link_receive.py;
the errors and records the link hands out are in link_types.py.
"""

from __future__ import annotations

import collections
import itertools
import os
import threading
import time
from collections.abc import Callable
from typing import Any

import serial

from firmware_bridge import messages as m
from firmware_bridge.codec import FrameDecoder, encode_frame
from firmware_bridge.link_receive import ReceivePath, _seq_reached
from firmware_bridge.link_types import (
    DEFAULT_BAUD,
    ArmRefused,
    BoardInfo,
    HandshakeTimeout,
    LinkCounters,
    LinkError,
    PortUnavailable,
    ProtocolMismatch,
    TelemetrySample,
    _to_fixed,
    open_port,
)
from firmware_bridge.timing import SEND_PERIOD_S


class BoardLink(ReceivePath):
    """A live, self-healing connection to a carrt board (real or virtual)."""

    def __init__(
        self,
        port: str,
        baud: int = DEFAULT_BAUD,
        *,
        handshake_timeout_s: float = 3.0,
        send_period_s: float = SEND_PERIOD_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.port = port
        self.send_period_s = send_period_s
        self.baud = baud
        self.handshake_timeout_s = handshake_timeout_s
        self.clock = clock
        self.counters = LinkCounters()
        self.board: BoardInfo | None = None
        self.error: LinkError | None = (
            None  # set when the link gave up (e.g. mismatch on reconnect)
        )
        self.on_reboot: Callable[[BoardInfo], None] | None = None
        self.on_telemetry: Callable[[TelemetrySample], None] | None = None

        self._ser: serial.Serial | None = None
        self._decoder = FrameDecoder()
        self._write_lock = threading.Lock()
        self._state_lock = threading.Lock()
        self._seq = itertools.count()
        self._steering = 0
        self._throttle = 0
        self._decision_id = 0
        self._estop_latched = False
        self._clear_pending = False
        self._want_arm = False
        self._arm_sent_seq: int | None = None
        self._clear_sent_seq: int | None = None
        self.last_arm_refusal: m.ArmRefusal | None = None
        self._telemetry: TelemetrySample | None = None
        self._telemetry_times: collections.deque[float] = collections.deque(maxlen=100)
        self._waiters: dict[tuple[int, int], tuple[threading.Event, list[Any]]] = {}
        self._connected = threading.Event()
        self._running = False
        self._threads: list[threading.Thread] = []

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> BoardLink:
        """Open, flush, handshake (raises LinkError subclasses), then start the threads."""
        ser = open_port(self.port, self.baud)
        try:
            self._handshake(ser)
        except Exception:
            ser.close()
            raise
        self._ser = ser
        self._connected.set()
        self._running = True
        for target, name in ((self._receive_loop, "link-rx"), (self._send_loop, "link-tx")):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)
        return self

    def _leave_disarmed(self, frames: int) -> None:
        """Drop the arm request, command neutral, and put that on the wire `frames` times."""
        with self._state_lock:
            self._want_arm = False
            self._steering = self._throttle = 0
        if self._connected.is_set():
            for _ in range(frames):
                self._write_command()

    def close(self) -> None:
        """Leave the board disarmed (neutral outputs), stop the threads, release the port."""
        self._leave_disarmed(frames=3)  # a few, in case one is lost on a noisy line
        self._running = False
        for thread in self._threads:
            thread.join(timeout=1.0)
        self._threads.clear()
        self._connected.clear()
        if self._ser is not None:
            self._ser.close()
            self._ser = None

    def __enter__(self) -> BoardLink:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def connected(self) -> bool:
        return self._connected.is_set()

    # ------------------------------------------------------------------ commands
    def set_command(
        self,
        steering: float,
        throttle: float,
        decision_id: int | None = None,
        *,
        send_now: bool = False,
    ) -> float | None:
        """Hand over the latest decision; it is repeated at 50 Hz until the next one.

        Each call is a new decision (a new id), which is what keeps the board's freshness
        check satisfied: if the caller stops calling, the board fails safe after 300 ms.
        With send_now the decision is also written at once (the control loop does this, so
        frame-to-command latency does not include up to 20 ms of waiting for the sender);
        the return value is then the clock time the write completed, or None if it failed.
        """
        with self._state_lock:
            self._steering = _to_fixed(steering)
            self._throttle = _to_fixed(throttle)
            self._decision_id = (
                (self._decision_id + 1) if decision_id is None else decision_id
            ) & 0xFFFFFFFF
        if send_now and self._write_command():
            return self.clock()
        return None

    def request_arm(self) -> None:
        """Ask to arm without waiting (the control loop must not block); see `arm`."""
        if self._estop_latched:
            return
        with self._state_lock:
            if not self._want_arm:
                self._want_arm = True
                self._arm_sent_seq = None

    def request_clear(self) -> None:
        """Send CLEAR frames until the board has left ESTOP/FAILSAFE, without waiting."""
        with self._state_lock:
            self._estop_latched = False
            self._want_arm = False
            self._clear_pending = True
            self._clear_sent_seq = None

    @property
    def arm_requested(self) -> bool:
        return self._want_arm

    def estop(self) -> None:
        """Latch e-stop on the host and put it on the wire now, from this thread."""
        with self._state_lock:
            self._estop_latched = True
            self._want_arm = False
            self._clear_pending = False
        self.counters.estops_sent += 1
        self._write_command()

    @property
    def estop_latched(self) -> bool:
        return self._estop_latched

    def clear(self, timeout_s: float = 1.0) -> None:
        """Leave ESTOP/FAILSAFE for DISARMED (never straight to driving).

        Only telemetry that acknowledges one of our CLEAR frames counts: a sample sent just
        before a failsafe would otherwise make a clear look done when it never arrived.
        """
        with self._state_lock:
            self._estop_latched = False
            self._want_arm = False
            self._clear_pending = True
            self._clear_sent_seq = None
        self._write_command()
        deadline = self.clock() + timeout_s
        try:
            while self.clock() < deadline:
                if self._acknowledged(self._clear_sent_seq) and self.board_state not in (
                    m.State.ESTOP,
                    m.State.FAILSAFE,
                ):
                    return
                time.sleep(0.005)
        finally:
            with self._state_lock:
                self._clear_pending = False
        raise LinkError(f"board on {self.port} did not leave {self.board_state.name} after a clear")

    def _acknowledged(self, sent_seq: int | None) -> bool:
        """Has the board reported a state that already includes the frame `sent_seq`?"""
        sample = self._telemetry
        return (
            sent_seq is not None
            and sample is not None
            and _seq_reached(sample.telemetry.last_seq, sent_seq)
        )

    def arm(self, timeout_s: float = 1.0) -> None:
        """Ask the board to arm and wait until it is ARMED or says why it refused."""
        if self._estop_latched:
            raise ArmRefused("e-stop is latched: clear it first")
        with self._state_lock:
            self._want_arm = True
            self._arm_sent_seq = None
        self._write_command()
        deadline = self.clock() + timeout_s
        while self.clock() < deadline:
            if self._acknowledged(self._arm_sent_seq):
                tel = self._telemetry.telemetry
                if tel.state == m.State.ARMED:
                    return
                if tel.arm_refusal:
                    self.disarm()
                    reason = m.ArmRefusal(tel.arm_refusal).name.lower().replace("_", " ")
                    raise ArmRefused(f"board refused to arm: {reason}")
            time.sleep(0.005)
        self.disarm()
        raise ArmRefused(f"board did not arm within {timeout_s:.1f} s")

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
            sample = self._telemetry
            if sample is not None:
                ticks = sample.telemetry.encoder_ticks
                if ticks != last_ticks:
                    last_ticks, since = ticks, sample.received_at
                elif sample.received_at - since >= still_s:
                    return
            time.sleep(0.005)
        raise LinkError(f"wheels still turning after {timeout_s:.1f} s (encoder keeps ticking)")

    def disarm(self) -> None:
        with self._state_lock:
            self._want_arm = False

    # ------------------------------------------------------------------ telemetry
    @property
    def telemetry(self) -> TelemetrySample | None:
        return self._telemetry

    def telemetry_age_s(self) -> float:
        sample = self._telemetry
        return float("inf") if sample is None else self.clock() - sample.received_at

    @property
    def board_state(self) -> m.State:
        sample = self._telemetry
        return m.State.DISARMED if sample is None else m.State(sample.telemetry.state)

    def telemetry_rate_hz(self) -> float:
        times = list(self._telemetry_times)
        if len(times) < 2 or times[-1] == times[0]:
            return 0.0
        return (len(times) - 1) / (times[-1] - times[0])

    # ------------------------------------------------------------------ request/response
    def ping(self, timeout_s: float = 0.5) -> float:
        """Round-trip time to the board in seconds (host → board → host)."""
        nonce = int.from_bytes(os.urandom(4), "little")
        start = self.clock()
        self._request(m.Ping(nonce=nonce), (m.Pong.TYPE, nonce), timeout_s)
        return self.clock() - start

    def read_config(self, timeout_s: float = 0.5) -> m.Config:
        return self._request(m.ConfigRequest(), (m.Config.TYPE, 0), timeout_s)

    def send_config(self, config: m.Config, timeout_s: float = 0.5) -> m.ConfigAck:
        return self._request(config, (m.ConfigAck.TYPE, None), timeout_s)

    def _request(self, message: Any, key: tuple[int, int | None], timeout_s: float) -> Any:
        event, box = threading.Event(), []
        seq = self._next_seq()
        if key[1] is None:  # answered by sequence number (CONFIG_ACK)
            key = (key[0], seq)
        self._waiters[key] = (event, box)
        try:
            self._write(encode_frame(message, seq))
            if not event.wait(timeout_s):
                raise LinkError(
                    f"board on {self.port} did not answer {type(message).__name__} "
                    f"within {timeout_s * 1000:.0f} ms"
                )
            return box[0]
        finally:
            self._waiters.pop(key, None)

    # ------------------------------------------------------------------ internals
    def _next_seq(self) -> int:
        return next(self._seq) & 0xFFFF

    def _write(self, data: bytes) -> bool:
        with self._write_lock:
            ser = self._ser
            if ser is None:
                return False
            try:
                ser.write(b"\x00" + data)  # leading delimiter: the board resyncs after noise
            except (serial.SerialException, OSError):
                self.counters.write_errors += 1
                return False
            self.counters.frames_sent += 1
            return True

    def _write_command(self) -> bool:
        with self._state_lock:
            flags = 0
            if self._estop_latched:
                flags = m.CommandFlags.ESTOP
            elif self._clear_pending:
                flags = m.CommandFlags.CLEAR
            elif self._want_arm:
                flags = m.CommandFlags.ARM
            command = m.Command(
                steering=self._steering,
                throttle=self._throttle,
                decision_id=self._decision_id,
                flags=flags,
            )
            seq = self._next_seq()
            if flags == m.CommandFlags.ARM and self._arm_sent_seq is None:
                self._arm_sent_seq = seq
            if flags == m.CommandFlags.CLEAR and self._clear_sent_seq is None:
                self._clear_sent_seq = seq
        return self._write(encode_frame(command, seq))

    def _send_loop(self) -> None:
        next_send = time.monotonic()
        while self._running:
            if self._connected.is_set():
                self._write_command()
            next_send += self.send_period_s
            delay = next_send - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                next_send = time.monotonic()


__all__ = [  # the link's whole public face, wherever each name is defined
    "DEFAULT_BAUD", "SEND_PERIOD_S", "ArmRefused", "BoardInfo", "BoardLink", "HandshakeTimeout",
    "LinkCounters", "LinkError", "PortUnavailable", "ProtocolMismatch", "TelemetrySample",
    "_to_fixed", "open_port",
]  # fmt: skip
