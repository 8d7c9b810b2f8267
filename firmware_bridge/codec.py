"""Framing of the serial protocol: COBS, 0x00 delimiters, CRC-16/CCITT-FALSE.

A decoded frame is ``type u8 · sequence u16 · payload · crc u16`` (little-endian), the CRC
taken over everything before it. COBS removes every 0x00 from the frame so a single 0x00 can
end it: a receiver that starts mid-stream, or loses bytes, resynchronises at the next 0x00
instead of misreading the rest of the session.

The decoder is written for a serial port: it takes whatever chunk ``read()`` returned, keeps
partial frames across calls, never raises on bad input, never grows without bound, and counts
what it throws away so the link can report it.
"""

from __future__ import annotations

import binascii
from dataclasses import dataclass
from typing import Any

from cobs import cobs

from firmware_bridge import messages as m

_MIN_FRAME = m.HEADER_SIZE + m.CRC_SIZE
# COBS adds one code byte per 254 data bytes (and one at the start).
MAX_FRAME_ENCODED = m.MAX_FRAME_DECODED + m.MAX_FRAME_DECODED // 254 + 1


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF); 0x29B1 for b"123456789"."""
    return binascii.crc_hqx(data, 0xFFFF)


@dataclass(frozen=True)
class Frame:
    """One accepted frame: its type, the sender's sequence number and the decoded message."""

    type_id: int
    seq: int
    message: Any


def frame_bytes(type_id: int, seq: int, payload: bytes) -> bytes:
    """Wire bytes (COBS + trailing 0x00) for a raw payload; ``encode_frame`` is the usual entry."""
    body = bytes((type_id, seq & 0xFF, (seq >> 8) & 0xFF)) + payload
    body += crc16(body).to_bytes(2, "little")
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
        if crc16(body[:-2]) != int.from_bytes(body[-2:], "little"):
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
