"""Does the world model know what actions do? Its imagination scored against the simulator's truth.

    python -m research.variants.counterfactual --run runs/iter1                 # tracks 200-204
    python -m research.variants.counterfactual --run runs/iter1 --data cf.npz   # a set made before

Refinement improves the policy only as far as the world model ranks action sequences the way
reality would. Losses on recorded windows cannot show that: the recordings hold the actions a
demonstrator took, not the ones refinement will try. So, in the simulator only (training never
sees simulator state), `carrt.sim.counterfactual` replays several action sequences from the same
held-out start states and records what each really did; here the world model imagines the same
sequences from the same frame and speed, and three numbers say how far to trust it:

  collision AUROC   over every (collides, does not) pair of sequences FROM THE SAME START, how
                    often the colliding one gets the higher imagined risk (max over the horizon
                    of p̂(collision)); 0.5 is a model that ignores the actions
  speed error       mean |imagined − true| m/s over the steps before any collision, next to the
                    constant-speed baseline (the start speed held): a useful model is below it
  rank correlation  Spearman's ρ, per start, between the imagined refinement objective
                    (training/refine.refine_objective, uncertainty term included) and the true
                    one (−w_spd·speed + w_coll·collision per step, speed 0 after a collision),
                    averaged over starts

and two that say what refinement itself can use, since it moves the plan by small steps and
ρ over nine sequences is earned mostly on the far ones: per sequence, how often the imagined
objective orders it against the plan as reality does; and the gradient agreement, how often
the objective's gradient at the plan points the way the true difference across it does.

The set is generated in a separate process: the simulator and torch in one process have
crashed with heap corruption here (see docs/architecture.md), and the generator needs neither
torch nor the world model, only the policy's ONNX file for its plans.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make `research` and `training` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from types import SimpleNamespace

import numpy as np
import torch

from carrt.policy import file_sha256
from research.variants.refine_search import SEARCH_SEQUENCES, best_moves
from training import checkpoint as ck
from training.refine import sequence_objective, uncertainty_weight
from training.report_metrics import auroc, spearman

TARGETS = {"collision_auroc": 0.85, "rank_correlation": 0.5}  # issue 14's bar for trusting it


def generate(model_onnx: Path, out: Path, layout: str, tracks: str, starts: int, seed: int) -> None:
    """The simulator's ground truth, in its own process (python -m carrt.sim.counterfactual)."""
    argv = [sys.executable, "-m", "carrt.sim.counterfactual", "--model", str(model_onnx),
            "--layout", layout, "--tracks", tracks, "--starts", str(starts), "--seed", str(seed),
            "--out", str(out)]  # fmt: skip
    done = subprocess.run(argv, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"counterfactual: generating {out} failed: {done.stderr.strip()}")


def load(path: str | Path) -> dict[str, np.ndarray]:
    with np.load(path) as data:
        out = {k: data[k] for k in data.files}
    out["meta"] = json.loads(str(out["meta"]))
    return out


def within_start_auroc(scores: np.ndarray, labels: np.ndarray) -> tuple[float, int]:
    """AUROC over (positive, negative) pairs that share a start; (nan, 0) with no such pair.

    Each start's AUROC weighted by its number of pairs: only comparisons between sequences
    from the same frame count, so a model cannot score by knowing which places are risky."""
    wins = pairs = 0.0
    for s, y in zip(scores, labels, strict=True):
        n_pos = int((y > 0).sum())
        n = n_pos * (len(y) - n_pos)
        if n:
            wins += auroc(s, y > 0) * n
            pairs += n
    return (wins / pairs if pairs else float("nan")), int(pairs)


def true_objective(data: dict, w_speed: float, w_collision: float) -> np.ndarray:
    """(N, K): Σ_t −w_spd·v_t + w_coll·c_t, with the car standing (v = 0) after a collision."""
    speed = data["true_speed"] * data["mask"]
    return (-w_speed * speed + w_collision * data["true_collision"]).sum(axis=2)


@torch.no_grad()
def score(world_model, data: dict, cfg) -> dict:
    """The three numbers (and their parts) for one world model on one counterfactual set; cfg:
    the refinement weights (an TrainingConfig, or its fields), -unc's zero included."""
    # No normalisation argument: the world model carries its own (WorldModel.imagine).
    world_model.eval()
    n, k, h, _ = data["actions"].shape
    if h != world_model.horizon:
        raise SystemExit(
            f"counterfactual: horizon {h} in the set, {world_model.horizon} in the model"
        )
    weights = (cfg.refine_w_speed, cfg.refine_w_collision, uncertainty_weight(cfg))
    imagined_speed, risk, objective = np.zeros((n, k, h)), np.zeros((n, k)), np.zeros((n, k))
    terms = {name: np.zeros((n, k)) for name in ("speed", "collision", "uncertainty")}
    for i in range(n):
        image = torch.from_numpy(data["image"][i : i + 1])  # encoded once for the k sequences
        speed = torch.full((1, 1), float(data["speed"][i]))
        actions = torch.from_numpy(data["actions"][i])
        out = world_model.imagine(image, speed, actions, cfg.uncertainty_clip, corrects(cfg))
        imagined_speed[i] = out["speed"].numpy()
        # a model that says the chance of a crash within the horizon is scored by it; the
        # Reveries-net's per-step p̂ by its highest step
        risk[i] = (
            out["p_crash"] if "p_crash" in out else out["p_collision"].max(dim=1).values
        ).numpy()
        objective[i] = sequence_objective(out, *weights).numpy()
        for name, term_weights in (("speed", (weights[0], 0.0, 0.0)),
                                   ("collision", (0.0, weights[1], 0.0)),
                                   ("uncertainty", (0.0, 0.0, weights[2]))):  # fmt: skip
            terms[name][i] = sequence_objective(out, *term_weights).numpy()
    collided = data["true_collision"].max(axis=2)
    auroc, pairs = within_start_auroc(risk, collided)
    # speed: steps before the first collision (the collision step's speed is the crash's)
    before = (data["mask"] > 0) & (np.cumsum(data["true_collision"], axis=2) == 0)
    true_speed = data["true_speed"]
    baseline = np.broadcast_to(data["speed"][:, None, None], true_speed.shape)
    truth = true_objective(data, cfg.refine_w_speed, cfg.refine_w_collision)
    true_distance = (true_speed * data["mask"]).sum(axis=2)
    return {
        "starts": int(n),
        "sequences_per_start": int(k),
        "collision_rate": float(collided.mean()),
        "collision_auroc": auroc,
        "auroc_pairs": pairs,
        "speed_mae": float(np.abs(imagined_speed - true_speed)[before].mean()),
        "speed_mae_constant": float(np.abs(baseline - true_speed)[before].mean()),
        "rank_correlation": rank_correlation(objective, truth),
        # Which term of the imagined objective ranks the sequences right or wrong, alone, and
        # how the true objective itself splits: its ranking by the true speed term alone.
        "rank_correlation_terms": {
            name: rank_correlation(term, truth) for name, term in terms.items()
        },
        "rank_correlation_true_speed_term": rank_correlation(-true_distance, truth),
        "imagined_vs_true_distance": rank_correlation(imagined_speed.sum(axis=2), true_distance),
        # Per kind of sequence (named in the set's meta, so this torch process never imports the
        # simulator), over the starts: what happened and what the world model imagined. A head
        # blind to steering shows here as the same imagined risk for a steering shift that truly
        # crashes as for the plan.
        "by_sequence": {
            name: {
                "true_distance": float(true_distance[:, j].mean()),
                "imagined_distance": float(imagined_speed[:, j].sum(axis=1).mean()),
                "true_collision": float(collided[:, j].mean()),
                "imagined_risk": float(risk[:, j].mean()),
                # null for the plan itself and where the truth ties (JSON has no NaN)
                "orders_like_truth": finite_or_none(orders_like_truth(objective, truth, j)),
                # Mean over the starts of each imagined term (weighted, as in the objective)
                # minus the plan's, and the same of the true objective (lower is better): which
                # term makes a sequence look worse or better than the plan than it truly is.
                "vs_plan": {
                    **{term: float((v[:, j] - v[:, 0]).mean()) for term, v in terms.items()},
                    "true": float((truth[:, j] - truth[:, 0]).mean()),
                },
            }
            for j, name in enumerate(data["meta"].get("sequences", ()))
        },
        "gradient_agreement": gradient_agreement(world_model, data, cfg, weights, truth),
        "search": search_check(objective, truth, list(data["meta"].get("sequences", ()))),
        # The same search with the uncertainty term left out (-unc's objective): whether the
        # paper's safety term steers the choice toward or away from what truly drives better.
        "search_without_uncertainty": search_check(
            objective - terms["uncertainty"], truth, list(data["meta"].get("sequences", ()))
        ),
        "plan_is_best_imagined": float(np.mean(objective.argmin(axis=1) == 0)),
        "plan_is_best_true": float(np.mean(truth.argmin(axis=1) == 0)),
    }


def corrects(cfg) -> bool:
    """The run's collision_prior_correction; a config from before the field existed has a
    world model with weight 1, for which it changes nothing."""
    return getattr(cfg, "collision_prior_correction", True)


def orders_like_truth(imagined: np.ndarray, real: np.ndarray, j: int) -> float:
    """Share of starts where the imagined objective says sequence j is better or worse than the
    plan (sequence 0) as the true one does (ties in the truth left out; NaN with none left).

    Why beside ρ: ρ over nine sequences is earned mostly on the far ones (brake, ±0.6 steering
    into a crash); refinement follows the gradient at the plan, so what it needs is the order
    of the plan and its near neighbours (±0.3 steering, full throttle)."""
    return sign_agreement(imagined[:, j] - imagined[:, 0], real[:, j] - real[:, 0])


def sign_agreement(imagined: np.ndarray, true: np.ndarray) -> float:
    """Share of entries where `imagined` has the sign of `true`, true ties (|·| ≤ 1e-6) left
    out; NaN with none left."""
    decided = np.abs(true) > 1e-6
    if not decided.any():
        return float("nan")
    return float(np.mean(np.sign(true[decided]) == np.sign(imagined[decided])))


# Each action channel's truth at the plan, as a difference of two sequences of the set that
# move only that channel: steering +0.3 against −0.3, full throttle against none.
GRADIENT_PAIRS = {"steering": ("steer+0.3", "steer-0.3"), "throttle": ("full", "lift")}


def gradient_agreement(world_model, data: dict, cfg, weights: tuple, truth: np.ndarray) -> dict:
    """How often the imagined objective's gradient at the plan (summed over the horizon, per
    action channel) has the sign of the true objective's difference across the plan: the
    direction refinement follows, scored against reality. "_centred" subtracts the mean over
    the starts from both, as `refine_center_gradient` does. 0.5 is a coin; {} without the
    named sequences. `truth`: true_objective of the set, (N, K)."""
    names = list(data["meta"].get("sequences", ()))
    if not all(n in names for pair in GRADIENT_PAIRS.values() for n in pair):
        return {}
    grads = np.zeros((len(truth), 2))
    for i in range(len(truth)):
        plan = torch.from_numpy(data["actions"][i, :1]).clone().requires_grad_(True)
        with torch.enable_grad():
            out = world_model.imagine(
                torch.from_numpy(data["image"][i : i + 1]),
                torch.full((1, 1), float(data["speed"][i])),
                plan, cfg.uncertainty_clip, corrects(cfg),
            )  # fmt: skip
            (grad,) = torch.autograd.grad(sequence_objective(out, *weights).sum(), plan)
        grads[i] = grad[0].sum(dim=0).numpy()
    result = {}
    for c, (channel, (up, down)) in enumerate(GRADIENT_PAIRS.items()):
        diff, grad = truth[:, names.index(up)] - truth[:, names.index(down)], grads[:, c]
        for suffix, g, d in (("", grad, diff),
                             ("_centred", grad - grad.mean(), diff - diff.mean())):  # fmt: skip
            result[channel + suffix] = finite_or_none(sign_agreement(g, d))
    return result


SEARCH_MARGINS = (0.0, 0.5, 1.0, 2.0)


def search_check(imagined: np.ndarray, truth: np.ndarray, names: list[str]) -> dict:
    """What `refine_search` would do from these starts, scored against reality, per margin:
    the share of starts it moves (`moves`), the share of those moves that truly beat the plan
    (`right`, 0.5 a coin), and the true gain per start, moves and stays together
    (`true_gain`: the plan's true objective less the chosen one's; the oracle's is the most
    any choice could gain). {} without the search's sequences in the set."""
    if not all(name in names for name in SEARCH_SEQUENCES):
        return {}
    cols = [names.index(name) for name in SEARCH_SEQUENCES]
    real = truth[:, cols]
    scores = torch.from_numpy(imagined[:, cols])
    picks = {margin: best_moves(scores, margin).numpy() for margin in SEARCH_MARGINS}
    result = {
        "oracle_true_gain": float((real[:, 0] - real.min(axis=1)).mean()),
        # what it picks (margin 0) and what would have been right, as shares of the starts
        "chosen": shares(picks[0.0]),
        "truly_best": shares(real.argmin(axis=1)),
    }
    for margin, chosen in picks.items():
        gain = real[:, 0] - real[np.arange(len(real)), chosen]
        moved = chosen > 0
        result[f"margin_{margin:g}"] = {
            "moves": float(moved.mean()),
            "right": finite_or_none(float((gain[moved] > 0).mean()) if moved.any() else np.nan),
            "true_gain": float(gain.mean()),
        }
    return result


def shares(columns: np.ndarray) -> dict[str, float]:
    """(N,) columns of SEARCH_SEQUENCES → the share of starts at each name (those with any)."""
    names, counts = np.unique(columns, return_counts=True)
    return {SEARCH_SEQUENCES[int(c)]: n / len(columns) for c, n in zip(names, counts, strict=True)}


def finite_or_none(value: float) -> float | None:
    return value if np.isfinite(value) else None


def rank_correlation(imagined: np.ndarray, real: np.ndarray) -> float:
    """Spearman's ρ between (N, K) scores within each start, averaged over the starts that
    have one (NaN where a start's sequences all score the same)."""
    values = [spearman(a, b) for a, b in zip(imagined, real, strict=True)]
    return float(np.nanmean(values)) if np.isfinite(values).any() else float("nan")


def check_run(run: Path, data_path: Path | None, layout: str, tracks: str, starts: int) -> dict:
    """Generate (unless given) the set from the run's policy, then score its world model."""
    wm_path = run / "world_model.pt"
    if not wm_path.is_file():
        raise SystemExit(f"counterfactual: {wm_path}: no such file (a run with a world model)")
    if data_path is None:  # made from this run's policy; remade when the policy changed
        data_path, onnx = run / "counterfactual.npz", run / "policy.onnx"
        if not data_path.is_file() or load(data_path)["meta"]["model_sha256"] != file_sha256(onnx):
            generate(onnx, data_path, layout, tracks, starts, seed=0)
    world_model, ckpt = ck.load_world_model(wm_path)
    cfg = SimpleNamespace(**ckpt["config"])  # the run's ResearchConfig, as its checkpoint saved it
    result = score(world_model, load(data_path), cfg)
    result["data"] = str(data_path)
    return result


def describe(result: dict) -> str:
    return (
        f"collision AUROC {result['collision_auroc']:.3f} over {result['auroc_pairs']} pairs "
        f"(target ≥ {TARGETS['collision_auroc']}); speed MAE {result['speed_mae']:.3f} m/s "
        f"(constant-speed {result['speed_mae_constant']:.3f}); rank correlation "
        f"{result['rank_correlation']:.3f} (target ≥ {TARGETS['rank_correlation']}); "
        f"{result['starts']} starts × {result['sequences_per_start']} sequences, "
        f"{result['collision_rate']:.0%} collide"
    )


def by_sequence_table(result: dict) -> list[str]:
    """Markdown: per kind of sequence, true against imagined distance and collision."""
    rows = result.get("by_sequence") or {}
    if not rows:
        return []
    lines = ["| sequence | true Σ speed | imagined Σ speed | collided | imagined risk | "
             "ordered against the plan as in truth | − plan: imagined speed / collision / "
             "uncertainty terms | − plan: true objective |",
             "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for name, r in rows.items():
        order = r.get("orders_like_truth")  # absent in results from before it
        d = r.get("vs_plan")  # absent in results from before it
        parts = ("— | —" if d is None else f"{d['speed']:+.2f} / {d['collision']:+.2f} / "
                 f"{d['uncertainty']:+.2f} | {d['true']:+.2f}")  # fmt: skip
        lines.append(
            f"| {name} | {r['true_distance']:.2f} | {r['imagined_distance']:.2f} | "
            f"{r['true_collision']:.2f} | {r['imagined_risk']:.2f} | "
            f"{'—' if order is None else f'{order:.2f}'} | {parts} |"
        )
    grads = result.get("gradient_agreement") or {}  # absent in results from before it
    if grads:
        shown = ", ".join(f"{k} {'—' if v is None else f'{v:.2f}'}" for k, v in grads.items())
        lines += ["", f"Gradient at the plan with the sign of the true difference (0.5 = a coin): "
                  f"{shown}."]  # fmt: skip
    lines += search_lines(result.get("search") or {})  # absent in results from before it
    lines += search_lines(result.get("search_without_uncertainty") or {}, "without the "
                          "uncertainty term")  # fmt: skip
    terms = ", ".join(f"{k} {v:.2f}" for k, v in result["rank_correlation_terms"].items())
    true_speed = result["rank_correlation_true_speed_term"]
    lines += ["", f"Rank correlation with the true objective of each imagined term alone: "
              f"{terms}; of the true speed term alone {true_speed:.2f}."]  # fmt: skip
    return lines


def search_lines(search: dict, variant: str = "") -> list[str]:
    """Markdown: what refine_search would choose from these starts, per margin."""
    if not search:
        return []
    parts = []
    for key, r in search.items():
        if key.startswith("margin_") and isinstance(r, dict):
            right = "—" if r["right"] is None else f"{r['right']:.2f}"
            parts.append(f"margin {key.removeprefix('margin_')}: moves {r['moves']:.2f}, "
                         f"right {right}, true gain {r['true_gain']:+.2f}")  # fmt: skip
    how = f" {variant}" if variant else ""
    lines = ["", f"Search among the alternatives (refine_search{how}): {'; '.join(parts)} "
             f"(oracle gain {search['oracle_true_gain']:+.2f} per start)."]  # fmt: skip
    if "chosen" in search:  # absent in results from before it
        picks = ", ".join(f"{k} {v:.0%}" for k, v in search["chosen"].items())
        best = ", ".join(f"{k} {v:.0%}" for k, v in search["truly_best"].items())
        lines[-1] += f" At margin 0 it picks {picks}; truly best: {best}."
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m research.variants.counterfactual", description=__doc__
    )
    p.add_argument("--run", required=True, help="carrt-train run directory (world_model.pt)")
    p.add_argument("--data", help="counterfactual .npz (default: generate RUN/counterfactual.npz)")
    p.add_argument("--layout", default="hard")
    p.add_argument("--tracks", default="200-204", help="held-out placements (not 100-199)")
    p.add_argument("--starts", type=int, default=20, help="start states per placement")
    p.add_argument("--json", help="write the numbers here")
    a = p.parse_args(argv)
    result = check_run(Path(a.run), Path(a.data) if a.data else None, a.layout, a.tracks, a.starts)
    print(describe(result))
    print("\n".join(by_sequence_table(result)))
    if a.json:
        Path(a.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
