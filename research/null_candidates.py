"""Null candidates: the start policy moved as far as refinement moved it, in random directions.

    python -m research.null_candidates --start RUN/dirl1/checkpoints/imitation.pt \
        --like RUN/dirl1/candidates/refine300.pt --episodes DATA/drives --count 4 --out NULL/

Why: refinement with the study's safeguards moves the policy's plan by about 1 % of the action
range (mean |Δμ| ~0.01 on recorded frames), yet on 20 validation placements its candidates'
paired scores against the policy they came from swing by ±0.1 from one candidate to the next.
Driving is chaotic: a plan that differs slightly takes a different line, meets the next
obstacle a little differently, and a lap is won or lost. Selection by driving asks a candidate
to beat its incumbent by two standard errors; whether a refined candidate that does so was
improved, or only moved, is judged against these: policies moved exactly as far with no
world model behind the direction. Drive them beside the real candidates with
`python -m research.variants.select_by_driving --candidates imitated=START NULL/null*.pt
REFINED/refine*.pt`.

Each null candidate adds to every parameter tensor (buffers excluded: BatchNorm statistics,
the normalisation) Gaussian noise in proportion to that tensor's RMS, scaled by bisection until
the mean |Δμ| over recorded frames of --episodes (export.parity.sample_frames, the frames the
export's parity check uses) equals the --like candidate's (within 2 %). OUT gets null<k>.pt
(the start checkpoint with the moved weights, loadable wherever a policy checkpoint is) and
null.json with each one's plan move (steering and throttle separately) beside the --like one's.

`--throttle-only`: one candidate instead, OUT/throttle.pt, whose plan's throttle is shifted by
as much on average (signed, mean Δ throttle over the frames and steps) as the --like
candidate's, its steering untouched: the head's pre-tanh throttle biases moved alike, no world
model behind it. Why: at σ 0.5 with a lasting-error person refinement improved driving on five
seeds and mostly raised the throttle (research/LOG.md); if this drives as well, the world
model's part in that was only "go a little faster".
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

if __package__ in (None, ""):  # run as a file, from any directory: the repository on the path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch

from carrt.errors import EXIT_USAGE, UserError
from export.parity import Frames, sample_frames, torch_outputs
from training import checkpoint as ck

FRAMES = 512  # recorded frames the plan move is measured on, spread over the episodes
TOLERANCE = 0.02  # relative agreement of the null move with the --like move


def plan(policy: torch.nn.Module, frames: Frames) -> np.ndarray:
    """μ (N, H, 2) of the policy on the frames."""
    return torch_outputs(policy, frames)[0]


def plan_move(moved: np.ndarray, start: np.ndarray) -> dict:
    """Mean |Δμ| over frames and steps: both channels, steering, throttle."""
    delta = np.abs(moved - start)
    return {
        "both": float(delta.mean()),
        "steering": float(delta[..., 0].mean()),
        "throttle": float(delta[..., 1].mean()),
    }


def perturbed(state: dict, direction: dict, scale: float) -> dict:
    return {k: v + scale * direction[k] if k in direction else v for k, v in state.items()}


def random_direction(policy: torch.nn.Module, generator: torch.Generator) -> dict:
    """Per parameter tensor: Gaussian noise times the tensor's RMS. Buffers (BatchNorm
    statistics, the normalisation) stay as they are."""
    direction = {}
    for key, value in policy.named_parameters():
        rms = value.detach().pow(2).mean().sqrt().clamp_min(1e-8)
        direction[key] = torch.randn(value.shape, generator=generator) * rms
    return direction


def throttle_direction(policy: torch.nn.Module) -> dict:
    """+1 on the pre-tanh throttle μ of every horizon step (column 1 of the head's last bias, laid
    out (H, 4): μ steering, μ throttle, σ steering, σ throttle); everything else untouched."""
    key, bias = next((k, v) for k, v in reversed(list(policy.named_parameters()))
                     if k.endswith("bias"))  # fmt: skip
    direction = torch.zeros_like(bias.detach()).view(-1, 4)
    direction[:, 1] = 1.0
    return {key: direction.view(-1)}


def throttle_shift(moved: np.ndarray, start: np.ndarray) -> float:
    """Mean signed Δ throttle over frames and steps."""
    return float((moved - start)[..., 1].mean())


def matched_scale(policy, state: dict, direction: dict, frames: Frames, start, target: float,
                  measure=lambda moved, start: plan_move(moved, start)["both"]):  # fmt: skip
    """Bisection on the scale until `measure` of the plan's move (default mean |Δμ|) reaches
    `target` > 0: (scale, the plan_move at it, `measure` at it). Leaves the policy holding
    those weights."""

    def move_at(scale: float) -> tuple[float, dict]:
        policy.load_state_dict(perturbed(state, direction, scale))
        moved = plan(policy, frames)
        return measure(moved, start), plan_move(moved, start)

    low, high = 0.0, 1e-3
    for _ in range(40):  # grow until the move overshoots
        if move_at(high)[0] >= target:
            break
        low, high = high, 2 * high
    for _ in range(40):
        mid = 0.5 * (low + high)
        value, move = move_at(mid)
        if abs(value - target) <= TOLERANCE * target:
            break
        low, high = (mid, high) if value < target else (low, mid)
    return mid, move, value


@dataclass
class Moving:
    """What both kinds of candidate start from: the start policy (its checkpoint, a copy of its
    weights), the recorded frames, and the start's and the --like candidate's plans on them."""

    policy: torch.nn.Module
    ckpt: dict
    state: dict
    frames: Frames
    start_plan: np.ndarray
    like_plan: np.ndarray


def moving(start: Path, like: Path, episodes: list[str]) -> Moving:
    """Load `start` and `like`, sample the frames once and plan both on them."""
    policy, ckpt = ck.load_policy(start)
    reference, _ = ck.load_policy(like)
    frames = sample_frames(episodes, max_frames=FRAMES)
    state = {k: v.clone() for k, v in policy.state_dict().items()}
    return Moving(policy, ckpt, state, frames, plan(policy, frames), plan(reference, frames))


def make_throttle_candidate(start: Path, like: Path, episodes: list[str], out: Path) -> dict:
    """OUT/throttle.pt: `start` with its throttle shifted as far as `like`'s, on average."""
    m = moving(start, like, episodes)
    target = throttle_shift(m.like_plan, m.start_plan)
    if not abs(target) > 0:
        raise UserError(f"{like}: its throttle equals {start}'s; nothing to match")
    sign = 1.0 if target > 0 else -1.0
    direction = {k: sign * v for k, v in throttle_direction(m.policy).items()}

    def shift(moved: np.ndarray, start_plan: np.ndarray) -> float:
        return sign * throttle_shift(moved, start_plan)

    scale, move, value = matched_scale(m.policy, m.state, direction, m.frames, m.start_plan,
                                       abs(target), shift)  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    path = out / "throttle.pt"
    ck.save_checkpoint(path, **{**m.ckpt, "policy": perturbed(m.state, direction, scale)})
    summary = {"start": str(start), "like": str(like), "frames": len(m.frames),
               "like_move": plan_move(m.like_plan, m.start_plan), "like_throttle_shift": target,
               "throttle": {"checkpoint": str(path), "scale": scale, "move": move,
                            "throttle_shift": sign * value}}  # fmt: skip
    (out / "throttle.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def make_null_candidates(start: Path, like: Path, episodes: list[str], count: int, out: Path,
                         seed: int = 0) -> dict:  # fmt: skip
    m = moving(start, like, episodes)
    target = plan_move(m.like_plan, m.start_plan)
    if not target["both"] > 0:
        raise UserError(f"{like}: its plan equals {start}'s; nothing to match")
    generator = torch.Generator().manual_seed(seed)
    out.mkdir(parents=True, exist_ok=True)
    made = []
    for k in range(count):
        direction = random_direction(m.policy, generator)
        scale, move, _ = matched_scale(m.policy, m.state, direction, m.frames, m.start_plan,
                                       target["both"])  # fmt: skip
        path = out / f"null{k}.pt"
        ck.save_checkpoint(path, **{**m.ckpt, "policy": perturbed(m.state, direction, scale)})
        made.append({"name": path.stem, "checkpoint": str(path), "scale": scale, "move": move})
    summary = {"start": str(start), "like": str(like), "like_move": target, "frames":
               len(m.frames), "seed": seed, "null": made}  # fmt: skip
    (out / "null.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m research.null_candidates", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    p.add_argument("--start", required=True, type=Path, help="the policy checkpoint to move")
    p.add_argument("--like", required=True, type=Path, help="a candidate whose move to match")
    p.add_argument("--episodes", required=True, nargs="+", help="recorded frames to measure on")
    p.add_argument("--count", type=int, default=4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, type=Path)
    p.add_argument(
        "--throttle-only",
        action="store_true",
        help="one candidate, OUT/throttle.pt: only the throttle shifted as --like's",
    )
    a = p.parse_args(argv)
    try:
        if a.count < 1:
            raise UserError(f"--count must be >= 1, got {a.count}")
        if a.throttle_only:
            summary = make_throttle_candidate(a.start, a.like, a.episodes, a.out)
            t = summary["throttle"]
            print(f"{a.like}: mean throttle shift {summary['like_throttle_shift']:+.4f}; "
                  f"{t['checkpoint']}: {t['throttle_shift']:+.4f} (|Δ steering| "
                  f"{t['move']['steering']:.4f})")  # fmt: skip
            return 0
        summary = make_null_candidates(a.start, a.like, a.episodes, a.count, a.out, a.seed)
    except UserError as exc:
        print(f"null_candidates: {exc}", file=sys.stderr)
        return EXIT_USAGE
    like = summary["like_move"]
    print(f"{a.like}: plan moved {like['both']:.4f} (steering {like['steering']:.4f}, "
          f"throttle {like['throttle']:.4f})")  # fmt: skip
    for c in summary["null"]:
        m = c["move"]
        print(f"{c['checkpoint']}: plan moved {m['both']:.4f} (steering {m['steering']:.4f}, "
              f"throttle {m['throttle']:.4f})")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
