"""The Python codec: round trips, hostile byte streams, corruption and resynchronisation."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st
from strategies import any_message, sequence

from firmware_bridge import messages as m
from firmware_bridge.codec import MAX_FRAME_ENCODED, FrameDecoder, crc32c, encode_frame


def test_crc_check_value():
    assert crc32c(b"123456789") == 0xE3069283  # the catalogue's check value for CRC-32C
    assert crc32c(b"") == 0


def test_definitions_fit_the_frame_limit():
    m.check_definitions()
    assert len({cls.TYPE for cls in m.MESSAGES}) == len(m.MESSAGES)


@given(any_message, sequence)
def test_every_message_round_trips(message, seq):
    wire = encode_frame(message, seq)
    assert wire.count(0) == 1 and wire.endswith(b"\x00"), "only the delimiter may be zero"
    frames = FrameDecoder().feed(wire)
    assert len(frames) == 1
    assert frames[0].message == message
    assert frames[0].seq == seq
    assert frames[0].type_id == message.TYPE


@given(st.lists(st.tuples(any_message, sequence), min_size=1, max_size=8), st.data())
def test_arbitrary_chunking_yields_the_same_frames(items, data):
    stream = b"".join(encode_frame(msg, seq) for msg, seq in items)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=12)))
    decoder = FrameDecoder()
    frames = []
    for start, end in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        frames += decoder.feed(stream[start:end])
    assert [(f.message, f.seq) for f in frames] == items
    assert decoder.rejected == 0


@given(st.lists(st.binary(max_size=300), max_size=20))
def test_any_byte_stream_never_raises_and_stays_bounded(chunks):
    decoder = FrameDecoder()
    for chunk in chunks:
        for frame in decoder.feed(chunk):
            # Anything accepted from noise must still be a well-formed message.
            assert frame.type_id in m.BY_TYPE
        assert len(decoder._buffer) <= MAX_FRAME_ENCODED


def test_a_long_run_without_delimiter_is_an_overrun_then_resyncs():
    decoder = FrameDecoder()
    ping = m.Ping(nonce=7)
    assert decoder.feed(b"\x55" * 10_000) == []
    assert decoder.feed(b"\x55" * 10_000) == []
    assert decoder.overruns == 1
    frames = decoder.feed(b"\x00" + encode_frame(ping, 1))
    assert [f.message for f in frames] == [ping]


@given(any_message, sequence, st.data())
def test_a_frame_with_any_corrupted_byte_is_never_accepted(message, seq, data):
    wire = bytearray(encode_frame(message, seq))
    index = data.draw(st.integers(0, len(wire) - 2), label="index")  # not the delimiter
    new = data.draw(st.integers(0, 255).filter(lambda b: b != wire[index]), label="value")
    wire[index] = new
    decoder = FrameDecoder()
    frames = decoder.feed(bytes(wire))
    assert frames == []
    assert decoder.rejected >= 1


@given(st.binary(max_size=200), any_message, sequence)
def test_after_garbage_the_next_valid_frame_is_received(garbage, message, seq):
    decoder = FrameDecoder()
    # The sender's leading delimiter ends whatever partial frame the garbage left open.
    frames = decoder.feed(garbage + b"\x00" + encode_frame(message, seq))
    assert frames[-1].message == message
    assert frames[-1].seq == seq


def test_wrong_length_and_unknown_type_are_counted_as_bad_length():
    from firmware_bridge.codec import frame_bytes

    decoder = FrameDecoder()
    assert decoder.feed(frame_bytes(m.Ping.TYPE, 0, b"\x01\x02\x03")) == []
    assert decoder.feed(frame_bytes(0xEE, 0, b"")) == []
    assert decoder.bad_length == 2
    assert decoder.bad_crc == 0


def test_oversized_frames_are_refused_at_encode_time():
    from firmware_bridge.codec import frame_bytes

    with pytest.raises(ValueError, match="exceeds"):
        frame_bytes(0x10, 0, bytes(100))


def test_crc32c_detects_every_error_of_up_to_5_bits_in_the_longest_frame():
    """PROTOCOL.md's claim, checked rather than quoted: Hamming distance ≥ 6 for a 64-byte frame
    (60 bytes + CRC). The CRC is affine, so a flip pattern passes iff the XOR of its bits'
    syndromes is zero; no XOR of ≤ 5 of the 512 syndromes may be zero, which meet-in-the-middle
    checks with every single, pair and triple (a pair equal to a triple is a 5-bit pattern, or a
    smaller one when they share a bit)."""
    import math

    import numpy as np

    data_len = m.MAX_FRAME_DECODED - m.CRC_SIZE
    base = crc32c(bytes(data_len))
    syndromes = [
        crc32c((1 << bit).to_bytes(data_len, "little")) ^ base for bit in range(8 * data_len)
    ] + [1 << bit for bit in range(8 * m.CRC_SIZE)]
    s = np.array(syndromes, dtype=np.uint32)
    n = len(s)
    assert n == 512 and np.all(s != 0) and len(np.unique(s)) == n  # 1 and 2 bits
    i, j = np.triu_indices(n, 1)
    pairs = s[i] ^ s[j]
    assert len(np.unique(pairs)) == len(pairs)  # 4 bits (2 + 2), or 2 bits
    assert not np.isin(s, pairs).any()  # 3 bits (1 + 2)
    triples = np.sort(np.concatenate([s[a] ^ pairs[i > a] for a in range(n)]))
    assert len(triples) == math.comb(n, 3)
    where = np.minimum(np.searchsorted(triples, pairs), len(triples) - 1)
    assert not (triples[where] == pairs).any()  # 5 bits (2 + 3), or fewer
