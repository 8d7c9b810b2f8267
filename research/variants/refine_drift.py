"""Where refinement took the policy, as the world model saw it: did its uncertainty notice?

    python -m research.variants.refine_drift --run runs/refined --start runs/world-model
    python -m research.variants.refine_drift --run runs/refined --start runs/world-model \\
        --members runs/member1 runs/member2 --json drift.json

The paper's uncertainty term is there to keep refinement where the world model is right (its
Table II: without it, 32.67 interventions against 4.33). It can only do that if the world
model's uncertainty grows where refinement moves the plan. The counterfactual check
(counterfactual.py here) scores fixed perturbations of the plan; this scores the one move
that matters, the one refinement made: from the same frames, the plan of the policy refinement
started from (`--start`, a run directory) against the refined one (`--run`), how far it moved
per action channel, and what the world model imagines of each (speed, collision probability
and each uncertainty, summed over the horizon, averaged over the frames). If the refined plan
crashes more when driven but is imagined faster, as safe and no more uncertain, the world
model was wrong where refinement went and its uncertainty did not say so: there was nothing
for the uncertainty term (or its -unc ablation) to act on.

`--members`: other world models trained on the same frames (different seeds and inits). Their
disagreement about a plan (the spread over the members, the refined run's world model
included, of the imagined speed and collision probability) is the uncertainty of a deep
ensemble, which grows off the data by construction: whether it grows where refinement went is
the question the evidential uncertainty answers "no" to, asked of a different estimator.

Frames: the start states of a counterfactual set (`--data`; default the `--start` run's
counterfactual.npz, held-out placements); only their images and speeds are read, no
simulator state.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make `research` and `training` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from types import SimpleNamespace

import numpy as np
import torch

from research.variants.counterfactual import corrects, load
from training import checkpoint as ck
from training.config import UsageError

TERMS = ("speed", "p_collision", "u_image", "u_speed", "u_collision")


@torch.no_grad()
def plan(policy, image: torch.Tensor, speed: torch.Tensor) -> torch.Tensor:
    """(N, H, 2): the policy's mean plan μ from each frame (what the car executes)."""
    policy.eval()
    mu, _ = policy(image, speed)
    return mu


@torch.no_grad()
def imagined_terms(world_model, image, speed, actions, clip: float, correct: bool) -> dict:
    """Each imagined term summed over the horizon, per frame: {term: (N,)}."""
    world_model.eval()
    out = world_model.imagine(image, speed, actions, clip, correct)
    return {term: out[term].sum(dim=1) for term in TERMS}


def disagreement(runs: list[dict]) -> dict:
    """Per frame, the standard deviation over the members' `imagined_terms` of Σ speed
    (m/s·steps) and Σ p(collision): a deep ensemble's uncertainty about this plan. {} with
    fewer than 2 members."""
    if len(runs) < 2:
        return {}
    return {
        f"{term}_spread": torch.stack([r[term] for r in runs]).std(dim=0)
        for term in ("speed", "p_collision")
    }


def drift(world_model, start_policy, refined_policy, image, speed, clip: float, correct: bool,
          members: list | None = None) -> dict:  # fmt: skip
    """The start plan against the refined plan from the same frames: {"start": terms,
    "refined": terms, "change": refined − start, "moved": per channel mean and mean |Δ|},
    every number a mean over the frames; members (other world models) add their spread."""
    ensemble = [world_model, *(members or [])]
    plans = {"start": plan(start_policy, image, speed),
             "refined": plan(refined_policy, image, speed)}  # fmt: skip
    result = {}
    for name, actions in plans.items():
        runs = [imagined_terms(m, image, speed, actions, clip, correct) for m in ensemble]
        terms = runs[0] | disagreement(runs)  # the refined run's world model judges
        terms["u_total"] = terms["u_image"] + terms["u_speed"] + terms["u_collision"]
        result[name] = {k: float(v.mean()) for k, v in terms.items()}
        result[name] |= {"steering": float(actions[..., 0].mean()),
                         "throttle": float(actions[..., 1].mean())}  # fmt: skip
    result["change"] = {k: result["refined"][k] - result["start"][k] for k in result["start"]}
    delta = (plans["refined"] - plans["start"]).abs()
    result["moved"] = {"steering_abs": float(delta[..., 0].mean()),
                       "throttle_abs": float(delta[..., 1].mean())}  # fmt: skip
    result["frames"] = int(image.shape[0])
    result["members"] = len(ensemble)
    return result


def policy_before_refinement(cfg, out: Path):
    """The policy this run's refinement started from, as a loaded PolicyNet, or None: the last
    checkpoint of an earlier stage in this run (world model, else imitation: their policy is
    the one refinement took), else --init's policy.pt. Read from files, so a run resumed in
    the middle of refinement still compares against where refinement began."""
    for stage in ("world_model", "imitation"):
        path = out / "checkpoints" / f"{stage}.pt"
        if path.is_file():
            return ck.load_policy(path)[0]
    if cfg.init and (Path(cfg.init) / "policy.pt").is_file():
        return ck.load_policy(Path(cfg.init) / "policy.pt")[0]
    return None


def report_drift(cfg, out: Path, policy, world_model, windows, device, limit: int = 256):
    """For report.md: `drift` of this run's refinement on up to `limit` start frames spread
    over `windows` (a WindowDataset of the held-out episodes); None when it refined nothing or
    its start is unknown. Recorded frames only, no simulator: it works on a car's episodes."""
    from training.data import take
    from training.report_metrics import spread_indices

    if cfg.refine_steps <= 0 or len(windows) == 0:
        return None
    start = policy_before_refinement(cfg, out)
    if start is None:
        return None
    batch = take(windows, [int(i) for i in spread_indices(len(windows), limit)])
    models = [m.to(device) for m in (world_model, start, policy)]
    return drift(*models, batch["image"].to(device), batch["speed"].to(device),
                 cfg.uncertainty_clip, cfg.collision_prior_correction)  # fmt: skip


def run_paths(run: Path) -> tuple[Path, Path]:
    policy, world_model = run / "policy.pt", run / "world_model.pt"
    for path in (policy, world_model):
        if not path.is_file():
            raise UsageError(f"{path}: no such file (a run directory)")
    return policy, world_model


def frames_from(path: Path) -> tuple[torch.Tensor, torch.Tensor]:
    """(images (N, 96, 96, 3) uint8, speeds (N, 1)) of a counterfactual set; anything else,
    or a speed that is not finite, is refused in one line."""
    if not path.is_file():
        raise UsageError(f"{path}: no such file (a counterfactual set)")
    try:
        frames = load(path)
        image, speed = frames["image"], np.asarray(frames["speed"], np.float32).reshape(-1, 1)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise UsageError(f"{path}: not a counterfactual set ({exc})") from None
    if image.ndim != 4 or image.dtype != np.uint8 or len(image) != len(speed) or not len(image):
        raise UsageError(f"{path}: images {image.shape} {image.dtype}, {len(speed)} speeds")
    if not np.isfinite(speed).all():
        raise UsageError(f"{path}: a speed is not finite")
    return torch.from_numpy(image), torch.from_numpy(speed)


def check(run: Path, start: Path, data: Path | None, members: list[Path]) -> dict:
    """Load the runs and the frames, then `drift`; the refined run's world model judges."""
    policy_path, wm_path = run_paths(run)
    start_policy_path, _ = run_paths(start)
    data = data or start / "counterfactual.npz"
    image, speed = frames_from(data)
    world_model, ckpt = ck.load_world_model(wm_path)
    cfg = SimpleNamespace(**ckpt["config"])
    others = [ck.load_world_model(run_paths(m)[1])[0] for m in members]
    result = drift(world_model, ck.load_policy(start_policy_path)[0],
                   ck.load_policy(policy_path)[0], image, speed, cfg.uncertainty_clip,
                   corrects(cfg), others)  # fmt: skip
    result |= {"run_dir": str(run), "start_dir": str(start), "data": str(data)}
    return result


def describe(result: dict) -> str:
    moved, change = result["moved"], result["change"]
    spread = ""
    if "speed_spread" in change:
        spread = (f"; members' spread of Σ speed {result['start']['speed_spread']:.2f} → "
                  f"{result['refined']['speed_spread']:.2f}, of Σ p(collision) "
                  f"{result['start']['p_collision_spread']:.3f} → "
                  f"{result['refined']['p_collision_spread']:.3f}")  # fmt: skip
    return (
        f"plan moved |Δsteering| {moved['steering_abs']:.3f}, |Δthrottle| "
        f"{moved['throttle_abs']:.3f} (mean steering {result['start']['steering']:+.2f} → "
        f"{result['refined']['steering']:+.2f}, throttle {result['start']['throttle']:+.2f} → "
        f"{result['refined']['throttle']:+.2f}); imagined Σ speed {change['speed']:+.2f}, "
        f"Σ p(collision) {change['p_collision']:+.3f}, Σ uncertainty {change['u_total']:+.2f} "
        f"(of {result['start']['u_total']:.2f}){spread}; {result['frames']} frames, "
        f"{result['members']} world model(s)"
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m research.variants.refine_drift",
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    p.add_argument("--run", required=True, help="the refined run (policy.pt, world_model.pt)")
    p.add_argument("--start", required=True, help="the run whose policy refinement started from")
    p.add_argument("--data", help="a counterfactual .npz (default START/counterfactual.npz)")
    p.add_argument("--members", nargs="*", default=[], help="other world models' run directories")
    p.add_argument("--json", help="write the numbers here")
    a = p.parse_args(argv)
    try:
        result = check(Path(a.run), Path(a.start), Path(a.data) if a.data else None,
                       [Path(m) for m in a.members])  # fmt: skip
    except (UsageError, ck.CheckpointError) as exc:
        print(f"python -m research.variants.refine_drift: error: {exc}", file=sys.stderr)
        return 2
    print(describe(result))
    if a.json:
        Path(a.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
