"""The C firmware and the Python host must read and write the very same bytes.

Both sides come from messages.py (the C side through the generated header), so these tests
check the generation is current and then compare the compiled C against the Python codec on
the same inputs: payload layouts, frame bytes, CRC.
"""

from __future__ import annotations

import binascii

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from strategies import any_message, sequence

from firmware_bridge import codec, gen_c, native
from firmware_bridge import messages as m

PROPS = settings(max_examples=300, deadline=None, derandomize=True)


def test_committed_header_is_generated_from_messages():
    assert gen_c.HEADER_PATH.read_text() == gen_c.render(), (
        "protocol_generated.h is stale: run python -m firmware_bridge.gen_c"
    )


def test_protocol_hash_agrees():
    assert native.protocol_hash() == m.PROTOCOL_HASH


@pytest.mark.parametrize("message_cls", m.MESSAGES, ids=lambda c: c.__name__)
def test_payload_sizes_agree(message_cls):
    assert native.payload_size(message_cls.TYPE) == m.PAYLOAD_SIZES[message_cls.TYPE]


def test_unknown_types_are_unknown_to_both():
    for type_id in range(256):
        if type_id not in m.BY_TYPE:
            assert native.payload_size(type_id) == -1
            assert native.proto_roundtrip(type_id, b"") is None


@PROPS
@given(message=any_message)
def test_python_pack_then_c_unpack_and_pack_is_identity(message):
    payload = m.pack_payload(message)
    assert native.proto_roundtrip(message.TYPE, payload) == payload


@pytest.mark.parametrize("message_cls", m.MESSAGES, ids=lambda c: c.__name__)
def test_c_refuses_payloads_of_the_wrong_length(message_cls):
    size = m.PAYLOAD_SIZES[message_cls.TYPE]
    assert native.proto_roundtrip(message_cls.TYPE, bytes(size + 1)) is None
    if size:
        assert native.proto_roundtrip(message_cls.TYPE, bytes(size - 1)) is None


@PROPS
@given(message=any_message, seq=sequence)
def test_c_frame_encoder_matches_the_codec(message, seq):
    assert native.encode_frame(message.TYPE, seq, m.pack_payload(message)) == (
        codec.encode_frame(message, seq)
    )


@PROPS
@given(
    type_id=st.integers(0, 255),
    seq=sequence,
    payload=st.binary(max_size=m.MAX_FRAME_DECODED - m.HEADER_SIZE - m.CRC_SIZE),
)
def test_c_frame_encoder_matches_for_any_bytes(type_id, seq, payload):
    # Zeros and long zero-free runs exercise every COBS code path.
    assert native.encode_frame(type_id, seq, payload) == codec.frame_bytes(type_id, seq, payload)


def test_c_frame_encoder_refuses_oversized_frames():
    with pytest.raises(ValueError):
        native.encode_frame(0x30, 0, bytes(m.MAX_FRAME_DECODED - 4))


def test_crc_check_value():
    assert native.crc32c(b"123456789") == 0xE3069283 == codec.crc32c(b"123456789")
    assert native.crc16(b"123456789") == 0x29B1 == binascii.crc_hqx(b"123456789", 0xFFFF)
    assert native.crc16(b"") == 0xFFFF


@PROPS
@given(data=st.binary(max_size=300))
def test_crc_agrees_with_the_codec_and_binascii(data):
    assert native.crc32c(data) == codec.crc32c(data)
    assert native.crc16(data) == binascii.crc_hqx(data, 0xFFFF)  # the stored config's CRC


def test_the_boards_timing_is_part_of_the_protocol(monkeypatch):
    """A board flashed with another watchdog speaks another protocol: refused at the HELLO."""
    from firmware_bridge import timing

    header = gen_c.HEADER_PATH.read_text()
    for entry in timing.board_entries():
        assert f"#define CARRT_T_{entry.name} {int(entry.value)}u" in header
    assert "LINK_TIMEOUT_MS=200" in m.canonical_definition()
    before = m.canonical_definition()
    other = tuple(
        timing.Timing(t.name, 201, t.unit, t.side, t.why) if t.name == "LINK_TIMEOUT_MS" else t
        for t in timing.TABLE
    )
    monkeypatch.setattr(timing, "TABLE", other)
    assert m.canonical_definition() != before
