"""The serial protocol's message definitions: the one source both ends are built from.

The C firmware core includes ``firmware/carrt_fw/src/protocol_generated.h``, which
``python -m firmware_bridge.gen_c`` writes from the tables below, and a test fails when the
committed header drifts from them. The protocol hash that the board announces in HELLO is a
digest of these definitions, so a host and a board built from different definitions refuse to
talk instead of misreading each other's bytes.

Fixed-point conventions: steering and throttle travel as int16 in units of 1/10000
(``SCALE``), so 10000 is full right / full forward and -10000 full left / full reverse.
All multi-byte fields are little-endian.
"""

from __future__ import annotations

import dataclasses
import hashlib
import struct
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any, ClassVar

from firmware_bridge import timing

SCALE = 10000
"""Fixed-point scale of steering and throttle on the wire (1.0 == SCALE)."""

MAX_FRAME_DECODED = 64
"""Largest decoded frame (type + sequence + payload + CRC) either side accepts."""

HEADER_SIZE = 3  # type u8 + sequence u16
CRC_SIZE = 4  # CRC-32C

FIRMWARE_VERSION = (0, 1, 0)

# Field kinds and their struct codes. Only fixed-width little-endian integers cross the wire.
KINDS: dict[str, tuple[str, int, bool]] = {
    # kind: (struct code, size, signed)
    "u8": ("B", 1, False),
    "u16": ("H", 2, False),
    "u32": ("I", 4, False),
    "i16": ("h", 2, True),
    "i32": ("i", 4, True),
}

HOST_TO_MCU = "host->mcu"
MCU_TO_HOST = "mcu->host"
BOTH = "both"


def wire(kind: str, doc: str, default: int = 0) -> Any:
    """Declare a message field with its wire kind; the doc goes into PROTOCOL.md and the header."""
    if kind not in KINDS:
        raise ValueError(f"unknown wire kind {kind!r}")
    return field(default=default, metadata={"kind": kind, "doc": doc})


class State(IntEnum):
    """The board's safety state. Only ARMED lets commands reach the outputs."""

    DISARMED = 0
    ARMED = 1
    ESTOP = 2
    FAILSAFE = 3


class Reason(IntEnum):
    """Why the board is in its current state; kept until the state changes."""

    NONE = 0
    BOOT = 1  # DISARMED after power-up or reset
    CLEARED = 2  # DISARMED after an explicit clear
    HOST_DISARM = 3  # DISARMED because the host dropped its arm request
    ESTOP_COMMAND = 4  # ESTOP: the e-stop flag arrived in a COMMAND
    LINK_TIMEOUT = 5  # FAILSAFE: no valid COMMAND for the watchdog period (200 ms)
    DECISION_STALE = 6  # FAILSAFE: frames arrive but the decision id stopped changing (300 ms)
    STALL = 7  # FAILSAFE: throttle above 15 % and no encoder tick for 500 ms
    ARMED_OK = 8  # ARMED after a valid arm request
    RC_SWITCH = 9  # ESTOP: the RC receiver's switch channel is in its e-stop position
    RC_LOST = 10  # FAILSAFE: the receiver holds the person's controls and its signal was lost


class ArmRefusal(IntEnum):
    """Why the last arm request was refused (0 when the last one succeeded or none came)."""

    NONE = 0
    NOT_DISARMED = 1  # e-stop or failsafe must be cleared first
    THROTTLE_NOT_NEUTRAL = 2
    WHEELS_MOVING = 3
    NO_EDGE = 4  # the arm flag must go 0 -> 1 in separate frames (clear, then arm)
    RC_NO_SIGNAL = 5  # the receiver holds the person's controls and has no valid signal
    RC_NOT_NEUTRAL = 6  # the receiver's sticks are outside their deadzone


class CommandFlags:
    """Bits of ``Command.flags``."""

    ESTOP = 0x01  # latch e-stop now
    ARM = 0x02  # level: the host wants to be armed; arming happens on its 0 -> 1 edge
    CLEAR = 0x04  # leave ESTOP/FAILSAFE for DISARMED (only honoured with ESTOP and ARM clear)
    AUTO = 0x08  # the policy drives; its 0 -> 1 edge hands the wheels back from the receiver


class Controls(IntEnum):
    """Which device holds the person's controls (``Config.controls``)."""

    PAD = 0  # a gamepad on the host; no receiver wired (its pins are ignored)
    RECEIVER = 1  # the car's RC receiver, wired to the board; it drives MANUAL by itself
    BOTH = 2  # pad and receiver; the receiver drives once a stick leaves its deadzone


class ResetCause(IntEnum):
    """Why the board last started (``Hello.reset_cause``), from the MCU's reset flags."""

    UNKNOWN = 0  # no flag to go by (a bootloader cleared them and handed nothing on)
    POWER_ON = 1  # power was applied (or came back after being off)
    EXTERNAL = 2  # the reset pin: the reset button, or a host opening the port (USB DTR)
    BROWN_OUT = 3  # the supply dipped below the brown-out level (a stalling motor, a weak battery)
    WATCHDOG = 4  # the MCU's watchdog timer ran out (this firmware does not start it)


RESET_CAUSE_TEXT = {
    ResetCause.UNKNOWN: "unknown",
    ResetCause.POWER_ON: "power-on",
    ResetCause.EXTERNAL: "reset pin",
    ResetCause.BROWN_OUT: "brown-out",
    ResetCause.WATCHDOG: "watchdog",
}


def reset_cause_text(code: int) -> str:
    """A reset cause (``ResetCause`` or its wire value) in words; "unknown" for any other."""
    try:
        return RESET_CAUSE_TEXT[ResetCause(code)]
    except ValueError:
        return "unknown"


class TelemetryFlags:
    """Bits of ``Telemetry.flags``."""

    CONFIG_FROM_STORAGE = 0x01  # the PWM config was loaded from the board's persistent storage
    LINK_OK = 0x02  # a valid COMMAND arrived within the watchdog period
    RC_SIGNAL = 0x04  # all three receiver channels have a valid signal
    RC_DRIVES = 0x08  # the receiver's sticks drive the wheels (MANUAL from it, or a take-over)


class ConfigResult(IntEnum):
    ACCEPTED = 0
    REJECTED_ARMED = 1  # configuration only changes while not ARMED
    REJECTED_INVALID = 2  # endpoints out of 800..2200 us, centre not between them, bad limits


@dataclass(frozen=True)
class HelloRequest:
    """Ask the board to announce itself (sent by the host until a HELLO arrives)."""

    TYPE: ClassVar[int] = 0x01
    DIRECTION: ClassVar[str] = HOST_TO_MCU


@dataclass(frozen=True)
class Hello:
    """The board's identity, sent at boot and in answer to HELLO_REQUEST."""

    TYPE: ClassVar[int] = 0x02
    DIRECTION: ClassVar[str] = MCU_TO_HOST
    protocol_hash: int = wire("u32", "first 4 bytes (little-endian) of the definitions' SHA-256")
    boot_id: int = wire("u32", "random per boot; a new value means the board has rebooted")
    fw_major: int = wire("u8", "firmware version, major")
    fw_minor: int = wire("u8", "firmware version, minor")
    fw_patch: int = wire("u8", "firmware version, patch")
    config_from_storage: int = wire("u8", "1 when the PWM config came from persistent storage")
    reset_cause: int = wire("u8", "why the board last started (see ResetCause)")


@dataclass(frozen=True)
class Ping:
    """Round-trip probe; the board echoes the nonce in a PONG at once."""

    TYPE: ClassVar[int] = 0x03
    DIRECTION: ClassVar[str] = HOST_TO_MCU
    nonce: int = wire("u32", "any value chosen by the host")


@dataclass(frozen=True)
class Pong:
    TYPE: ClassVar[int] = 0x04
    DIRECTION: ClassVar[str] = MCU_TO_HOST
    nonce: int = wire("u32", "the PING's nonce")
    mcu_time_ms: int = wire("u32", "board time when the PING was handled")


@dataclass(frozen=True)
class Command:
    """The host's latest decision, sent at 50 Hz; e-stop also goes out at once, out of band."""

    TYPE: ClassVar[int] = 0x10
    DIRECTION: ClassVar[str] = HOST_TO_MCU
    steering: int = wire("i16", "-10000 full left .. 10000 full right")
    throttle: int = wire("i16", "-10000 full reverse/brake .. 10000 full forward")
    decision_id: int = wire("u32", "changes with every new decision of the host's control loop")
    flags: int = wire(
        "u8", "bit0 ESTOP, bit1 ARM (level, arms on 0->1 edge), bit2 CLEAR, bit3 AUTO"
    )


@dataclass(frozen=True)
class Config:
    """PWM calibration and limits; host->mcu to set (only while not ARMED), mcu->host to report."""

    TYPE: ClassVar[int] = 0x20
    DIRECTION: ClassVar[str] = BOTH
    steer_left_us: int = wire("u16", "servo pulse at steering -1.0", 1000)
    steer_center_us: int = wire("u16", "servo pulse at steering 0", 1500)
    steer_right_us: int = wire("u16", "servo pulse at steering +1.0", 2000)
    throttle_reverse_us: int = wire("u16", "ESC pulse at throttle -1.0", 1000)
    throttle_neutral_us: int = wire("u16", "ESC pulse at throttle 0", 1500)
    throttle_forward_us: int = wire("u16", "ESC pulse at throttle +1.0", 2000)
    max_forward: int = wire("u16", "largest forward throttle allowed, 0..10000", 10000)
    max_reverse: int = wire("u16", "largest reverse/brake throttle allowed, 0..10000", 10000)
    slew_per_s: int = wire(
        "u32", "throttle rise limit in 1/10000 per second (falls are immediate)", 20000
    )
    persist: int = wire("u8", "host->mcu: 1 to store in EEPROM/flash; mcu->host: 1 if stored")
    controls: int = wire("u8", "the person's controls: 0 pad (no receiver), 1 receiver, 2 both")
    rc_steer_center_us: int = wire("u16", "receiver steering pulse with the stick centred", 1500)
    rc_throttle_center_us: int = wire("u16", "receiver throttle pulse at neutral", 1500)
    rc_deadzone_us: int = wire("u16", "a stick further than this from its centre has moved", 60)
    rc_estop_us: int = wire("u16", "switch channel pulse at or above this: e-stop", 1700)


@dataclass(frozen=True)
class ConfigRequest:
    """Ask the board to report its current CONFIG."""

    TYPE: ClassVar[int] = 0x21
    DIRECTION: ClassVar[str] = HOST_TO_MCU


@dataclass(frozen=True)
class ConfigAck:
    TYPE: ClassVar[int] = 0x22
    DIRECTION: ClassVar[str] = MCU_TO_HOST
    config_seq: int = wire("u16", "sequence number of the CONFIG frame answered")
    result: int = wire("u8", "0 accepted, 1 rejected (armed), 2 rejected (invalid values)")
    persisted: int = wire("u8", "1 when the accepted config was written to persistent storage")


@dataclass(frozen=True)
class Telemetry:
    """The board's state at 50 Hz: what it applies and why, and what it has rejected."""

    TYPE: ClassVar[int] = 0x30
    DIRECTION: ClassVar[str] = MCU_TO_HOST
    mcu_time_ms: int = wire("u32", "board time (ms since boot, wraps after 49 days)")
    encoder_ticks: int = wire("i32", "cumulative wheel-encoder ticks since boot")
    steer_us: int = wire("u16", "servo pulse being applied")
    throttle_us: int = wire("u16", "ESC pulse being applied")
    state: int = wire("u8", "0 DISARMED, 1 ARMED, 2 ESTOP, 3 FAILSAFE")
    reason: int = wire("u8", "why the board is in that state (see Reason)")
    arm_refusal: int = wire("u8", "why the last arm request was refused (see ArmRefusal)")
    flags: int = wire(
        "u8", "bit0 config from storage, bit1 link ok, bit2 receiver signal, bit3 receiver drives"
    )
    bad_crc: int = wire("u16", "frames dropped for a bad CRC (saturating)")
    bad_length: int = wire("u16", "frames dropped: malformed COBS, unknown type or wrong length")
    overruns: int = wire("u16", "frames dropped because they outgrew the receive buffer")
    last_seq: int = wire("u16", "sequence number of the last accepted host frame")
    decision_id: int = wire("u32", "decision id of the last accepted COMMAND")
    rc_steer_us: int = wire("u16", "receiver steering pulse (0: no valid signal)")
    rc_throttle_us: int = wire("u16", "receiver throttle pulse (0: no valid signal)")
    rc_switch_us: int = wire("u16", "receiver switch-channel pulse (0: no valid signal)")


MESSAGES: tuple[type, ...] = (
    HelloRequest,
    Hello,
    Ping,
    Pong,
    Command,
    Config,
    ConfigRequest,
    ConfigAck,
    Telemetry,
)

ENUMS: tuple[type[IntEnum], ...] = (State, Reason, ArmRefusal, ConfigResult, Controls, ResetCause)
"""The enumerations on the wire, in the header, the protocol hash and PROTOCOL.md."""

BY_TYPE: dict[int, type] = {m.TYPE: m for m in MESSAGES}


def fields_of(message_cls: type) -> list[tuple[str, str, str]]:
    """(name, kind, doc) of each wire field, in wire order."""
    return [
        (f.name, f.metadata["kind"], f.metadata["doc"]) for f in dataclasses.fields(message_cls)
    ]


def _struct_for(message_cls: type) -> struct.Struct:
    return struct.Struct("<" + "".join(KINDS[kind][0] for _, kind, _ in fields_of(message_cls)))


STRUCTS: dict[int, struct.Struct] = {m.TYPE: _struct_for(m) for m in MESSAGES}
PAYLOAD_SIZES: dict[int, int] = {t: s.size for t, s in STRUCTS.items()}


def canonical_definition() -> str:
    """The text the protocol hash is taken of: names, ids, directions, field names and kinds.

    Docs are left out on purpose: rewording a comment must not make boards incompatible.
    """
    lines = [f"carrt-serial scale={SCALE} max={MAX_FRAME_DECODED} crc=crc32c cobs"]
    for m in MESSAGES:
        body = ",".join(f"{name}:{kind}" for name, kind, _ in fields_of(m))
        lines.append(f"{m.__name__}={m.TYPE:#04x}/{m.DIRECTION}({body})")
    for enum in ENUMS:
        lines.append(enum.__name__ + "=" + ",".join(f"{e.name}:{e.value}" for e in enum))
    # the board's watchdog and freshness timing: a board with other values is another protocol
    lines.append(timing.canonical())
    return "\n".join(lines) + "\n"


PROTOCOL_HASH: int = int.from_bytes(
    hashlib.sha256(canonical_definition().encode()).digest()[:4], "little"
)


def pack_payload(message: Any) -> bytes:
    """Payload bytes of a message; raises struct.error when a field is out of its kind's range."""
    values = [getattr(message, name) for name, _, _ in fields_of(type(message))]
    return STRUCTS[message.TYPE].pack(*values)


def unpack_payload(type_id: int, payload: bytes) -> Any:
    """Message object from a payload whose length has already been checked."""
    return BY_TYPE[type_id](*STRUCTS[type_id].unpack(payload))


def check_definitions() -> None:
    """Fail loudly if a definition breaks the framing limits (run by tests and the generator)."""
    seen: set[int] = set()
    for m in MESSAGES:
        if m.TYPE in seen or not 0 < m.TYPE < 0x100:
            raise ValueError(f"{m.__name__}: duplicate or invalid type id {m.TYPE:#x}")
        seen.add(m.TYPE)
        size = HEADER_SIZE + PAYLOAD_SIZES[m.TYPE] + CRC_SIZE
        if size > MAX_FRAME_DECODED:
            raise ValueError(f"{m.__name__}: {size} bytes exceeds {MAX_FRAME_DECODED}")
