"""The control loop through the whole stack: jitter, frame-to-command latency, e-stop latency.

`carrt drive` runs in-process against the virtual board on a pty, a video file as the camera,
a synthetic pad and a small ONNX policy, in AUTO and recording, for CARRT_BENCH_LOOP_S seconds
(60 by default). Then the e-stop button is pressed repeatedly during `carrt teleop` and the
time until the board is in ESTOP is measured, against the loop period it must not wait for.
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from e2e_rig import PAD_SETTINGS, CliRun, SyntheticPad, clear_and_rearm, wait_for, write_video
from onnx_models import build_policy

from firmware_bridge import messages as m
from firmware_bridge.virtual import VirtualBoard

SECONDS = float(os.environ.get("CARRT_BENCH_LOOP_S", "60"))
PERIOD_S = 0.1


def _argv(command, board, video, out, seconds, *extra):
    return [
        command, "--port", board.port, "--camera", str(video), "--out", str(out),
        "--duration", str(seconds), "--set", "camera.loop_video=true",
        *(x for s in PAD_SETTINGS for x in ("--set", s)), *extra,
    ]  # fmt: skip


def _arm(pad, board):
    pad.wait_ready()
    pad.connect_neutral()
    time.sleep(0.3)
    pad.press("arm")
    wait_for(lambda: board.state == m.State.ARMED)


def loop_run(tmp: Path) -> dict:
    video = write_video(tmp / "camera.avi", seconds=3.0)
    model = build_policy(tmp / "policy.onnx")
    summary_path = tmp / "summary.json"
    with VirtualBoard() as board:
        run = CliRun(
            _argv("drive", board, video, tmp / "eps", SECONDS, "--model", str(model),
                  "--record", "--summary-json", str(summary_path))
        )  # fmt: skip
        pad = SyntheticPad()
        _arm(pad, board)
        pad.press("auto")
        assert run.result(timeout_s=SECONDS + 30) == 0
    s = json.loads(summary_path.read_text())
    return {
        "seconds": s["duration_s"],
        "ticks": s["steps"],
        "achieved_hz": s["achieved_hz"],
        "overruns": s["overruns"],
        "tick_lateness_p50_ms": s["tick_lateness_ms"][0],
        "tick_lateness_p99_ms": s["tick_lateness_ms"][1],
        "tick_lateness_max_ms": s["max_tick_lateness_ms"],
        "ratio_lateness_p99_over_period": s["tick_lateness_ms"][1] / 1e3 / PERIOD_S,
        "frame_to_command_p50_ms": s["frame_to_command_ms"][0],
        "frame_to_command_p99_ms": s["frame_to_command_ms"][1],
        # The phase lock's figure: what a command waits beyond its inference (target ≤ 3 ms).
        "frame_to_command_minus_inference_p50_ms": (
            s["frame_to_command_ms"][0] - s["sections_ms"]["inference"][0]
        ),
        "sections_ms": s["sections_ms"],
        "recorded_steps": s["recorded_steps"],
        "dropped_steps": s["dropped_steps"],
    }


def estop_latency(tmp: Path, trials: int = 10) -> dict:
    video = write_video(tmp / "camera.avi", seconds=3.0)
    latencies = []
    with VirtualBoard() as board:
        run = CliRun(_argv("teleop", board, video, tmp / "eps2", trials * 2.5 + 5))
        pad = SyntheticPad()
        _arm(pad, board)
        for _ in range(trials):
            pad.sticks(0.0, 0.3)
            wait_for(lambda: board.throttle_us > 1550, timeout_s=3.0)
            posted = time.perf_counter()
            pad.press("estop")
            while board.state != m.State.ESTOP:
                time.sleep(0.0002)
            latencies.append(time.perf_counter() - posted)
            pad.sticks(0.0, 0.0)
            clear_and_rearm(pad, board, pause_s=0.3)
        run.result(timeout_s=60)
    latencies.sort()
    p50 = statistics.median(latencies)
    worst = latencies[-1]
    return {
        "trials": trials,
        "estop_button_to_board_p50_ms": p50 * 1e3,
        "estop_button_to_board_max_ms": worst * 1e3,
        "ratio_max_over_loop_period": worst / PERIOD_S,
    }


def run() -> dict:
    with tempfile.TemporaryDirectory(prefix="carrt-bench-loop-") as tmp:
        loop = loop_run(Path(tmp))
        estop = estop_latency(Path(tmp))
    print(
        f"   loop ({loop['seconds']:.0f} s, AUTO, recording): {loop['achieved_hz']:.2f} Hz, "
        f"{loop['overruns']} overruns, tick lateness p50 {loop['tick_lateness_p50_ms']:.2f} ms "
        f"p99 {loop['tick_lateness_p99_ms']:.2f} ms max {loop['tick_lateness_max_ms']:.2f} ms "
        f"= {loop['ratio_lateness_p99_over_period']:.3f} of the period"
    )
    print(
        f"   frame -> command: p50 {loop['frame_to_command_p50_ms']:.1f} ms, "
        f"p99 {loop['frame_to_command_p99_ms']:.1f} ms = inference p50 "
        f"{loop['sections_ms']['inference'][0]:.2f} ms + "
        f"{loop['frame_to_command_minus_inference_p50_ms']:.2f} ms; steps recorded "
        f"{loop['recorded_steps']}, dropped {loop['dropped_steps']}"
    )
    print(
        f"   e-stop button -> board ESTOP: p50 {estop['estop_button_to_board_p50_ms']:.2f} ms, "
        f"max {estop['estop_button_to_board_max_ms']:.2f} ms "
        f"= {estop['ratio_max_over_loop_period']:.3f} of one 100 ms loop period"
    )
    return {"loop": loop, "estop": estop}
