"""LeRobotDataset v3.0 export and import: seconds per 1,000 frames, bytes per frame, frame error.

A drive of the shipped policy in the simulator (placement 101, on the simulated clock, about
1,000 frames: real camera frames, whose edges are what the codec finds hard) is exported with
each video setting and imported back; the error is the largest and the mean absolute
difference of an imported frame from the recorded one, in levels of 255 (PyAV's decoder here;
LeRobot's reader through torchcodec is within 2 levels of the recorded frames with lossless,
tests/test_episodes_lerobot_reader.py).
"""

from __future__ import annotations

import contextlib
import io
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from carrt.cli import main as carrt
from carrt.episodes.lerobot_export import VIDEO, export_lerobot
from carrt.episodes.lerobot_import import import_lerobot
from carrt.episodes.reader import list_episodes, read_episode
from carrt.shipped import SHIPPED_MODELS

SECONDS = 100  # 10 Hz: about 1,000 frames


def record(out: Path) -> list:
    argv = ["drive", "--sim", "--autopilot", "--model", str(SHIPPED_MODELS["demo"]), "--record",
            "--layout", "hard", "--track-seed", "101", "--duration", str(SECONDS),
            "--out", str(out)]  # fmt: skip
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert carrt(argv) == 0
    return [read_episode(p) for p in list_episodes([str(out)])]


def run() -> dict:
    root = Path(tempfile.mkdtemp(prefix="carrt-bench-lerobot-"))
    try:
        recorded = record(root / "episodes")
        frames = sum(ep.n for ep in recorded)
        rows = {}
        for video in VIDEO:
            dataset, back = root / f"lerobot-{video}", root / f"back-{video}"
            start = time.perf_counter()
            export_lerobot([str(root / "episodes")], dataset, video=video)
            exported = time.perf_counter() - start
            start = time.perf_counter()
            paths = import_lerobot(dataset, back)
            imported = time.perf_counter() - start
            errors = [
                np.abs(np.asarray(a.frames, int) - np.asarray(read_episode(p).frames, int))
                for a, p in zip(recorded, paths, strict=True)
            ]
            size = sum(f.stat().st_size for f in (dataset / "videos").rglob("*.mp4"))
            rows[video] = {
                "export_s_per_1000_frames": exported / frames * 1000,
                "import_s_per_1000_frames": imported / frames * 1000,
                "video_bytes_per_frame": size / frames,
                "frame_error_max": int(max(e.max() for e in errors)),
                "frame_error_mean": float(np.mean([e.mean() for e in errors])),
            }
        print(f"{frames} frames of a simulated drive")
        print(f"{'video':<9} {'export s/1000':>14} {'import s/1000':>14} {'bytes/frame':>12} "
              f"{'max err':>8} {'mean err':>9}")  # fmt: skip
        for video, r in rows.items():
            print(f"{video:<9} {r['export_s_per_1000_frames']:>14.2f} "
                  f"{r['import_s_per_1000_frames']:>14.2f} {r['video_bytes_per_frame']:>12.0f} "
                  f"{r['frame_error_max']:>8} {r['frame_error_mean']:>9.2f}")  # fmt: skip
        return {"frames": frames, "settings": rows}
    finally:
        shutil.rmtree(root, ignore_errors=True)
