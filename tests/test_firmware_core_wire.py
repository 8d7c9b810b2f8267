"""The firmware's side of the wire, checked on the real C core with a fake clock.

PING is answered with the board's time, telemetry goes out every 20 ms without drift (and
across the 32-bit clock wrap) with every field, bad frames are counted and dropped exactly as
the Python decoder counts them, the receive buffer holds one maximal frame, the counters
saturate, and a full transmit buffer drops whole frames. The safety rules are in
test_firmware_core.py.
"""

from __future__ import annotations

import pytest
from cobs import cobs
from firmware_rig import ARM, Bench
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_bridge import codec
from firmware_bridge import messages as m
from firmware_bridge.messages import ArmRefusal, Reason, State


def test_pong_echoes_nonce_and_board_time():
    b = Bench(now=1234)
    b.frames()
    b.send(m.Ping(0xCAFEF00D))
    (pong,) = b.frames()
    assert pong.message == m.Pong(0xCAFEF00D, 1234)


def test_telemetry_every_20_ms_without_drift_and_with_every_field():
    b = Bench(now=5)
    b.frames()
    b.core.tick(5)
    times = [f.message.mcu_time_ms for f in b.frames(m.Telemetry)]
    for t in range(5, 1000, 7):  # irregular ticks
        b.now = t
        b.core.tick(t)
    times += [f.message.mcu_time_ms for f in b.frames(m.Telemetry)]
    assert len(times) == 50
    assert all(t - 5 - 20 * i < 7 for i, t in enumerate(times))
    b.now = 5000  # far behind: one frame, then resync
    b.core.tick(5000)
    b.run(40, every=None)
    assert [f.message.mcu_time_ms for f in b.frames(m.Telemetry)] == [5000, 5020, 5040]

    b.set_encoder(-12345)
    b.run(120, flags=0)  # wheels still again for more than 100 ms
    b.command(steering=100, throttle=50, flags=ARM, decision_id=0xABCDEF01)
    b.run(20, every=None)
    frames = b.frames()
    tel = frames[-1].message
    assert tel == m.Telemetry(
        mcu_time_ms=b.now,
        encoder_ticks=-12345,
        steer_us=1505,
        throttle_us=1502,
        state=State.ARMED,
        reason=Reason.ARMED_OK,
        arm_refusal=ArmRefusal.NONE,
        flags=m.TelemetryFlags.LINK_OK,
        last_seq=b.seq - 1,
        decision_id=0xABCDEF01,
    )
    seqs = [f.seq for f in frames]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    b.run(200, every=None)
    assert not b.frames(m.Telemetry)[-1].message.flags & m.TelemetryFlags.LINK_OK


def test_telemetry_across_the_clock_wrap():
    b = Bench(now=0xFFFFFFF0)
    b.run(100, every=None)
    times = [f.message.mcu_time_ms for f in b.frames(m.Telemetry)]
    assert times == [0xFFFFFFF1] + [(0xFFFFFFF0 + 20 * i) & 0xFFFFFFFF for i in range(1, 6)]


def test_bad_frames_are_counted_and_dropped():
    b = Bench()
    good = codec.encode_frame(m.Ping(5), 1)
    body = cobs.decode(good[:-1])
    bad_crc = cobs.encode(body[:-1] + bytes([body[-1] ^ 0x55])) + b"\x00"
    short = codec.frame_bytes(m.Ping.TYPE, 2, b"\x01\x02\x03")
    unknown = codec.frame_bytes(0x7F, 3, b"")
    b.core.feed(b"\x00\x00" + bad_crc + short + unknown + b"\x05\x01\x00" + b"\x01" * 100, 0)
    b.core.feed(b"\x00\x00\x00" + good, 0)
    assert b.core.counters == {"bad_crc": 1, "bad_length": 3, "overruns": 1, "tx_dropped": 0}
    assert [f.message for f in b.frames(m.Pong)] == [m.Pong(5, 0)]


chunks = st.one_of(
    st.binary(max_size=80),
    st.builds(codec.encode_frame, st.builds(m.Ping, st.integers(0, 2**32 - 1)), st.integers(0, 9)),
    st.builds(lambda p: codec.frame_bytes(0x10, 0, p), st.binary(max_size=12)),
    st.just(b"\x00"),
)


@settings(max_examples=150, deadline=None, derandomize=True)
@given(parts=st.lists(chunks, max_size=12), split=st.integers(1, 40))
def test_any_byte_stream_is_counted_like_the_python_decoder(parts, split):
    stream = b"".join(parts)
    b = Bench()
    for i in range(0, len(stream), split):
        b.core.feed(stream[i : i + split], i)
        b.core.tick(i)
    ref = codec.FrameDecoder()
    ref.feed(stream)
    counters = b.core.counters
    assert (counters["bad_crc"], counters["bad_length"], counters["overruns"]) == (
        ref.bad_crc,
        ref.bad_length,
        ref.overruns,
    )


@pytest.mark.parametrize("n", [64, 65, 66, 200])
def test_the_receive_buffer_holds_exactly_one_maximal_encoded_frame(n):
    stream = b"\x01" * n + b"\x00" + codec.encode_frame(m.Ping(9), 3)
    b = Bench()
    b.core.feed(stream, 0)
    ref = codec.FrameDecoder()
    assert [f.message for f in ref.feed(stream)] == [m.Ping(9)]
    assert b.core.counters["overruns"] == ref.overruns == (1 if n > 65 else 0)
    assert b.core.counters["bad_crc"] + b.core.counters["bad_length"] == (0 if n > 65 else 1)
    assert [f.message for f in b.frames(m.Pong)] == [m.Pong(9, 0)]


def test_counters_saturate():
    b = Bench()
    body = cobs.decode(codec.encode_frame(m.Ping(0), 0)[:-1])
    bad_crc = cobs.encode(body[:-1] + bytes([body[-1] ^ 1])) + b"\x00"
    b.core.feed(b"\x01\x00" * 70000 + bad_crc * 70000 + (b"\x01" * 70 + b"\x00") * 70000, 0)
    assert b.core.counters == {
        "bad_crc": 0xFFFF,
        "bad_length": 0xFFFF,
        "overruns": 0xFFFF,
        "tx_dropped": 0,
    }


def test_tx_overflow_drops_whole_frames():
    b = Bench()
    b.run(10000, every=None)  # 500 telemetry frames, nobody reading
    assert b.core.counters["tx_dropped"] > 0
    out = b.core.take_output()
    assert len(out) <= 8192 and out.endswith(b"\x00")
    assert all(b.decoder.feed(out)) and b.decoder.rejected == 0
