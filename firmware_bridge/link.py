"""The host end of the serial link: one object that owns the port, the handshake and the threads.

Why threads: the board's watchdog must hear a COMMAND every 200 ms whatever the 10 Hz control
loop is doing, so a sender thread repeats the latest decision at 50 Hz; a hung loop still trips
the board because the decision id stops changing (300 ms freshness check on the board). An
e-stop is written at once from the caller's thread instead of waiting for the next send tick.
A receiver thread timestamps telemetry on arrival so its age is a measurement, and it owns
reconnection: when the cable is pulled the port errors, the link reopens it when it comes back,
re-handshakes, and drops any arm request so the car stays stopped until it is armed again.
The receiving half (handshake, reconnection, dispatch of what arrives) is a part the link owns, a
`Receiver` (link_receive.py), that reports to the link through the `LinkEvents` methods below;
the errors and records the link hands out are in link_types.py.
"""

from __future__ import annotations

import contextlib
import itertools
import threading
import time
from collections.abc import Callable

import serial

from firmware_bridge import messages as m
from firmware_bridge.codec import encode_frame
from firmware_bridge.link_receive import Receiver
from firmware_bridge.link_requests import Requests
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
    _seq_reached,
    _to_fixed,
    open_port,
)
from firmware_bridge.timing import SEND_PERIOD_S


class BoardLink(Requests):
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
        self.clock = clock
        self.counters = LinkCounters()
        self.error: LinkError | None = (
            None  # set when the link gave up (e.g. mismatch on reconnect)
        )
        self.on_reboot: Callable[[BoardInfo], None] | None = None
        self.on_telemetry: Callable[[TelemetrySample], None] | None = None
        self._seq = itertools.count()
        self.receiver = Receiver(
            self,
            port=port,
            baud=baud,
            handshake_timeout_s=handshake_timeout_s,
            clock=clock,
            counters=self.counters,
            next_seq=self._next_seq,
        )

        self._ser: serial.Serial | None = None
        # re-entrant: the in-process board (direct.py) answers inside the write that it reads
        self._write_lock = threading.RLock()
        self._state_lock = threading.Lock()
        self._steering = 0
        self._throttle = 0
        self._decision_id = 0
        self._estop_latched = False
        self._clear_pending = False
        self._want_arm = False
        self._auto = False
        self._arm_sent_seq: int | None = None
        self._clear_sent_seq: int | None = None
        self.last_arm_refusal: m.ArmRefusal | None = None
        # The car's CONFIG, sent again to every new boot before anything else (keep_config);
        # until the board has acknowledged it no ARM goes out, so a rebooted board never drives
        # on its defaults (throttle limit, the receiver's rules).
        self._car_config: m.Config | None = None
        self._config_pending = False
        self._restore: tuple[float, threading.Event, list] | None = None  # sent at, answer
        self._restore_seq = 0
        self.config_restore_error: str | None = None  # the board refused the car's CONFIG
        self._connected = threading.Event()
        self._running = False
        self._threads: list[threading.Thread] = []

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> BoardLink:
        """Open, flush, handshake (raises LinkError subclasses), then start the threads."""
        ser = open_port(self.port, self.baud)
        try:
            self.receiver.handshake(ser)
        except Exception:
            ser.close()
            raise
        self._ser = ser
        self._connected.set()
        self._running = True
        self.receiver.start(ser)
        thread = threading.Thread(target=self._send_loop, name="link-tx", daemon=True)
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
        self.receiver.stop()
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

    # the link's settings and what its receiver learned, read where they always were
    baud = property(lambda self: self.receiver.baud)
    handshake_timeout_s = property(lambda self: self.receiver.handshake_timeout_s)
    board = property(lambda self: self.receiver.board)
    _telemetry = property(lambda self: self.receiver.telemetry)

    def receive(self, data: bytes) -> None:
        """Bytes from the board, from whichever transport carried them (the receiver thread's
        serial port, or the in-process core of firmware_bridge/direct.py)."""
        self.receiver.feed(data)

    # ------------------------------------------------------------------ LinkEvents
    def port_back(self, ser: serial.Serial) -> None:
        with self._write_lock:
            self._ser = ser
        self.counters.reconnects += 1
        self._connected.set()

    def port_lost(self) -> None:
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

    def telemetry_arrived(self, sample: TelemetrySample) -> None:
        self._watch_arming(sample.telemetry)
        if self.on_telemetry is not None:
            self.on_telemetry(sample)

    def board_rebooted(self, info: BoardInfo) -> None:
        with self._state_lock:
            self._want_arm = False
            self._config_pending = self._car_config is not None
            self._restore = None
        if self.on_reboot is not None:
            self.on_reboot(info)

    def board_mismatched(self, error: ProtocolMismatch) -> None:
        self.error = error
        self.estop()

    def gave_up(self, error: LinkError) -> None:
        self.error = error
        self._running = False

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

    def set_auto(self, auto: bool) -> None:
        """Tell the board whether the policy drives (the COMMAND's AUTO flag): with a receiver
        wired, a stick then takes over on the board, and the flag's next 0 -> 1 edge hands the
        wheels back to the policy."""
        with self._state_lock:
            self._auto = bool(auto)

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
        """Wait until the encoder has not moved for `still_s` (the board refuses to arm before);
        see Receiver.wait_until_still."""
        self.receiver.wait_until_still(still_s, timeout_s)

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
        times = list(self.receiver.telemetry_times)
        if len(times) < 2 or times[-1] == times[0]:
            return 0.0
        return (len(times) - 1) / (times[-1] - times[0])

    # ------------------------------------------------------------------ internals
    def _next_seq(self) -> int:
        return next(self._seq) & 0xFFFF

    def _send(self, make_frame: Callable[[int], bytes]) -> bool:
        """Number a frame and write it under one lock: frames reach the board in the order of
        their sequence numbers whichever thread sends them (the sender thread, the loop's
        send_now, an e-stop from the joystick's thread, a request). Numbered under one lock and
        written under another, an older COMMAND could follow a newer one: its AUTO flag going
        back to 0 hands the wheels to the receiver, and the board's last_seq runs backwards."""
        with self._write_lock:
            ser = self._ser
            if ser is None:
                return False
            data = make_frame(self._next_seq())
            try:
                ser.write(b"\x00" + data)  # leading delimiter: the board resyncs after noise
            except (serial.SerialException, OSError):
                self.counters.write_errors += 1
                return False
            self.counters.frames_sent += 1
            return True

    def _write_command(self) -> bool:
        with self._write_lock:  # a rebooted board's CONFIG, then this command, nothing between
            self._restore_config()
            return self._send(self._command_frame)

    def _command_frame(self, seq: int) -> bytes:
        with self._state_lock:
            flags = 0
            if self._estop_latched:
                flags = m.CommandFlags.ESTOP
            elif self._clear_pending:
                flags = m.CommandFlags.CLEAR
            elif self._want_arm and not self._config_pending:  # a rebooted board: config first
                flags = m.CommandFlags.ARM
                if self._auto:
                    flags |= m.CommandFlags.AUTO
            command = m.Command(
                steering=self._steering,
                throttle=self._throttle,
                decision_id=self._decision_id,
                flags=flags,
            )
            if flags & m.CommandFlags.ARM and self._arm_sent_seq is None:
                self._arm_sent_seq = seq
            if flags == m.CommandFlags.CLEAR and self._clear_sent_seq is None:
                self._clear_sent_seq = seq
        return encode_frame(command, seq)

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
