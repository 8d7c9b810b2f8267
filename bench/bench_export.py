"""Exported policy: per-frame latency of onnxruntime (fp32, int8) against PyTorch eager.

Batch 1 (how the car runs it), the same thread count on both sides (torch.set_num_threads(n),
intra_op_num_threads=n, n = 1 and 2), onnxruntime with carrt's own session options (no
spinning). Needs no trained run: each profile's PolicyNet with random weights, fed frames the
simulator renders along the expert's laps (also the int8 calibration/held-out frames).
Ratio printed: eager p50 / onnxruntime p50 (target: fp32 >= 3x).
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

PROFILES = ("tiny", "cpu")
THREADS = (1, 2)
TARGET_RATIO = 3.0
FRAMES = 160


def _pct(values, q):
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def sim_frames(n: int = FRAMES):
    """Frames and speeds along the scripted expert's laps, split into two 'episodes'."""
    from carrt.sim.expert import ScriptedExpert
    from carrt.sim.render import Renderer
    from carrt.sim.world import SimWorld
    from export.parity import Frames

    world = SimWorld(layout="hard", seed=0)
    expert, renderer = ScriptedExpert(world.track, world.params), Renderer(world.track)
    images, speeds = [], []
    for _ in range(n):
        car = world.car
        images.append(renderer.render(car.x, car.y, car.yaw))
        speeds.append([car.v])
        steering, throttle = expert.act(car)
        for _ in range(20):
            info = world.step(0.005, steering, throttle)
        if info.collision:
            world.reset()
            expert.reset()
    episode = (np.arange(n) >= n // 2).astype(np.int64)
    return Frames(np.stack(images), np.array(speeds, np.float32), episode, ["a", "b"])


def _time(fn, feeds, iterations: int) -> list[float]:
    for i in range(10):
        fn(feeds[i % len(feeds)])
    out = []
    for i in range(iterations):
        start = time.perf_counter()
        fn(feeds[i % len(feeds)])
        out.append(time.perf_counter() - start)
    return out


def _session(path: Path, threads: int):
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.log_severity_level = 3
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")  # as carrt does
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def export_pair(profile: str, frames, out_dir: Path):
    """(policy, fp32 path, int8 VariantReport) through export's own checks."""
    import onnx
    import torch

    from export import graph
    from export import onnx_export as ox
    from export.quantize import Bounds, int8_variant
    from training.models import PolicyNet
    from training.profiles import get_profile

    torch.manual_seed(0)
    policy = PolicyNet(get_profile(profile)).eval()
    model, exporter = ox.torch_to_onnx(policy, frames)
    horizon = get_profile(profile).horizon
    graph.declare_outputs(model, horizon)
    fake = {"data_digest": "0" * 64, "iteration": 0, "profile": profile}
    graph.set_metadata(model, ox.build_metadata(fake, horizon, exporter))
    graph.check_structure(model, horizon)
    fp32 = out_dir / f"{profile}.onnx"
    onnx.save(model, fp32)
    int8 = int8_variant(model, frames, out_dir / f"{profile}.int8.onnx", Bounds(1.0, 2.0), horizon)
    return policy, fp32, int8, exporter


def bench_profile(profile: str, frames, out_dir: Path, iterations: int) -> dict:
    import torch

    policy, fp32, int8, exporter = export_pair(profile, frames, out_dir)
    singles = [(frames.images[i : i + 1], frames.speeds[i : i + 1]) for i in range(len(frames))]
    torch_feeds = [(torch.from_numpy(im.copy()), torch.from_numpy(sp)) for im, sp in singles]
    ort_feeds = [{"image": im, "speed": sp} for im, sp in singles]
    result: dict = {
        "profile": profile,
        "fp32_bytes": fp32.stat().st_size,
        "int8_bytes": int8.size_bytes,
        "int8_written": int8.written,
        "int8_mean_abs_mu_vs_fp32": int8.mean_abs_mu,
        "int8_max_abs_mu_vs_fp32": int8.max_abs_mu,
        "exporter": exporter,
        "threads": {},
    }
    before = torch.get_num_threads()
    for n in THREADS:
        torch.set_num_threads(n)

        def eager(feed):
            with torch.inference_mode():
                policy(*feed)

        runs = {"eager": _time(eager, torch_feeds, iterations)}
        for name, path in (("ort_fp32", fp32), ("ort_int8", int8.path if int8.written else None)):
            if path is not None:
                session = _session(path, n)
                runs[name] = _time(lambda f, s=session: s.run(None, f), ort_feeds, iterations)
        row = {}
        for name, t in runs.items():
            row[f"{name}_p50_ms"] = statistics.median(t) * 1e3
            row[f"{name}_p99_ms"] = _pct(t, 0.99) * 1e3
        for name in ("ort_fp32", "ort_int8"):
            if f"{name}_p50_ms" in row:
                row[f"ratio_eager_over_{name}"] = row["eager_p50_ms"] / row[f"{name}_p50_ms"]
        result["threads"][str(n)] = row
    torch.set_num_threads(before)
    return result


def run() -> dict:
    frames = sim_frames()
    out: dict = {"batch": 1, "frames": len(frames), "target_ratio_fp32": TARGET_RATIO}
    with tempfile.TemporaryDirectory(prefix="bench-export-") as tmp:
        for profile in PROFILES:
            iterations = 300 if profile == "tiny" else 150
            res = bench_profile(profile, frames, Path(tmp), iterations)
            out[profile] = res
            print(
                f"   {profile}: fp32 {res['fp32_bytes'] / 1e6:.2f} MB, int8 "
                f"{res['int8_bytes'] / 1e6:.2f} MB (|mu - mu_fp32| mean "
                f"{res['int8_mean_abs_mu_vs_fp32']:.4f}, max {res['int8_max_abs_mu_vs_fp32']:.4f} "
                "on held-out frames)"
            )
            for n, row in res["threads"].items():
                int8 = ""
                if "ort_int8_p50_ms" in row:
                    int8 = (
                        f", ort int8 {row['ort_int8_p50_ms']:.2f}/{row['ort_int8_p99_ms']:.2f} "
                        f"= {row['ratio_eager_over_ort_int8']:.1f}x"
                    )
                print(
                    f"     {n} thread(s), p50/p99 ms: eager {row['eager_p50_ms']:.2f}/"
                    f"{row['eager_p99_ms']:.2f}, ort fp32 {row['ort_fp32_p50_ms']:.2f}/"
                    f"{row['ort_fp32_p99_ms']:.2f} = {row['ratio_eager_over_ort_fp32']:.1f}x "
                    f"faster than eager (target {TARGET_RATIO:.0f}x){int8}"
                )
    return out
