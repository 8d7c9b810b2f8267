"""Serial link: round trip host → virtual board → host, e-stop latency, codec throughput.

Ratios printed: RTT p99 against the 200 ms watchdog budget, e-stop latency against the 20 ms
send period it must not wait for, and the C core's frame rate against the Python decoder's
on the same byte stream.
"""

from __future__ import annotations

import random
import statistics
import time

from firmware_bridge import messages as m
from firmware_bridge.codec import FrameDecoder, encode_frame
from firmware_bridge.link import SEND_PERIOD_S, BoardLink
from firmware_bridge.native import FirmwareCore
from firmware_bridge.virtual import VirtualBoard

WATCHDOG_S = 0.2


def _pct(values, q):
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def _stream(n_frames: int) -> bytes:
    rng = random.Random(0)
    frames = []
    for i in range(n_frames):
        cmd = m.Command(rng.randint(-10000, 10000), rng.randint(-10000, 10000), i, 0)
        frames.append(b"\x00" + encode_frame(cmd, i & 0xFFFF))
    return b"".join(frames)


def codec_throughput(n_frames: int = 50_000) -> dict:
    stream = _stream(n_frames)
    chunks = [stream[i : i + 64] for i in range(0, len(stream), 64)]

    start = time.perf_counter()
    for i in range(n_frames):
        encode_frame(m.Telemetry(mcu_time_ms=i), i & 0xFFFF)
    encode_s = time.perf_counter() - start

    decoder = FrameDecoder()
    start = time.perf_counter()
    got = sum(len(decoder.feed(chunk)) for chunk in chunks)
    py_s = time.perf_counter() - start
    assert got == n_frames

    core = FirmwareCore()
    core.boot(1, 0)
    start = time.perf_counter()
    for i, chunk in enumerate(chunks):
        core.feed(chunk, i // 8)
    c_s = time.perf_counter() - start
    assert sum(core.counters[k] for k in ("bad_crc", "bad_length", "overruns")) == 0
    return {
        "frames": n_frames,
        "stream_bytes": len(stream),
        "python_encode_frames_per_s": n_frames / encode_s,
        "python_decode_frames_per_s": n_frames / py_s,
        "python_decode_mb_per_s": len(stream) / py_s / 1e6,
        "c_core_rx_frames_per_s": n_frames / c_s,
        "ratio_c_core_over_python_decode": py_s / c_s,
    }


def round_trip(pings: int = 500) -> dict:
    with VirtualBoard() as board, BoardLink(board.port) as link:
        link.ping()
        rtts = [link.ping() for _ in range(pings)]
        estops = []
        for _ in range(30):
            link.set_command(0.0, 0.0)
            time.sleep(0.03)
            start = time.perf_counter()
            link.estop()
            while board.state != m.State.ESTOP:
                time.sleep(0.0002)
            estops.append(time.perf_counter() - start)
            link.clear()
    p50, p99 = statistics.median(rtts), _pct(rtts, 0.99)
    e50, e99 = statistics.median(estops), _pct(estops, 0.99)
    return {
        "pings": pings,
        "rtt_p50_ms": p50 * 1e3,
        "rtt_p99_ms": p99 * 1e3,
        "rtt_max_ms": max(rtts) * 1e3,
        "ratio_rtt_p99_over_watchdog": p99 / WATCHDOG_S,
        "estop_trials": len(estops),
        "estop_to_board_p50_ms": e50 * 1e3,
        "estop_to_board_p99_ms": e99 * 1e3,
        "ratio_estop_p99_over_send_period": e99 / SEND_PERIOD_S,
    }


def run() -> dict:
    codec = codec_throughput()
    rtt = round_trip()
    print(
        f"   codec: encode {codec['python_encode_frames_per_s']:,.0f} frames/s, "
        f"decode {codec['python_decode_frames_per_s']:,.0f} frames/s "
        f"({codec['python_decode_mb_per_s']:.2f} MB/s); C core rx "
        f"{codec['c_core_rx_frames_per_s']:,.0f} frames/s "
        f"= {codec['ratio_c_core_over_python_decode']:.1f}x the Python decoder"
    )
    print(
        f"   round trip over pty: p50 {rtt['rtt_p50_ms']:.2f} ms, p99 {rtt['rtt_p99_ms']:.2f} ms "
        f"= {rtt['ratio_rtt_p99_over_watchdog']:.3f} of the 200 ms watchdog"
    )
    print(
        f"   e-stop call -> board ESTOP: p50 {rtt['estop_to_board_p50_ms']:.2f} ms, "
        f"p99 {rtt['estop_to_board_p99_ms']:.2f} ms "
        f"= {rtt['ratio_estop_p99_over_send_period']:.2f} of one 20 ms send period"
    )
    return {"codec": codec, "round_trip": rtt}
