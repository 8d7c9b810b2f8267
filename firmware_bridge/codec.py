"""Framing of the serial protocol: COBS, 0x00 delimiters, CRC-32C.

A decoded frame is ``type u8 · sequence u16 · payload · crc u32`` (little-endian), the CRC-32C
taken over everything before it. (It was a CRC-16, which let about 1 in 65,536 damaged frames
through; PROTOCOL.md has the rate now and what it costs the AVR.) COBS removes every 0x00 from
the frame so a single 0x00 can end it: a receiver that starts mid-stream, or loses bytes,
resynchronises at the next 0x00 instead of misreading the rest of the session.

The decoder is written for a serial port: it takes whatever chunk ``read()`` returned, keeps
partial frames across calls, never raises on bad input, never grows without bound, and counts
what it throws away so the link can report it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from cobs import cobs

from firmware_bridge import messages as m

_MIN_FRAME = m.HEADER_SIZE + m.CRC_SIZE
# COBS adds one code byte per 254 data bytes (and one at the start).
MAX_FRAME_ENCODED = m.MAX_FRAME_DECODED + m.MAX_FRAME_DECODED // 254 + 1


def _crc32c_table() -> tuple[int, ...]:
    table = []
    for n in range(256):
        c = n
        for _ in range(8):
            c = (c >> 1) ^ 0x82F63B78 if c & 1 else c >> 1
        table.append(c)
    return tuple(table)


_CRC32C_TABLE = _crc32c_table()


def crc32c(data: bytes) -> int:
    """CRC-32C (Castagnoli, reflected poly 0x82F63B78); 0xE3069283 for b"123456789"."""
    crc = 0xFFFFFFFF
    table = _CRC32C_TABLE
    for byte in data:
        crc = table[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc ^ 0xFFFFFFFF


@dataclass(frozen=True)
class Frame:
    """One accepted frame: its type, the sender's sequence number and the decoded message."""

    type_id: int
    seq: int
    message: Any


def frame_bytes(type_id: int, seq: int, payload: bytes) -> bytes:
    """Wire bytes (COBS + trailing 0x00) for a raw payload; ``encode_frame`` is the usual entry."""
    body = bytes((type_id, seq & 0xFF, (seq >> 8) & 0xFF)) + payload
    body += crc32c(body).to_bytes(m.CRC_SIZE, "little")
    if len(body) > m.MAX_FRAME_DECODED:
        raise ValueError(f"frame of {len(body)} bytes exceeds {m.MAX_FRAME_DECODED}")
    return cobs.encode(body) + b"\x00"


def encode_frame(message: Any, seq: int) -> bytes:
    """Wire bytes for a message object from ``firmware_bridge.messages``."""
    return frame_bytes(message.TYPE, seq, m.pack_payload(message))


class FrameDecoder:
    """Streaming decoder: feed it arbitrary chunks, get back only valid frames.

    Counters (never reset, so a link can report deltas):
      bad_crc     frames whose CRC did not match
      bad_length  malformed COBS, shorter than a header, unknown type or wrong payload length
      overruns    frames that outgrew the receive buffer before their delimiter (discarded)
      accepted    frames returned
    """

    def __init__(self) -> None:
        self._buffer = bytearray()
        self._discarding = False
        self.bad_crc = 0
        self.bad_length = 0
        self.overruns = 0
        self.accepted = 0

    @property
    def rejected(self) -> int:
        return self.bad_crc + self.bad_length + self.overruns

    def discard_partial(self) -> None:
        """Forget a half-received frame (the port was flushed or reopened), uncounted."""
        self._buffer.clear()
        self._discarding = False

    def feed(self, data: bytes) -> list[Frame]:
        frames: list[Frame] = []
        start = 0
        while True:
            end = data.find(b"\x00", start)
            chunk = data[start:] if end < 0 else data[start:end]
            if not self._discarding:
                self._buffer += chunk
                if len(self._buffer) > MAX_FRAME_ENCODED:
                    # Keep memory bounded: drop this frame and skip to the next delimiter.
                    self.overruns += 1
                    self._buffer.clear()
                    self._discarding = True
            if end < 0:
                return frames
            if not self._discarding and self._buffer:
                frame = self._decode(bytes(self._buffer))
                if frame is not None:
                    frames.append(frame)
            self._buffer.clear()
            self._discarding = False
            start = end + 1

    def _decode(self, encoded: bytes) -> Frame | None:
        try:
            body = cobs.decode(encoded)
        except cobs.DecodeError:
            self.bad_length += 1
            return None
        if len(body) < _MIN_FRAME:
            self.bad_length += 1
            return None
        crc_at = len(body) - m.CRC_SIZE
        if crc32c(body[:crc_at]) != int.from_bytes(body[crc_at:], "little"):
            self.bad_crc += 1
            return None
        type_id = body[0]
        payload = body[m.HEADER_SIZE : -m.CRC_SIZE]
        if m.PAYLOAD_SIZES.get(type_id) != len(payload):
            self.bad_length += 1
            return None
        self.accepted += 1
        seq = body[1] | (body[2] << 8)
        return Frame(type_id, seq, m.unpack_payload(type_id, payload))
