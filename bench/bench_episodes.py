"""Episodes: what recording costs the control loop, and how fast training can read frames back.

Ratios printed: the loop thread's cost of EpisodeWriter.write() against writing the same step
synchronously on the loop thread (append frame + record, fdatasync every 10 steps = 1 s at
10 Hz); the writer thread's sustained steps/s against the 10 Hz it must keep up with; and the
reader's frames/s through the memory map against the 10 Hz recording rate. Files live in the
system temp directory; reads are from the page cache (no cache dropping here).
"""

from __future__ import annotations

import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from carrt.episodes import EpisodeWriter, read_episode
from carrt.episodes import format as fmt
from carrt.interfaces import Mode, Step
from carrt.model_contract import HORIZON

RATE_HZ = 10.0
PACED_HZ = 200.0


def _pct(values, q):
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def _steps(n: int) -> list[Step]:
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, size=(16, 96, 96, 3), dtype=np.uint8)
    plan = rng.uniform(-1, 1, (HORIZON, 2)).astype(np.float32)
    out = []
    for i in range(n):
        t = 100.0 + i / RATE_HZ
        out.append(
            Step(index=i, image=images[i % 16], frame_captured_at=t, command_sent_at=t + 0.01,
                 wall_time=1.7e9 + t, speed_mps=1.5, encoder_ticks=i * 7, human_action=(0.1, 0.5),
                 policy_action=(0.1, 0.5), executed_action=(0.1, 0.5), mode=Mode.AUTO,
                 override=False, estop=False, noise=False, collision=False, lap=False,
                 plan_mu=plan, plan_sigma=plan * 0.1)
        )  # fmt: skip
    return out


def _timed_writes(root: Path, steps: list[Step], period_s: float) -> tuple[list[int], int]:
    """write() durations (ns) with the producer paced at `period_s` (0: back to back)."""
    with EpisodeWriter(root) as writer:
        writer.begin({"command": "bench"})
        durations = []
        deadline = time.perf_counter()
        for step in steps:
            deadline += period_s
            if period_s:  # sleep, not spin: a spinning producer starves the writer of the GIL
                time.sleep(max(0.0, deadline - time.perf_counter()))
            start = time.perf_counter_ns()
            writer.write(step)
            durations.append(time.perf_counter_ns() - start)
        dropped = writer.dropped
        writer.end("stopped")
    return durations, dropped


def loop_cost(root: Path, n: int = 600) -> dict:
    steps = _steps(n)
    # At 200 Hz (20x the loop rate) the writer keeps up: every write() is a real copy + enqueue.
    write_ns, dropped = _timed_writes(root / "paced", steps, 1.0 / PACED_HZ)
    burst_ns, burst_dropped = _timed_writes(root / "burst", steps, 0.0)

    sync_dir = root / "sync"
    sync_dir.mkdir()
    flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND
    frames_fd = os.open(sync_dir / fmt.FRAMES, flags, 0o644)
    steps_fd = os.open(sync_dir / fmt.STEPS, flags, 0o644)
    sync_ns = []
    try:
        for i, step in enumerate(steps):
            start = time.perf_counter_ns()
            image = step.image.tobytes()
            os.write(frames_fd, image)
            os.write(steps_fd, fmt.pack_step(step, image, i))
            if i % int(RATE_HZ) == int(RATE_HZ) - 1:
                os.fdatasync(frames_fd)
                os.fdatasync(steps_fd)
            sync_ns.append(time.perf_counter_ns() - start)
    finally:
        os.close(frames_fd)
        os.close(steps_fd)
    us = 1e-3
    w50, w99 = statistics.median(write_ns) * us, _pct(write_ns, 0.99) * us
    s50, s99 = statistics.median(sync_ns) * us, _pct(sync_ns, 0.99) * us
    return {
        "steps": n,
        "write_p50_us": w50,
        "write_p99_us": w99,
        "write_max_us": max(write_ns) * us,
        "paced_hz": PACED_HZ,
        "write_dropped_paced": dropped,
        "burst_write_p50_us": statistics.median(burst_ns) * us,
        "burst_write_p99_us": _pct(burst_ns, 0.99) * us,
        "burst_dropped": burst_dropped,
        "sync_p50_us": s50,
        "sync_p99_us": s99,
        "sync_max_us": max(sync_ns) * us,
        "ratio_sync_over_write_p50": s50 / w50,
        "ratio_sync_over_write_p99": s99 / w99,
    }


def writer_throughput(root: Path, n: int = 3000) -> tuple[dict, Path]:
    steps = _steps(n)
    with EpisodeWriter(root / "throughput", queue_steps=n + 1) as writer:
        writer.begin({"command": "bench"})
        start = time.perf_counter()
        for step in steps:
            writer.write(step)
        writer.end("stopped")
        writer.flush(None)
        elapsed = time.perf_counter() - start
        path = writer.last_episode_path
    return {
        "steps": n,
        "steps_per_s": n / elapsed,
        "mb_per_s": n * (fmt.FRAME_BYTES + fmt.STEP_DTYPE.itemsize) / elapsed / 1e6,
        "ratio_over_10hz": n / elapsed / RATE_HZ,
    }, path


def reader_speed(path: Path) -> dict:
    start = time.perf_counter()
    ep = read_episode(path)
    open_s = time.perf_counter() - start
    start = time.perf_counter()
    read_episode(path, verify_all=True)
    verify_s = time.perf_counter() - start
    n = ep.n
    batch = np.empty((128, 96, 96, 3), dtype=np.uint8)
    start = time.perf_counter()
    for i in range(n):
        batch[i % 128] = ep.frames[i]
    seq_s = time.perf_counter() - start
    order = np.random.default_rng(0).permutation(n)
    start = time.perf_counter()
    for k in range(0, n, 128):
        idx = np.sort(order[k : k + 128])
        batch[: len(idx)] = ep.frames[idx]
    shuffled_s = time.perf_counter() - start
    return {
        "frames": n,
        "open_ms": open_s * 1e3,
        "verify_all_ms": verify_s * 1e3,
        "verify_all_mb_per_s": n * fmt.FRAME_BYTES / verify_s / 1e6,
        "sequential_frames_per_s": n / seq_s,
        "shuffled_batches_frames_per_s": n / shuffled_s,
        "ratio_sequential_over_10hz": n / seq_s / RATE_HZ,
    }


def run() -> dict:
    root = Path(tempfile.mkdtemp(prefix="carrt-bench-episodes-"))
    try:
        cost = loop_cost(root)
        throughput, path = writer_throughput(root)
        reader = reader_speed(path)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print(
        f"   loop thread, {cost['steps']} steps at {PACED_HZ:.0f} Hz: write() p50 "
        f"{cost['write_p50_us']:.1f} us, p99 {cost['write_p99_us']:.1f} us "
        f"({cost['write_dropped_paced']} dropped); synchronous write p50 "
        f"{cost['sync_p50_us']:.1f} us, p99 {cost['sync_p99_us']:.0f} us "
        f"= {cost['ratio_sync_over_write_p50']:.0f}x / {cost['ratio_sync_over_write_p99']:.0f}x"
    )
    print(
        f"   back to back: write() p50 {cost['burst_write_p50_us']:.1f} us, p99 "
        f"{cost['burst_write_p99_us']:.1f} us, {cost['burst_dropped']}/{cost['steps']} dropped "
        "(queue of 32 full: drops, never waits)"
    )
    print(
        f"   writer thread: {throughput['steps_per_s']:,.0f} steps/s "
        f"({throughput['mb_per_s']:.0f} MB/s) = {throughput['ratio_over_10hz']:,.0f}x "
        "the 10 Hz loop"
    )
    print(
        f"   reader, {reader['frames']} frames: open {reader['open_ms']:.1f} ms, verify all "
        f"{reader['verify_all_mb_per_s']:,.0f} MB/s; memmap "
        f"{reader['sequential_frames_per_s']:,.0f} frames/s sequential, "
        f"{reader['shuffled_batches_frames_per_s']:,.0f} frames/s in shuffled batches of 128 "
        f"= {reader['ratio_sequential_over_10hz']:,.0f}x the 10 Hz rate"
    )
    return {"loop_cost": cost, "writer_throughput": throughput, "reader": reader}
