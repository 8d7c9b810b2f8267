"""The simulated-clock loop's speed-up over real time.

`carrt teleop --sim --expert auto --record` runs the real control loop, arbitration, C firmware
core (in-process), renderer and episode writer for SIM_SECONDS of simulated driving; the ratio
of simulated to wall-clock seconds is how much faster than real time data collection and
evaluation run on this machine.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from e2e_rig import CliRun

SIM_SECONDS = float(os.environ.get("CARRT_BENCH_SIM_S", "120"))


def run() -> dict:
    with tempfile.TemporaryDirectory(prefix="carrt-bench-simloop-") as tmp:
        out = Path(tmp) / "eps"
        summary = Path(tmp) / "summary.json"
        start = time.perf_counter()
        code = CliRun(
            ["teleop", "--sim", "--expert", "auto", "--record", "--layout", "easy",
             "--duration", str(SIM_SECONDS), "--out", str(out), "--summary-json", str(summary)]
        ).result(timeout_s=SIM_SECONDS * 2 + 60)  # fmt: skip
        wall = time.perf_counter() - start
        assert code == 0
        loop = json.loads(summary.read_text())
    result = {
        "simulated_s": loop["duration_s"],
        "wall_s": wall,
        "ticks": loop["steps"],
        "ticks_per_wall_s": loop["steps"] / wall,
        "speedup_over_real_time": loop["duration_s"] / wall,
        "recorded_steps": loop["recorded_steps"],
        "dropped_steps": loop["dropped_steps"],
    }
    print(
        f"   simulated clock: {result['simulated_s']:.0f} s of driving in {wall:.1f} s "
        f"= {result['speedup_over_real_time']:.1f}x real time "
        f"({result['ticks_per_wall_s']:.0f} control ticks/s, recorded "
        f"{result['recorded_steps']}, dropped {result['dropped_steps']})"
    )
    return result
