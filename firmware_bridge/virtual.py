"""A virtual microcontroller: the real C firmware core behind a pseudo-terminal.

The host opens the pty with pyserial exactly as it opens /dev/ttyACM0, so everything above the
wire (link, loop, CLI) is exercised for real. The port path is a symlink in a private folder,
kept stable across a simulated cable pull the way a udev by-id path is on a real car: pulling
the cable closes the pty (the host's reads fail) and removes the link; plugging it back creates
a new pty behind the same path.

Run from the command line with ``python -m firmware_bridge.virtual``: it prints the port path
and runs until interrupted.
"""

from __future__ import annotations

import argparse
import errno
import os
import secrets
import select
import signal
import sys
import tempfile
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path

from firmware_bridge.drivetrain import Plant, WheelPlant
from firmware_bridge.messages import Reason, ResetCause, State
from firmware_bridge.native import FirmwareBuildError, FirmwareCore
from firmware_bridge.port_lock import PortLock
from firmware_bridge.receiver_pins import ReceiverPins

TICK_S = 0.001  # the core is ticked at about 1 kHz, like an Arduino loop()


class VirtualBoard:
    """The C core, a plant and a pty, stepped by a background thread or by the caller."""

    LABEL = "virtual board"  # how carrt's start-up line names it

    def __init__(
        self,
        plant: Plant | None = None,
        *,
        port_path: str | os.PathLike | None = None,
        reset_on_open: bool = False,
        storage_path: str | os.PathLike | None = None,
        clock: Callable[[], float] = time.monotonic,
        sanitize: bool = False,
    ) -> None:
        self.plant = plant if plant is not None else WheelPlant()
        self.reset_on_open = reset_on_open
        self.storage_path = Path(storage_path) if storage_path else None
        self._clock = clock
        self._t0 = clock()
        self._lock = threading.RLock()
        self._core = FirmwareCore(sanitize=sanitize)
        if self.storage_path and self.storage_path.exists():
            self._core.storage = self.storage_path.read_bytes()
        self._receiver = ReceiverPins(self._core)  # silent until a transmitter is set
        self._tick_offset = 0
        self._last_step_s: float | None = None
        self._master: int | None = None
        self._host_connected = False
        self._thread: threading.Thread | None = None
        self._running = False
        self._own_dir: tempfile.TemporaryDirectory | None = None
        if port_path is None:
            self._own_dir = tempfile.TemporaryDirectory(prefix="carrt-vboard-")
            port_path = Path(self._own_dir.name) / "ttyCARRT0"
        self.port = str(port_path)
        self._port_lock = PortLock(self.port)  # a second board on this path stops here
        self.boot_count = 0
        self.bytes_dropped = 0  # board → host bytes lost because nobody was reading
        self.on_state_change: Callable[[float, State, Reason], None] | None = None
        self._last_state: tuple[State, Reason] | None = None
        self.reboot()
        self.plug_cable()

    # ----------------------------------------------------------------- power and cable
    def now_ms(self) -> int:
        return int((self._clock() - self._t0) * 1000.0)

    def reboot(self, reset_cause: ResetCause = ResetCause.POWER_ON) -> None:
        """Restart the board: new boot id, RAM state lost, persistent config kept; its HELLO
        names reset_cause (POWER_ON: a power cycle; EXTERNAL: the reset pin, as DTR does;
        BROWN_OUT; WATCHDOG)."""
        with self._lock:
            self._core.boot(secrets.randbits(32), self.now_ms(), reset_cause)
            self._tick_offset = self.plant.step(0.0, 1500, 1500)
            self.boot_count += 1

    def plug_cable(self) -> None:
        """Create a fresh pty and point the stable port path at it."""
        with self._lock:
            if self._master is not None:
                return
            master, slave = os.openpty()
            tty.setraw(slave)  # no echo, no line editing, even before the host configures it
            slave_name = os.ttyname(slave)
            os.close(slave)  # the host opens it by name; until then the master sees HUP
            os.set_blocking(master, False)
            self._master = master
            self._host_connected = False
            tmp = f"{self.port}.tmp"
            if os.path.lexists(tmp):
                os.unlink(tmp)
            os.symlink(slave_name, tmp)
            os.replace(tmp, self.port)
            self.pty_name = slave_name

    def pull_cable(self) -> None:
        """Close the pty: the host's port errors out and the board hears nothing any more."""
        with self._lock:
            if self._master is None:
                return
            if os.path.lexists(self.port):
                os.unlink(self.port)
            os.close(self._master)
            self._master = None
            self._host_connected = False

    @property
    def cable_connected(self) -> bool:
        return self._master is not None

    # ----------------------------------------------------------------- stepping
    def step(self) -> None:
        """One iteration of the board's main loop: serial in, plant, core tick, serial out."""
        with self._lock:
            now_s = self._clock()
            now_ms = int((now_s - self._t0) * 1000.0)
            self._service_host_side(now_ms)
            self._receiver.advance(int((now_s - self._t0) * 1e6))
            dt = 0.0 if self._last_step_s is None else now_s - self._last_step_s
            self._last_step_s = now_s
            ticks = self.plant.step(dt, self._core.steer_us, self._core.throttle_us)
            self._core.set_encoder(ticks - self._tick_offset)
            self._core.tick(now_ms)
            self._flush_output()
            self._report_state_change(now_s)

    def set_receiver(self, steer_us: int, throttle_us: int, switch_us: int) -> None:
        """The RC receiver's three pulse widths from its next frame on (the simulator's radio)."""
        with self._lock:
            self._receiver.set(steer_us, throttle_us, switch_us)

    def receiver_off(self) -> None:
        """The RC receiver's pins go quiet (transmitter off, out of range, a wire loose)."""
        with self._lock:
            self._receiver.off()

    def _service_host_side(self, now_ms: int) -> None:
        if self._master is None:
            return
        poller = select.poll()
        poller.register(self._master, select.POLLIN)
        events = poller.poll(0)
        hung_up = any(ev & select.POLLHUP for _, ev in events)
        if not hung_up and not self._host_connected:
            self._host_connected = True
            if self.reset_on_open:  # like an Arduino's DTR auto-reset: the reset pin
                self.reboot(ResetCause.EXTERNAL)
        elif hung_up:
            self._host_connected = False
        if not hung_up and any(ev & select.POLLIN for _, ev in events):
            try:
                data = os.read(self._master, 4096)
            except OSError as exc:
                if exc.errno not in (errno.EAGAIN, errno.EIO):
                    raise
                data = b""
            if data:
                self._core.feed(data, now_ms)

    def _flush_output(self) -> None:
        out = self._core.take_output()
        if not out:
            return
        if self._master is None or not self._host_connected:
            self.bytes_dropped += len(out)  # a UART with nobody listening
            return
        try:
            written = os.write(self._master, out)
            self.bytes_dropped += len(out) - written
        except OSError as exc:
            if exc.errno not in (errno.EAGAIN, errno.EIO):
                raise
            self.bytes_dropped += len(out)

    def _report_state_change(self, now_s: float) -> None:
        current = (self._core.state, self._core.reason)
        if current != self._last_state:
            self._last_state = current
            if self.on_state_change is not None:
                self.on_state_change(now_s - self._t0, *current)

    # ----------------------------------------------------------------- test hooks
    def inject_to_board(self, data: bytes) -> None:
        """Bytes that reach the board's UART as if sent by the host (noise on the line)."""
        with self._lock:
            self._core.feed(data, self.now_ms())

    def inject_to_host(self, data: bytes) -> None:
        """Bytes that reach the host as if sent by the board (a bootloader banner, noise)."""
        with self._lock:
            if self._master is not None:
                os.write(self._master, data)

    # ----------------------------------------------------------------- observed outputs
    @property
    def state(self) -> State:
        with self._lock:
            return self._core.state

    @property
    def reason(self) -> Reason:
        with self._lock:
            return self._core.reason

    @property
    def steer_us(self) -> int:
        with self._lock:
            return self._core.steer_us

    @property
    def throttle_us(self) -> int:
        with self._lock:
            return self._core.throttle_us

    @property
    def counters(self) -> dict[str, int]:
        with self._lock:
            return self._core.counters

    # ----------------------------------------------------------------- thread
    def start(self) -> VirtualBoard:
        if self._thread is None:
            self._running = True
            self._thread = threading.Thread(target=self._run, name="virtual-board", daemon=True)
            self._thread.start()
        return self

    def _run(self) -> None:
        next_tick = time.monotonic()
        while self._running:
            self.step()
            next_tick += TICK_S
            delay = next_tick - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                next_tick = time.monotonic()  # fell behind (loaded CI machine): do not spin

    def stop(self) -> None:
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        with self._lock:
            if self.storage_path is not None:
                self.storage_path.write_bytes(self._core.storage)
        self.pull_cable()
        self._port_lock.release()
        if self._own_dir is not None:
            self._own_dir.cleanup()
            self._own_dir = None

    def __enter__(self) -> VirtualBoard:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m firmware_bridge.virtual",
        description="Run the carrt firmware core behind a pseudo-terminal, as a stand-in board.",
    )
    parser.add_argument(
        "--port-path", help="stable path for the port symlink (default: a temp dir)"
    )
    parser.add_argument(
        "--reset-on-open", action="store_true", help="reboot when the host opens the port (DTR)"
    )
    parser.add_argument("--storage", help="file that keeps the board's persistent config")
    parser.add_argument("--ticks-per-metre", type=float, default=200.0)
    args = parser.parse_args(argv)

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        board = VirtualBoard(
            WheelPlant(ticks_per_metre=args.ticks_per_metre),
            port_path=args.port_path,
            reset_on_open=args.reset_on_open,
            storage_path=args.storage,
        )
    except (FirmwareBuildError, OSError) as exc:
        first_line = str(exc).splitlines()[0]
        print(f"virtual board: error: {first_line}", file=sys.stderr)
        return 2
    board.on_state_change = lambda t, state, reason: print(
        f"[{t:8.3f} s] board {state.name} ({reason.name})", flush=True
    )
    # The ready line comes first: scripts wait for it to learn the port.
    print(f"virtual board ready on {board.port} (pty {board.pty_name}); Ctrl-C to stop", flush=True)
    with board:
        stop.wait()
    print("virtual board stopped", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
