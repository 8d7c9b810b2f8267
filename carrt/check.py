"""`carrt check`: is this board healthy enough to drive a car?

A short report a user can paste into an issue: handshake and firmware, round-trip latency,
telemetry rate, state, encoder, error counters. It never moves the car unless asked to
(`--spin-wheels`, with the car on a stand), because a self-test that drives off the table is
worse than no self-test.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import dataclass, field

from firmware_bridge import messages as m
from firmware_bridge.link import DEFAULT_BAUD, BoardLink, LinkError

TELEMETRY_HZ = 50.0
TELEMETRY_TOLERANCE = 0.1
MAX_RTT_P99_S = 0.05
SPIN_THROTTLE = 0.2
SPIN_SECONDS = 1.0


@dataclass
class CheckReport:
    lines: list[tuple[str, bool, str]] = field(default_factory=list)

    def add(self, name: str, ok: bool, detail: str) -> None:
        self.lines.append((name, ok, detail))

    @property
    def healthy(self) -> bool:
        return all(ok for _, ok, _ in self.lines)

    @property
    def problems(self) -> list[str]:
        return [f"{name}: {detail}" for name, ok, detail in self.lines if not ok]

    def render(self) -> str:
        rows = [
            f"  {name:<12} {'ok  ' if ok else 'FAIL'}  {detail}" for name, ok, detail in self.lines
        ]
        return "\n".join(rows)


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def run_check(
    link: BoardLink, *, pings: int = 20, duration_s: float = 1.0, spin_wheels: bool = False
) -> CheckReport:
    report = CheckReport()
    board = link.board
    assert board is not None  # open() succeeded, so the handshake did
    version = ".".join(map(str, board.firmware_version))
    report.add(
        "handshake",
        True,
        f"protocol {board.protocol_hash:08x}, firmware {version}, boot id {board.boot_id:08x}, "
        f"config {'from storage' if board.config_from_storage else 'defaults'}",
    )

    rtts: list[float] = []
    lost = 0
    for _ in range(pings):
        try:
            rtts.append(link.ping(timeout_s=0.25))
        except LinkError:
            lost += 1
    if rtts:
        p50, p99 = statistics.median(rtts), _percentile(rtts, 0.99)
        ok = lost == 0 and p99 <= MAX_RTT_P99_S
        report.add(
            "round trip",
            ok,
            f"p50 {p50 * 1e3:.1f} ms, p99 {p99 * 1e3:.1f} ms, {lost}/{pings} lost"
            + ("" if p99 <= MAX_RTT_P99_S else f" (p99 limit {MAX_RTT_P99_S * 1e3:.0f} ms)"),
        )
    else:
        report.add("round trip", False, f"no answer to {pings} pings")

    start = link.telemetry
    before_counters = _board_counters(start.telemetry) if start else None
    time.sleep(duration_s)
    rate = link.telemetry_rate_hz()
    low, high = TELEMETRY_HZ * (1 - TELEMETRY_TOLERANCE), TELEMETRY_HZ * (1 + TELEMETRY_TOLERANCE)
    report.add(
        "telemetry",
        low <= rate <= high,
        f"{rate:.1f} Hz (expected {TELEMETRY_HZ:.0f} Hz ± {TELEMETRY_TOLERANCE:.0%}), "
        f"age {link.telemetry_age_s() * 1e3:.0f} ms",
    )
    sample = link.telemetry
    if sample is None:
        report.add("state", False, "no telemetry received")
        return report
    tel = sample.telemetry
    report.add(
        "state",
        True,
        f"{m.State(tel.state).name} ({m.Reason(tel.reason).name}), "
        f"steering {tel.steer_us} us, throttle {tel.throttle_us} us",
    )

    report.add(*_receiver_line(link, tel))
    if spin_wheels:
        report.add(*_spin_test(link))
    else:
        moved = before_counters is not None and tel.encoder_ticks != start.telemetry.encoder_ticks
        report.add(
            "encoder",
            True,
            f"{tel.encoder_ticks} ticks ({'moving' if moved else 'still'}); "
            "pass --spin-wheels with the car on a stand to test it under power",
        )

    after = _board_counters(link.telemetry.telemetry)
    if before_counters is not None:
        delta = {k: after[k] - before_counters[k] for k in after}
        report.add(
            "errors",
            not any(delta.values()),
            "during the check: board "
            + ", ".join(f"{k.replace('_', ' ')} +{v}" for k, v in delta.items())
            + f"; host bad crc {link.counters.bad_crc}, bad length {link.counters.bad_length}",
        )
    return report


def _receiver_line(link: BoardLink, tel: m.Telemetry) -> tuple[str, bool, str]:
    """The RC receiver's signal; missing is a failure only when the board is configured to
    take the person's controls from it."""
    try:
        controls = m.Controls(link.read_config().controls)
    except (LinkError, ValueError):
        controls = None
    named = controls.name.lower() if controls is not None else "unknown"
    if tel.flags & m.TelemetryFlags.RC_SIGNAL:
        return (
            "receiver",
            True,
            f"signal: steering {tel.rc_steer_us} us, throttle {tel.rc_throttle_us} us, switch "
            f"{tel.rc_switch_us} us; the person's controls: {named}",
        )
    if controls in (None, m.Controls.PAD):
        return "receiver", True, f"no signal (the person's controls: {named})"
    return (
        "receiver",
        False,
        f"no signal, and the board takes the person's controls from it ({named}): is the "
        "transmitter on, the receiver bound and wired to D4-D6?",
    )


def _board_counters(tel: m.Telemetry) -> dict[str, int]:
    return {"bad_crc": tel.bad_crc, "bad_length": tel.bad_length, "overruns": tel.overruns}


def _spin_test(link: BoardLink) -> tuple[str, bool, str]:
    """Arm, turn the wheels at low throttle for a second, and see the encoder count move."""
    if link.board_state in (m.State.ESTOP, m.State.FAILSAFE):
        link.clear()
    link.set_command(0.0, 0.0)
    time.sleep(0.05)
    link.arm()
    first = link.telemetry.telemetry.encoder_ticks
    end = time.monotonic() + SPIN_SECONDS
    try:
        while time.monotonic() < end and link.board_state == m.State.ARMED:
            link.set_command(0.0, SPIN_THROTTLE)
            time.sleep(0.05)
    finally:
        link.set_command(0.0, 0.0)
        link.disarm()
    time.sleep(0.1)
    tel = link.telemetry.telemetry
    ticks = tel.encoder_ticks - first
    if tel.state == m.State.FAILSAFE and tel.reason == m.Reason.STALL:
        return "encoder", False, "no ticks at 20 % throttle: the board's stall check tripped"
    return (
        "encoder",
        ticks > 0,
        f"+{ticks} ticks in {SPIN_SECONDS:.0f} s at {SPIN_THROTTLE:.0%} throttle",
    )


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "check", help="self-test a board: handshake, latency, telemetry, encoder, errors"
    )
    parser.add_argument("--port", required=True, help="serial port, e.g. /dev/serial/by-id/...")
    parser.add_argument(
        "--baud", type=int, default=DEFAULT_BAUD, help="serial speed (default: %(default)s)"
    )
    parser.add_argument(
        "--pings", type=int, default=20, help="round trips to time (default: %(default)s)"
    )
    parser.add_argument("--duration", type=float, default=1.0, help="telemetry window, seconds")
    parser.add_argument(
        "--spin-wheels",
        action="store_true",
        help="arm and turn the wheels at 20%% throttle for 1 s (car on a stand!)",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    link = BoardLink(args.port, args.baud)
    with link:
        print(f"carrt check {args.port} @ {args.baud} baud")
        report = run_check(
            link, pings=args.pings, duration_s=args.duration, spin_wheels=args.spin_wheels
        )
    print(report.render())
    if report.healthy:
        print("healthy")
        return 0
    print("unhealthy: " + "; ".join(report.problems))
    return 1
