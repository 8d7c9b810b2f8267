"""What the host link raises and reports: its errors, the board's identity, telemetry samples,
counters, and opening a serial port with readable failures. Kept apart from link.py so the
link's logic reads on its own; link.py re-exports every name here."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import serial

from firmware_bridge import messages as m

DEFAULT_BAUD = 250000


class LinkError(Exception):
    """A link problem worth one clear line to the user."""


class PortUnavailable(LinkError):
    pass


class ProtocolMismatch(LinkError):
    pass


class HandshakeTimeout(LinkError):
    pass


class ArmRefused(LinkError):
    pass


@dataclass(frozen=True)
class BoardInfo:
    protocol_hash: int
    boot_id: int
    firmware_version: tuple[int, int, int]
    config_from_storage: bool
    reset_cause: int = m.ResetCause.UNKNOWN  # a messages.ResetCause: why the board last started


@dataclass(frozen=True)
class TelemetrySample:
    telemetry: m.Telemetry
    received_at: float  # host monotonic seconds when the frame was decoded


@dataclass
class LinkCounters:
    """Everything the link sent, dropped or survived; reported by `carrt check` and the loop."""

    frames_sent: int = 0
    frames_received: int = 0
    estops_sent: int = 0
    write_errors: int = 0
    disconnects: int = 0
    reconnects: int = 0
    reboots_detected: int = 0
    configs_restored: int = 0  # the car's CONFIG acknowledged by a rebooted board
    bad_crc: int = 0
    bad_length: int = 0
    overruns: int = 0
    extra: dict[str, int] = field(default_factory=dict)


def _to_fixed(value: float) -> int:
    return round(max(-1.0, min(1.0, float(value))) * m.SCALE)


def open_port(port: str, baud: int) -> serial.Serial:
    """Open a serial port exclusively, turning the usual failures into one readable line."""
    if not port.startswith(("socket://", "rfc2217://", "loop://")) and not os.path.exists(port):
        raise PortUnavailable(
            f"serial port {port} does not exist (is the board plugged in? "
            "use the /dev/serial/by-id/... path: docs/car.md#a-stable-port-name)"
        )
    try:
        return serial.Serial(port, baud, timeout=0.02, write_timeout=0.2, exclusive=True)
    except serial.SerialException as exc:
        text = str(exc)
        if "Permission denied" in text or "Errno 13" in text:
            raise PortUnavailable(
                f"no permission to open {port}: add your user to the 'dialout' group"
            ) from exc
        if "Resource temporarily unavailable" in text or "Errno 11" in text:
            raise PortUnavailable(
                f"serial port {port} is busy: another process has it open"
            ) from exc
        raise PortUnavailable(f"cannot open serial port {port}: {text}") from exc


def _seq_reached(current: int, target: int) -> bool:
    """True when u16 sequence `current` is at or past `target` (wrap-aware)."""
    return ((current - target) & 0xFFFF) < 0x8000
