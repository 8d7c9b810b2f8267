"""Training throughput: windows per second of each DIRL stage, per model profile, on this machine.

Each stage runs through the same loop iterate.py uses (batches from WindowDataset over episodes
the real stack records in the simulator, Adam, gradient clipping), with the profile's preset
batch sizes, after a few warm-up steps, at 1 torch thread and at torch's default thread count
(on a small machine shared with other work, extra intra-op threads can cost more than they
give). Also timed: WindowDataset alone (reading + resizing the future frames), the ceiling for
every stage without DataLoader workers. Ratios printed: each stage's samples/s against the data
ceiling, and the cpu profile's cost against tiny's.
"""

from __future__ import annotations

import dataclasses
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

PROFILES = ("tiny", "cpu")
STEPS = {"tiny": 20, "cpu": 6}
WARMUP = 2
STAGES = ("imitation", "world_model", "refine")


def record_episodes(root: Path) -> Path:
    """Expert laps and crashes, exactly as the tests' sim_episodes fixture records them."""
    from e2e_rig import record_sim_dataset

    return record_sim_dataset(root)


def _stage(name, cfg, policy, world_model, windows, free, norm):
    from training.imitation import train_imitation
    from training.refine import train_refine
    from training.world_training import train_world_model

    if name == "imitation":
        return train_imitation(cfg, policy, free)
    if name == "world_model":
        return train_world_model(cfg, world_model, windows, norm, collision_weight=5.0)
    world_model.unfreeze()
    return train_refine(cfg, policy, world_model, windows, norm)


def profile_throughput(profile: str, episodes) -> dict:
    import torch

    from training.data import WindowDataset, compute_normalisation
    from training.iterate import PRESETS, IterateConfig
    from training.models import PolicyNet, WorldModel, count_parameters

    cfg = dataclasses.replace(IterateConfig(profile=profile), **PRESETS[profile], progress=False)
    p = cfg.profile_obj
    norm = compute_normalisation(episodes)
    windows = WindowDataset(episodes, p.horizon, predict_size=p.predict_size)
    free = WindowDataset(episodes, p.horizon, predict_size=p.predict_size, collision_free_only=True)
    torch.manual_seed(0)
    policy, world_model = PolicyNet(p), WorldModel(p)
    policy.set_normalisation(norm)
    world_model.set_normalisation(norm)

    start = time.perf_counter()
    n = min(len(windows), 200)
    for i in range(n):
        windows[i]
    data_rate = n / (time.perf_counter() - start)

    out = {
        "policy_parameters": count_parameters(policy),
        "world_model_parameters": count_parameters(world_model),
        "data_windows_per_s": data_rate,
    }
    for stage in STAGES:
        prefix = {"imitation": "imitation", "world_model": "world_model", "refine": "refine"}[stage]
        batch = getattr(cfg, f"{prefix}_batch_size")
        for steps in (WARMUP, STEPS[profile]):
            run = dataclasses.replace(cfg, **{f"{prefix}_steps": steps})
            result = _stage(stage, run, policy, world_model, windows, free, norm)
        out[stage] = {
            "batch_size": batch,
            "steps": STEPS[profile],
            "samples_per_s": result.samples_per_s,
            "step_ms": 1e3 * result.seconds / STEPS[profile],
            "ratio_over_data_ceiling": result.samples_per_s / data_rate,
        }
    return out


def run() -> dict:
    import torch

    from training.data import load_episodes

    default_threads = torch.get_num_threads()
    thread_counts = sorted({1, default_threads})
    with tempfile.TemporaryDirectory(prefix="carrt-bench-training-") as tmp:
        episodes = load_episodes([record_episodes(Path(tmp))])
        frames = sum(ep.n for ep in episodes)
        result: dict = {"episodes": len(episodes), "frames": frames}
        for n in thread_counts:
            torch.set_num_threads(n)
            result[f"threads_{n}"] = {p: profile_throughput(p, episodes) for p in PROFILES}
        torch.set_num_threads(default_threads)
    print(f"   {len(episodes)} sim episodes, {frames} frames")
    for n in thread_counts:
        for profile in PROFILES:
            r = result[f"threads_{n}"][profile]
            print(
                f"   {profile} profile, {n} torch thread(s) (policy {r['policy_parameters']:,} "
                f"params, world model {r['world_model_parameters']:,}); data ceiling "
                f"{r['data_windows_per_s']:.0f} windows/s"
            )
            for stage in STAGES:
                s = r[stage]
                print(
                    f"     {stage:12s} batch {s['batch_size']:3d}: {s['samples_per_s']:7.1f} "
                    f"samples/s ({s['step_ms']:.0f} ms/step) = "
                    f"{s['ratio_over_data_ceiling']:.2f} of the data ceiling"
                )
    best = result["threads_1"]
    for stage in STAGES:
        ratio = best["tiny"][stage]["samples_per_s"] / best["cpu"][stage]["samples_per_s"]
        result[f"ratio_tiny_over_cpu_{stage}_1_thread"] = ratio
        print(f"   {stage}: tiny runs {ratio:.1f}x the samples/s of cpu (1 thread)")
    return result


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=2))
