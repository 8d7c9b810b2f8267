"""`carrt episodes replay`: a policy over what you drove, against the person, before it drives.

On a real car the only way to see what a new policy would do is to let it drive. This puts
every recorded frame through each model as the car runs it instead: the stored 96×96 crop (the
loop records the preprocessed image, so this is the frame the policy would have seen) and the
measured speed go into OnnxPolicy (the same model contract, providers and clipping), and the
plan's first step is the action it would have sent (PlanBuffer.fresh). Beside it the person's
a* and the executed action. Scored against the person only where the person drove (MANUAL, a
take-over included): in AUTO the sticks rest at neutral and are no label. Steps the person
excluded (`carrt episodes mark`) are left out, as training leaves them out.

What it cannot say: how the policy would have driven from the states its own actions lead to
(the frames are those of the drive that happened), so a small error here is necessary for a
good drive, not sufficient (DonkeyCar's "pilot arena" has the same limit).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from carrt.episodes.marks import read_marks
from carrt.episodes.reader import Episode, collision_events, list_episodes, read_episode
from carrt.errors import UserError
from carrt.interfaces import Mode

TOLERANCE = 0.1  # an action within this of the person's (each of steering, throttle) agrees
BEFORE_COLLISION_S = 2.0  # what the policy would have done in the seconds before a collision
WORST = 3  # the steps where each policy would have differed most, per episode


@dataclass
class Replayed:
    """One episode through the models: per step the person's, the executed and each model's
    action, which steps are scored against the person, and the capture times."""

    episode: Episode
    t: np.ndarray  # s from the episode's first step
    person: np.ndarray  # (N, 2)
    executed: np.ndarray  # (N, 2)
    actions: dict[str, np.ndarray]  # model name → (N, 2)
    scored: np.ndarray  # bool (N,): the person drove and the step is not excluded


def model_actions(policy: Any, episode: Episode) -> np.ndarray:
    """The action `policy` (an OnnxPolicy) would have sent at each step of `episode`."""
    from carrt.plan import PlanBuffer

    plans = PlanBuffer()
    out = np.empty((episode.n, 2), dtype=np.float32)
    speeds = episode.steps["speed_mps"]
    for i in range(episode.n):
        out[i] = plans.fresh(policy.predict(np.asarray(episode.frames[i]), float(speeds[i])))
    return out


def replay(episode: Episode, policies: dict[str, Any]) -> Replayed:
    steps = episode.steps
    t = episode.timestamps.astype(np.float64)
    t = t - t[0] if len(t) else t
    excluded = read_marks(episode.path).excluded(episode.timestamps)
    return Replayed(
        episode=episode,
        t=t,
        person=steps["human_action"].astype(np.float32),
        executed=steps["executed_action"].astype(np.float32),
        actions={name: model_actions(p, episode) for name, p in policies.items()},
        scored=(steps["mode"] == Mode.MANUAL) & ~excluded,
    )


def score(person: np.ndarray, action: np.ndarray, tolerance: float = TOLERANCE) -> dict:
    """Mean absolute error and the share within `tolerance`, for steering and throttle."""
    if len(person) == 0:
        return {"steps": 0, "steering_mae": None, "throttle_mae": None,
                "steering_within": None, "throttle_within": None}  # fmt: skip
    err = np.abs(action - person)
    return {
        "steps": len(person),
        "steering_mae": float(err[:, 0].mean()),
        "throttle_mae": float(err[:, 1].mean()),
        "steering_within": float((err[:, 0] <= tolerance).mean()),
        "throttle_within": float((err[:, 1] <= tolerance).mean()),
    }


def episode_report(r: Replayed, tolerance: float = TOLERANCE) -> dict:
    ep, on = r.episode, r.scored
    models: dict[str, Any] = {}
    for name, action in r.actions.items():
        err = np.abs(action - r.person).sum(axis=1)
        err[~on] = -1.0
        worst = [int(i) for i in np.argsort(-err)[:WORST] if err[i] >= 0]
        before = []
        for k in collision_events(ep.steps, (ep.meta.get("end") or {}).get("reason")):
            window = (r.t > r.t[k] - BEFORE_COLLISION_S) & (r.t <= r.t[k])
            before.append({
                "step": int(k), "t_s": float(r.t[k]),
                "policy": action[window].mean(axis=0).round(3).tolist(),
                "executed": r.executed[window].mean(axis=0).round(3).tolist(),
            })  # fmt: skip
        models[name] = {
            **score(r.person[on], action[on], tolerance),
            "differed_most": [_at(r, action, i) for i in worst],
            "before_collisions": before,
        }
    return {"episode": ep.name, "frames": ep.n, "scored_steps": int(on.sum()), "models": models}


def _at(r: Replayed, action: np.ndarray, i: int) -> dict:
    return {"step": i, "t_s": float(r.t[i]), "policy": action[i].round(3).tolist(),
            "person": r.person[i].round(3).tolist()}  # fmt: skip


def overall(replays: list[Replayed], tolerance: float = TOLERANCE) -> dict[str, dict]:
    names = list(replays[0].actions) if replays else []
    out = {}
    for name in names:
        person = np.concatenate([r.person[r.scored] for r in replays])
        action = np.concatenate([r.actions[name][r.scored] for r in replays])
        out[name] = score(person, action, tolerance)
    return out


def _pair(action: list[float]) -> str:
    return f"steering {action[0]:+.2f} throttle {action[1]:+.2f}"


def _pct(v: float | None) -> str:
    return "-" if v is None else f"{100 * v:.0f}%"


def _num(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f}"


def render(episodes: list[dict], total: dict[str, dict], tolerance: float) -> str:
    lines = [f"{'episode':<24} {'model':<22} {'steps':>6} {'steer MAE':>9} {'thr MAE':>8} "
             f"{'steer ≤' + str(tolerance):>10} {'thr ≤' + str(tolerance):>9}"]  # fmt: skip
    rows = [(e["episode"], e["models"]) for e in episodes] + [("all", total)]
    for ep_name, models in rows:
        for name, m in models.items():
            lines.append(
                f"{ep_name:<24} {name:<22} {m['steps']:>6} {_num(m['steering_mae']):>9} "
                f"{_num(m['throttle_mae']):>8} {_pct(m['steering_within']):>10} "
                f"{_pct(m['throttle_within']):>9}"
            )
    for e in episodes:
        for name, m in e["models"].items():
            for w in m["differed_most"]:
                lines.append(
                    f"{e['episode']} {name}: differed most at {w['t_s']:.1f} s (step "
                    f"{w['step']}): {_pair(w['policy'])} where the person {_pair(w['person'])}"
                )
            for c in m["before_collisions"]:
                lines.append(
                    f"{e['episode']} {name}: in the {BEFORE_COLLISION_S:g} s before the collision "
                    f"at {c['t_s']:.1f} s it would have sent {_pair(c['policy'])} on average "
                    f"(executed {_pair(c['executed'])})"
                )
    return "\n".join(lines)


def plot(replays: list[Replayed], out: Path) -> None:
    """Steering and throttle over time per episode: the person, the executed, each model."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(replays), 2, figsize=(12, 2.6 * len(replays)), squeeze=False)
    for row, r in zip(axes, replays, strict=True):
        for col, label in enumerate(("steering", "throttle")):
            ax = row[col]
            ax.plot(r.t, r.person[:, col], color="black", lw=1.2, label="person a*")
            ax.plot(r.t, r.executed[:, col], color="grey", lw=0.8, ls="--", label="executed")
            for name, action in r.actions.items():
                ax.plot(r.t, action[:, col], lw=1.0, label=name)
            ax.set_title(f"{r.episode.name}: {label}", fontsize=9)
            ax.set_ylim(-1.05, 1.05)
        row[0].legend(fontsize=7, loc="lower left")
    fig.supxlabel("s")
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay",
        help="every recorded frame through one or two policies, against the person's actions",
        description="Run each policy over recorded episodes as the car would have (same crop, "
        "speed and model contract) and compare its action with the person's a* where the "
        "person drove: mean absolute error, share within a tolerance, where it differed most, "
        "and what it would have done before each collision.",
        epilog="example: carrt episodes replay episodes/ --model runs/iter1/policy.onnx "
        "--model demo --plot replay.png",
    )
    p.add_argument("episode", metavar="EP", nargs="+", help="episodes, or folders of them")
    p.add_argument("--model", action="append", required=True, metavar="M.onnx",
                   help="a policy (.onnx, or demo); give it twice to compare two")  # fmt: skip
    p.add_argument("--tolerance", type=float, default=TOLERANCE,
                   help=f"agreement within this, per action (default {TOLERANCE})")  # fmt: skip
    p.add_argument("--plot", metavar="PNG", help="also draw the actions over time")
    p.add_argument("--json", metavar="OUT", help="also write the numbers as JSON")


def run_replay(args: argparse.Namespace) -> int:
    from carrt.policy import OnnxPolicy

    if not (np.isfinite(args.tolerance) and args.tolerance > 0):
        raise UserError(f"--tolerance: expected a number > 0, got {args.tolerance}")
    policies = {}
    for model in args.model:
        policy = OnnxPolicy(model)  # refused as the car would refuse it
        name = policy.path.name if policy.path.name not in policies else str(policy.path)
        policies[name] = policy
    episodes = [read_episode(p) for p in list_episodes(args.episode)]
    start = time.perf_counter()
    replays = [replay(ep, policies) for ep in episodes if ep.n]
    seconds = time.perf_counter() - start
    if not replays:
        raise UserError("no recorded steps in the episodes given")
    reports = [episode_report(r, args.tolerance) for r in replays]
    total = overall(replays, args.tolerance)
    print(render(reports, total, args.tolerance))
    frames = sum(r.episode.n for r in replays) * len(policies)
    print(f"replayed {frames} frames in {seconds:.1f} s ({frames / max(seconds, 1e-9):.0f} / s)")
    if args.plot:
        plot(replays, Path(args.plot))
        print(f"plot written to {args.plot}")
    if args.json:
        Path(args.json).write_text(json.dumps({"episodes": reports, "all": total}, indent=2))
        print(f"numbers written to {args.json}")
    return 0
