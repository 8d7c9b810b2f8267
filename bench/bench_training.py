"""Training throughput: windows per second of each DIRL stage, per model profile, on this machine.

Each stage runs through the same loop iterate.py uses (batches gathered from one FrameStore of
episodes the real stack records in the simulator, Adam, gradient clipping), with the profile's
preset batch sizes, after a few warm-up steps, at 1 torch thread and at torch's default thread
count (on a small machine shared with other work, extra intra-op threads can cost more than they
give). Also timed: get_batch alone, the data ceiling of every stage; and the world model's
imagination of K action sequences per start frame with the frame encoded once against K copies
of it. (Refinement by search is a research variant: research/variants/refine_search.py.) The
cpu profile's figures are compared with BASELINE, measured before the training-speed work of
issue 13.
"""

from __future__ import annotations

import dataclasses
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

PROFILES = ("tiny", "cpu")
STEPS = {"tiny": 20, "cpu": 12}
WARMUP = 2
STAGES = ("imitation", "world_model", "refine")
# Samples/s of the cpu profile before issue 13's speed work (2026-11-22, this 2-core machine,
# 2 torch threads, same sim episodes): width 24 at 96×96, 32×32 futures, a DataLoader reading
# memory maps and resizing 10 future frames per window, imitation included.
BASELINE = {"imitation": 265.0, "world_model": 99.0}
BASELINE_BATCH = {"imitation": 64, "world_model": 16}


def record_episodes(root: Path) -> Path:
    """Expert laps and crashes, exactly as the tests' sim_episodes fixture records them."""
    from e2e_rig import record_sim_dataset

    return record_sim_dataset(root)


def _stage(name, cfg, policy, world_model, windows, free, norm):
    from training.imitation import train_imitation
    from training.refine import train_refine
    from training.world_model_stage import train_world_model

    if name == "imitation":
        return train_imitation(cfg, policy, free)
    if name == "world_model":
        return train_world_model(cfg, world_model, windows, norm, collision_weight=5.0)
    world_model.unfreeze()
    return train_refine(cfg, policy, world_model, windows, norm)


def profile_throughput(profile: str, episodes) -> dict:
    import torch

    from training.config import PRESETS, TrainingConfig
    from training.data import FrameStore, ImitationDataset, WindowDataset, compute_normalisation
    from training.models import PolicyNet, WorldModel, count_parameters

    preset = {**PRESETS[profile], "eval_every": 0}
    cfg = dataclasses.replace(TrainingConfig(profile=profile), **preset, progress=False)
    p = cfg.profile_obj
    norm = compute_normalisation(episodes)
    store = FrameStore(episodes)
    windows = WindowDataset(episodes, p.horizon, predict_size=p.predict_size, store=store)
    free = ImitationDataset(episodes, p.horizon, store=store)
    torch.manual_seed(0)
    policy, world_model = PolicyNet(p), WorldModel(p)
    policy.set_normalisation(norm)
    world_model.set_normalisation(norm)

    windows.get_batch(range(min(len(windows), 32)))  # the resized futures, built once
    start = time.perf_counter()
    n = 0
    while time.perf_counter() - start < 0.5:
        windows.get_batch(torch.randint(len(windows), (64,)).tolist())
        n += 64
    data_rate = n / (time.perf_counter() - start)

    out = {
        "policy_parameters": count_parameters(policy),
        "world_model_parameters": count_parameters(world_model),
        "data_windows_per_s": data_rate,
    }
    for stage in STAGES:
        batch = getattr(cfg, f"{stage}_batch_size")
        for steps in (WARMUP, STEPS[profile]):
            run = dataclasses.replace(cfg, **{f"{stage}_steps": steps})
            result = _stage(stage, run, policy, world_model, windows, free, norm)
        out[stage] = {
            "batch_size": batch,
            "steps": STEPS[profile],
            "samples_per_s": result.samples_per_s,
            "step_ms": 1e3 * result.seconds / STEPS[profile],
            "ratio_over_data_ceiling": result.samples_per_s / data_rate,
        }
    return out


def imagine_shared_over_copies(k: int = 8, starts: int = 32, repeats: int = 6) -> dict:
    """Imagination (cpu profile, 1 thread, no gradient): K sequences per start
    frame with the frame encoded once (WorldModel.forward) against K copies of the frame, timed
    alternately; the median of `repeats` each."""
    import torch

    from training.models import WorldModel
    from training.profiles import get_profile

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    profile = get_profile("cpu")
    world = WorldModel(profile).eval()
    g = torch.Generator().manual_seed(0)
    image = torch.randint(0, 256, (starts, 96, 96, 3), dtype=torch.uint8, generator=g)
    speed = torch.rand(starts, 1, generator=g)
    actions = torch.rand(starts * k, profile.horizon, 2, generator=g) * 2 - 1
    inputs = {"shared": (image, speed),
              "copies": (image.repeat_interleave(k, 0), speed.repeat_interleave(k, 0))}  # fmt: skip
    seconds: dict[str, list[float]] = {name: [] for name in inputs}
    with torch.no_grad():
        for _ in range(repeats):
            for name, (frames, speeds) in inputs.items():
                start = time.perf_counter()
                world.imagine(frames, speeds, actions, 5.0)
                seconds[name].append(time.perf_counter() - start)
    torch.set_num_threads(threads)
    median = {name: sorted(v)[len(v) // 2] for name, v in seconds.items()}
    return {"k": k, "starts": starts, "shared_s": median["shared"], "copies_s": median["copies"],
            "copies_over_shared": median["copies"] / median["shared"]}  # fmt: skip


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
    cpu = result[f"threads_{default_threads}"]["cpu"]
    for stage, before in BASELINE.items():
        now = cpu[stage]["samples_per_s"]
        result[f"cpu_{stage}_over_baseline"] = now / before
        print(
            f"   cpu {stage}: {now:.0f} samples/s (batch {cpu[stage]['batch_size']}) = "
            f"{now / before:.1f}x the {before:.0f} before issue 13 "
            f"(batch {BASELINE_BATCH[stage]}, {default_threads} threads)"
        )
    best = result["threads_1"]
    for stage in STAGES:
        ratio = best["tiny"][stage]["samples_per_s"] / best["cpu"][stage]["samples_per_s"]
        result[f"ratio_tiny_over_cpu_{stage}_1_thread"] = ratio
        print(f"   {stage}: tiny runs {ratio:.1f}x the samples/s of cpu (1 thread)")
    shared = result["imagine_shared"] = imagine_shared_over_copies()
    print(f"   imagination ({shared['starts']} starts x {shared['k']} sequences, cpu, "
          f"1 thread): {shared['shared_s']:.2f} s with each frame encoded once, "
          f"{shared['copies_s']:.2f} s with {shared['k']} copies: "
          f"{shared['copies_over_shared']:.2f}x")  # fmt: skip
    return result


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=2))
