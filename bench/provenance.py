"""Where a benchmark's or a study's numbers came from: the date, the machine, the code and the
versions of the libraries that compute them.

Why: two runs of the same study on the same seeds disagreed by more than the seeds of one run
(the σ 0 pool held 19,710 frames in one and 19,815 in another). The cause, measured 2026-11-27,
was steps the recorder dropped under load, not the libraries (the same install, recording again
on an idle machine, gave 239 of 240 episodes byte-identical); fixed in carrt/episodes/writer.py.
Library versions can still differ between installs; a results file that names what computed it
lets two runs be told apart by more than their dates.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
from importlib import metadata
from pathlib import Path

from carrt.version import code_version

# The CPU features numpy, OpenCV, OpenBLAS and torch pick their code paths by.
SIMD_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512_vnni", "asimd", "sve")

# The distributions whose arithmetic reaches a number: the simulator and data (numpy, OpenCV),
# training (torch), driving (onnxruntime), the trajectories' plots (matplotlib), the videos (av).
PACKAGES = ("numpy", "torch", "opencv-python-headless", "opencv-python", "onnxruntime",
            "onnxruntime-gpu", "onnx", "gymnasium", "pygame", "matplotlib", "av")  # fmt: skip


def package_versions() -> dict[str, str]:
    """The installed version of each of PACKAGES that is installed."""
    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return versions


def cpu(cpuinfo: str = "/proc/cpuinfo") -> dict:
    """The CPU's model name and which of SIMD_FLAGS it has (Linux; empty where unreadable)."""
    try:
        text = Path(cpuinfo).read_text()
    except OSError:
        return {}
    fields = dict(
        (key.strip(), value.strip())
        for key, _, value in (line.partition(":") for line in text.splitlines())
        if key.strip() in ("model name", "flags", "Features")
    )
    flags = set((fields.get("flags") or fields.get("Features", "")).split())
    return {"model": fields.get("model name", ""), "simd": [f for f in SIMD_FLAGS if f in flags]}


def recorded(data: str | os.PathLike) -> dict:
    """Episodes, frames and steps the recorder dropped under `data` (every meta.json below it):
    a study's data is the same from run to run only while nothing is dropped."""
    episodes = frames = dropped = 0
    for meta in sorted(Path(data).glob("**/meta.json")):
        counts = json.loads(meta.read_text()).get("counts") or {}
        episodes += 1
        frames += int(counts.get("steps", 0))
        dropped += int(counts.get("dropped", 0))
    return {"episodes": episodes, "frames": frames, "dropped": dropped}


def environment() -> dict:
    """The date (UTC), the machine, carrt's code version and the library versions."""
    return {
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu": cpu(),
        "cpus": os.cpu_count(),
        "code_version": code_version(),
        "packages": package_versions(),
    }
