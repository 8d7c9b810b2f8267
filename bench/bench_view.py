"""What watching costs the loop: p99 tick lateness with a browser's worth of polling, and without.

`carrt drive --sim --autopilot --realtime --model demo --view 0` (the whole stack in real time:
virtual board on a pty, the camera rendering on its own thread, the demo policy in AUTO) runs
CARRT_BENCH_VIEW_S seconds (30 by default) per run, in CARRT_BENCH_VIEW_ROUNDS rounds (3) of
one run without a client and one with one, alternated so that whatever else loads the machine
falls on both. The client is another process, as a browser is: it does what the live page does
(state.json?after=N, answered when the next tick is published, then the camera and crop JPEGs
of that tick, then 20 ms later the next poll) over one keep-alive connection. The issue's
target: p99 with a client within 0.5 ms of p99 without.
"""

from __future__ import annotations

import http.client
import json
import os
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SECONDS = float(os.environ.get("CARRT_BENCH_VIEW_S", "30"))
ROUNDS = int(os.environ.get("CARRT_BENCH_VIEW_ROUNDS", "3"))
TARGET_MS = 0.5


class PageClient:
    """Polls like carrt/view/live.html does, on its own thread, until stopped."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.stop = threading.Event()
        self.requests = self.frames = self.errors = 0
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _get(self, conn: http.client.HTTPConnection, path: str) -> bytes:
        conn.request("GET", path)
        answer = conn.getresponse()
        body = answer.read()
        self.requests += 1
        if answer.status != 200:
            self.errors += 1
        return body

    def _run(self) -> None:
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=5)
        last_tick = -1
        while not self.stop.is_set():
            try:
                state = json.loads(self._get(conn, f"/state.json?after={last_tick}"))
                tick = state["tick"]
                if tick != last_tick and state["frame_seq"] is not None:
                    last_tick = tick
                    self._get(conn, f"/camera.jpg?t={tick}")
                    self._get(conn, f"/crop.jpg?t={tick}")
                    self.frames += 1
            except (OSError, http.client.HTTPException, ValueError):
                self.errors += 1
                conn.close()
                conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=5)
            self.stop.wait(0.02)  # the page's pause between polls
        conn.close()


def one_run(tmp: Path, with_client: bool) -> dict:
    summary = tmp / f"summary-{int(with_client)}.json"
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy", "PYTHONPATH": str(ROOT)}
    argv = [sys.executable, "-m", "carrt", "drive", "--sim", "--autopilot", "--realtime",
            "--model", "demo", "--layout", "easy", "--duration", str(SECONDS), "--view", "0",
            "--summary-json", str(summary)]  # fmt: skip
    process = subprocess.Popen(argv, env=env, cwd=tmp, stdout=subprocess.PIPE, text=True)
    client = None
    for line in process.stdout:
        if line.startswith("view: "):
            port = int(line.split("://", 1)[1].split("/", 1)[0].rsplit(":", 1)[1])
            if with_client:
                client = PageClient(port)
                client.thread.start()
            break
    process.stdout.read()  # the rest of its output, until it exits
    if client is not None:
        client.stop.set()
        client.thread.join(5)
    assert process.wait(timeout=60) == 0, "carrt drive --sim failed"
    s = json.loads(summary.read_text())
    return {
        "client": with_client,
        "ticks": s["steps"],
        "overruns": s["overruns"],
        "tick_lateness_p50_ms": s["tick_lateness_ms"][0],
        "tick_lateness_p99_ms": s["tick_lateness_ms"][1],
        "tick_lateness_max_ms": s["max_tick_lateness_ms"],
        "client_requests": client.requests if client else 0,
        "client_frames": client.frames if client else 0,
        "client_errors": client.errors if client else 0,
    }


def run() -> dict:
    runs = []
    with tempfile.TemporaryDirectory(prefix="carrt-bench-view-") as tmp:
        for _ in range(ROUNDS):
            for with_client in (False, True):
                runs.append(one_run(Path(tmp), with_client))
                r = runs[-1]
                print(
                    f"   {'with' if with_client else 'no  '} client: p99 lateness "
                    f"{r['tick_lateness_p99_ms']:.2f} ms (p50 {r['tick_lateness_p50_ms']:.2f}, "
                    f"max {r['tick_lateness_max_ms']:.2f}, {r['overruns']} overruns); client "
                    f"{r['client_requests']} requests, {r['client_frames']} frame pairs, "
                    f"{r['client_errors']} errors",
                    flush=True,
                )

    def mean_p99(with_client: bool) -> float:
        values = [r["tick_lateness_p99_ms"] for r in runs if r["client"] == with_client]
        return sum(values) / len(values)

    without, with_ = mean_p99(False), mean_p99(True)
    result = {
        "seconds_per_run": SECONDS,
        "rounds": ROUNDS,
        "p99_lateness_without_client_ms": without,
        "p99_lateness_with_client_ms": with_,
        "p99_difference_ms": with_ - without,
        "target_ms": TARGET_MS,
        "within_target": with_ - without <= TARGET_MS,
        "runs": runs,
    }
    print(
        f"   p99 tick lateness, mean of {ROUNDS} runs each: without a client {without:.2f} ms, "
        f"with one {with_:.2f} ms, difference {with_ - without:+.2f} ms "
        f"(target <= {TARGET_MS} ms: {'met' if result['within_target'] else 'NOT met'})"
    )
    return result
