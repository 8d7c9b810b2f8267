"""Issue 67, items 3 and 4: refinement by planning, distilled into the policy, and its check.

    python -m research.plan_distil record --policy weak=research/runs/pd/weak/policy.onnx \
        --tracks 1024-1063 --out research/runs/pd/rec_weak.npz
    python -m research.plan_distil score --rec research/runs/pd/rec_weak.npz \
        --ensemble research/runs/pd/gm --line research/runs/pd/line/person_line.pt
    python -m research.plan_distil distil --rec … --arm T3 --out …
    python -m research.plan_distil drive --policy … --tracks 200-259 --seeds 0,1 --out …

Why: planning in a learnt ground model cut a weak policy's crashes but a policy that plans at
run time is a different car from the one that learnt; what DIRL trains is a policy that drives
alone. Here the planner is the refinement: at frames the car recorded (never a simulator
state), plans around the policy's μ are sampled (`plan_set`: the ceiling's 13, swerve-and-
return, a brake, antithetic horizon-correlated noise), scored in the world model (survival with
the person's line, less w_unc·u), and the policy's whole μ_{t:t+H−1} is fitted to the plans
weighted by exp(−L/λ) (`weighted_target`) with imitation's L1 on the demonstrations as the
anchor. That weighting is the closed-form minimiser of E[L] + λ·KL(new ‖ old) over plans
sampled from the old policy (MPPI, reward-weighted regression): the paper's L_π with a trust
region, estimated by sampling instead of the pathwise gradient (which measured useless for the
ground model: sign 0.53). A gate (`gated_target`) keeps a strong policy from getting worse:
the target stays μ unless the best plan beats it by `margin` and the ensemble agrees.

The decisive check (research/LOG.md, 2026-12-02): the same recorded states scored twice, by the
simulator (the teacher, allowed for the check only, as "Learning by Cheating" uses a
privileged teacher) and by the learnt ensemble; four policies distilled from them; each drives
plain. The policy's σ is kept fixed (nothing here samples from it at run time; the plan set's
noise has its own fixed scale, NOISE_STD).
"""

from __future__ import annotations

import argparse
import json
import math
import random
import sys
import time
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch
from torch import Tensor

from carrt.errors import EXIT_USAGE, UserError
from research import ceiling
from research.recorded_runs import load_recorded

HORIZON = 10
SWERVES = (-0.6, -0.3, 0.3, 0.6)  # steering offsets held for SWERVE_STEPS, then back to μ
SWERVE_STEPS = 3
BRAKE = -0.5  # throttle for SWERVE_STEPS, then μ's
NOISE_PAIRS = 4  # antithetic pairs μ ± ε
NOISE_STD = (0.25, 0.2)  # steering, throttle: the stationary std of ε
NOISE_RHO = 0.8  # ε is AR(1) along the horizon: a plan's error lasts (horizon-correlated)
TRAINING_TRACKS = range(1000, 10000)


# -- the plans ------------------------------------------------------------------------------


def plan_set(mu: np.ndarray, low, high, rng: np.random.Generator) -> np.ndarray:
    """(P, H, 2) plans around μ (H, 2): μ first (a tie keeps it), the ceiling's 12 others,
    swerve-and-return, a brake, antithetic horizon-correlated noise; clipped to the bounds."""
    base = ceiling.candidates(mu, HORIZON, low, high)
    mu = base[0]
    extra = []
    for d in SWERVES:
        p = mu.copy()
        p[:SWERVE_STEPS, 0] += d
        extra.append(p)
    p = mu.copy()
    p[:SWERVE_STEPS, 1] = BRAKE
    extra.append(p)
    std = np.asarray(NOISE_STD, np.float32)
    for _ in range(NOISE_PAIRS):
        eps = np.zeros((HORIZON, 2), np.float32)
        eps[0] = rng.standard_normal(2) * std
        for k in range(1, HORIZON):
            eps[k] = NOISE_RHO * eps[k - 1] + math.sqrt(1 - NOISE_RHO**2) * std * (
                rng.standard_normal(2)
            )
        extra += [mu + eps, mu - eps]
    plans = np.concatenate([base, np.stack(extra)])
    return np.clip(plans, np.asarray(low, np.float32), np.asarray(high, np.float32))


def weighted_target(plans: np.ndarray, cost: np.ndarray, lam: float) -> np.ndarray:
    """Σ w_i·plan_i with w ∝ exp(−(L_i − min L)/λ): the minimiser of E_w[L] + λ·KL(w ‖ uniform
    over the sampled plans) — MPPI / reward-weighted regression's target."""
    z = -(cost - cost.min()) / max(lam, 1e-9)
    w = np.exp(z - z.max())
    w = w / w.sum()
    return np.tensordot(w, plans, axes=(0, 0))


def gated_target(
    plans: np.ndarray, cost: np.ndarray, agree: bool, margin: float, lam: float
) -> tuple[np.ndarray, bool]:
    """The target for μ (plans[0]): μ itself unless the best plan's cost beats μ's by more
    than `margin` and the ensemble agrees on it; then the weighted plan over the plans that beat
    μ (μ included). Returns (target, moved)."""
    best = int(np.argmin(cost))
    if best == 0 or cost[0] - cost[best] <= margin or not agree:
        return plans[0].copy(), False
    keep = cost <= cost[0]
    return weighted_target(plans[keep], cost[keep], lam), True


# -- policies as torch modules ----------------------------------------------------------------


class TorchPolicy:
    """A PolicyNet with OnnxPolicy's predict(): μ clipped to the action bounds."""

    def __init__(self, net, low, high, name: str = "") -> None:
        self.net, self.name = net.eval(), name
        self.action_low = np.asarray(low, np.float32)
        self.action_high = np.asarray(high, np.float32)
        self.sha256 = name

    @torch.no_grad()
    def mu(self, images: np.ndarray, speeds: np.ndarray) -> np.ndarray:
        mu, _ = self.net(
            torch.from_numpy(np.ascontiguousarray(images)),
            torch.from_numpy(np.asarray(speeds, np.float32)).view(-1, 1),
        )
        return np.clip(mu.numpy(), self.action_low, self.action_high)

    def predict(self, image: np.ndarray, speed_mps: float):
        from carrt.plan import Plan

        mu = self.mu(image[None], np.array([speed_mps]))[0]
        return Plan(mu=mu, sigma=np.full_like(mu, 0.05))


def policy_from_checkpoint(path: Path, onnx_path: Path):
    """The PolicyNet of a carrt-train checkpoint, with its ONNX file's action bounds."""
    from carrt.policy import OnnxPolicy
    from training.models import PolicyNet
    from training.profiles import PROFILES

    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    net = PolicyNet(PROFILES[ckpt["profile"]])
    net.load_state_dict(ckpt["policy"])
    onnx = OnnxPolicy(str(onnx_path), intra_op_threads=1)
    return TorchPolicy(net, onnx.action_low, onnx.action_high, str(onnx_path))


def policy_from_onnx(onnx_path: Path):
    """A PolicyNet holding an exported policy's weights (the shipped one has no checkpoint in
    the tree): the export folds each batch norm into its convolution, so each convolution
    gets the folded weight and its norm becomes the identity with the folded bias. Checked
    against the ONNX file on frames (max |Δμ|)."""
    import onnx
    from onnx import numpy_helper

    from carrt.policy import OnnxPolicy
    from training.models import PolicyNet
    from training.profiles import PROFILES

    model = onnx.load(str(onnx_path))
    meta = {p.key: p.value for p in model.metadata_props}
    net = PolicyNet(PROFILES[meta.get("carrt.profile", "cpu")])
    inits = {
        i.name: torch.from_numpy(numpy_helper.to_array(i).copy()) for i in model.graph.initializer
    }
    state = net.state_dict()
    for name in list(state):
        if name in inits:
            state[name] = inits[name].reshape(state[name].shape)
    convs = [n for n in inits if n.startswith("onnx::Conv_")]
    convs.sort(key=lambda n: int(n.rsplit("_", 1)[1]))
    pairs = list(zip(convs[0::2], convs[1::2], strict=True))
    conv_names = [n for n in state if n.endswith(".weight") and state[n].dim() == 4]
    if len(conv_names) != len(pairs):
        raise UserError(
            f"{onnx_path}: {len(pairs)} folded convolutions, the net has {len(conv_names)}"
        )
    bns = [n[: -len(".running_var")] for n in state if n.endswith(".running_var")]
    for (w, b), conv, bn in zip(pairs, conv_names, bns, strict=True):
        state[conv] = inits[w]
        state[bn + ".weight"] = torch.ones_like(state[bn + ".weight"])
        state[bn + ".bias"] = inits[b]
        state[bn + ".running_mean"] = torch.zeros_like(state[bn + ".running_mean"])
        state[bn + ".running_var"] = torch.full_like(state[bn + ".running_var"], 1 - 1e-5)
    sub = [n for n in inits if n.startswith("onnx::Sub_")]
    div = [n for n in inits if n.startswith("onnx::Div_")]
    if sub and div:
        state["image_mean"] = inits[sub[0]].view(1, 3, 1, 1)
        state["image_std"] = inits[div[0]].view(1, 3, 1, 1)
    net.load_state_dict(state)
    onnx_policy = OnnxPolicy(str(onnx_path), intra_op_threads=1)
    policy = TorchPolicy(net, onnx_policy.action_low, onnx_policy.action_high, str(onnx_path))
    rng = np.random.default_rng(0)
    worst = 0.0
    for _ in range(4):
        img = rng.integers(0, 256, (96, 96, 3), dtype=np.uint8)
        v = float(rng.uniform(0, 2.5))
        worst = max(
            worst, float(np.abs(policy.predict(img, v).mu - onnx_policy.predict(img, v).mu).max())
        )
    if worst > 1e-3:
        raise UserError(f"{onnx_path}: the torch copy differs from the ONNX file by {worst:.2g}")
    return policy


def load_policy(spec: str):
    """weak=CKPT.pt:ONNX, shipped=ONNX (or demo), or NAME=DISTILLED.pt (a fine-tuned copy)."""
    from carrt.shipped import resolve_model

    _, _, rest = spec.partition("=")
    if rest.endswith(".pt") and ":" not in rest:
        blob = torch.load(rest, map_location="cpu", weights_only=False)
        from training.models import PolicyNet
        from training.profiles import PROFILES

        net = PolicyNet(PROFILES[blob["profile"]])
        net.load_state_dict(blob["policy"])
        return TorchPolicy(net, blob["low"], blob["high"], rest)
    if ":" in rest:
        ckpt, onnx_path = rest.split(":", 1)
        return policy_from_checkpoint(Path(ckpt), Path(onnx_path))
    return policy_from_onnx(resolve_model(rest))


# -- recording and driving ------------------------------------------------------------------


def drive(
    policy,
    *,
    track: int,
    seed: int,
    seconds: float,
    layout: str = "hard",
    record: bool = False,
    teacher: bool = False,
    planner=None,
) -> tuple[dict, dict | None]:
    """One run as research.ceiling.run drives it (the board's rise limit, the 30 fps camera's
    latest frame, auto-reset and 1 s standing after a collision). `planner` (optional) picks the
    executed plan at each step from (world, image, speed, plans, throttle_now, history). With
    `record`, what a car records at each driving step (frame, speed, μ, the plans, executed
    command, the board's throttle before it, a collision in the step, the segment since the last
    reset) and with `teacher` the simulator's survival and speed scores of every plan (the
    privileged teacher's, kept apart as `sim_*`)."""
    from carrt.sim.metrics import TrajectoryRecorder
    from carrt.sim.render import Renderer
    from carrt.sim.world import SimWorld, StepInfo

    w = ceiling.Weights.from_training()
    world = SimWorld(layout=layout, seed=track)
    renderer = Renderer(world.track)
    phase = random.Random(seed).uniform(0.0, 1.0 / ceiling.CAMERA_FPS)
    rng = np.random.default_rng([seed, track])
    recorder = TrajectoryRecorder()
    recorder.record(world)
    poses = [(world.time, world.car.x, world.car.y, world.car.yaw)]
    throttle_now, standing, segment = 0.0, 0, 0
    rec: dict[str, list] = {
        k: []
        for k in (
            "image",
            "speed",
            "mu",
            "plans",
            "executed",
            "throttle_before",
            "collision",
            "segment",
            "sim_survival",
            "sim_speed",
            "truth_pose",
        )
    }
    history: list = []
    started = time.perf_counter()
    for _ in range(round(seconds / ceiling.CONTROL_PERIOD_S)):
        if standing > 0:
            standing -= 1
            throttle_now, *_ = ceiling.drive_period(world, 0.0, 0.0, 0.0, poses)
            recorder.record(world, StepInfo(False, "", False), resetting=True)
            continue
        image = renderer.render(*ceiling.frame_pose(poses, world.time, phase))
        v = float(world.car.v)
        mu = policy.predict(image, v).mu
        if record or teacher or planner is not None:
            plans = plan_set(mu, policy.action_low, policy.action_high, rng)
        else:  # plain: μ's first command, as research.ceiling's candidates clip it
            plans = np.clip(mu[None, :1], policy.action_low, policy.action_high)
        best = 0 if planner is None else planner(world, image, v, plans, throttle_now, history)
        if teacher:
            outs = [ceiling.rollout(world, p, throttle_now) for p in plans]
            rec["sim_survival"].append([ceiling.score("survival", o, w) for o in outs])
            rec["sim_speed"].append([ceiling.score("speed", o, w) for o in outs])
        steering, throttle = plans[best, 0]
        if record:
            if record != "light":
                rec["image"].append(image)
                rec["plans"].append(plans)
            rec["speed"].append(v)
            rec["mu"].append(plans[0])
            rec["throttle_before"].append(throttle_now)
            rec["segment"].append(segment)
            rec["truth_pose"].append((world.car.x, world.car.y, world.car.yaw))
        history.append((float(steering), float(throttle), v))
        throttle_now, hit, lap, _, _ = ceiling.drive_period(
            world, steering, throttle, throttle_now, poses
        )
        recorder.record(world, StepInfo(hit, "", lap))
        if record:
            rec["executed"].append((float(steering), float(throttle)))
            rec["collision"].append(bool(hit))
        if hit:
            world.reset()
            throttle_now, standing = 0.0, round(ceiling.RESET_PAUSE_S / ceiling.CONTROL_PERIOD_S)
            segment += 1
            history = []
            poses.append((world.time, world.car.x, world.car.y, world.car.yaw))
    m = recorder.metrics(world.track.length)
    minutes = (recorder.t[-1] - recorder.t[0]) / 60.0
    row = {
        "track": track,
        "seed": seed,
        "completion_ratio": m.completion_ratio,
        "collisions_per_min": m.collisions / minutes if minutes > 0 else 0.0,
        "laps_per_min": m.laps_per_min,
        "average_speed": m.average_speed,
        "wall_s": time.perf_counter() - started,
    }
    return row, (rec if record else None)


def record(policy, tracks, seed: int, seconds: float, out: Path, teacher: bool) -> None:
    """The recorded set: the policy drives training placements plain (one .npz per run, kept)."""
    out.mkdir(parents=True, exist_ok=True)
    for track in tracks:
        if track not in TRAINING_TRACKS:
            raise UserError(f"--tracks: {track} is not a training placement (1000 and up)")
        f = out / f"{track}-s{seed}.npz"
        if f.is_file():
            continue
        row, rec = drive(
            policy, track=track, seed=seed, seconds=seconds, record=True, teacher=teacher
        )
        arrays = {k: np.asarray(v) for k, v in rec.items() if v}
        arrays["track"] = np.full(len(rec["speed"]), track)
        part = f.with_suffix(".part.npz")
        np.savez_compressed(part, **arrays)
        part.replace(f)
        print(
            f"record {track}: {len(rec['speed'])} steps, {row['collisions_per_min']:.1f} "
            f"collisions/min, {row['wall_s']:.0f} s",
            flush=True,
        )


# -- the learnt teacher: scoring recorded frames -------------------------------------------

W_UNC = 1.0  # cost per std of the members' objectives: a one-std lower confidence bound
LAMBDA_M = 0.3  # the weighting's temperature, metres of survival-weighted progress
MARGINS = (0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 1.0)
PRECISION_BAR = 0.7


def survival_scores(out: dict, progress: Tensor, w) -> Tensor:
    """(K, N, P) each member's survival-form score (research.ceiling.choose_imagined's)."""
    h = progress.shape[-1]
    gains = torch.diff(progress, dim=-1, prepend=torch.zeros_like(progress[..., :1]))
    surv, pc = out["survival"], out["p_collision"]  # (K, N, P, H)
    alive = torch.cat([torch.ones_like(surv[..., :1]), surv[..., :-1]], dim=-1)
    discount = w.discount ** torch.arange(h, dtype=progress.dtype)
    total = (discount * (gains[None] * alive - w.crash_cost_m * pc)).sum(-1)
    beyond = w.discount**h * out["speed"][None, ..., -1] * w.beyond_s * surv[..., -1]
    return total + beyond


@torch.no_grad()
def score_recorded(rec: dict, ensemble, line, batch: int = 64) -> dict[str, np.ndarray]:
    """The learnt scores of every recorded plan, from what the car recorded alone: each frame's
    hazard maps fused with the two frames before (dead reckoning), the start state from the
    recorded commands since the last reset, the speed law, the person's line. Returns per frame
    (N, P): mean and std over members of the survival score, the cost L = −mean + W_UNC·std,
    each member's agreement that the best beats μ, the evidential u and unseen share summed
    over the horizon (discounted), and the imagined speeds of the executed commands."""
    from research import ground_v2
    from research.person_line import progress_along

    w = ceiling.Weights.from_training()
    geo = ensemble.geo
    n = len(rec["speed"])
    out = {
        k: np.zeros((n, rec["plans"].shape[1]), np.float32)
        for k in ("mean", "std", "cost", "u_evid", "unseen")
    }
    out["agree"] = np.zeros(n, bool)
    out["speed_exec"] = np.full((n, HORIZON), np.nan, np.float32)
    visible = ensemble.members[0].visible[0, 0]
    discount = w.discount ** torch.arange(HORIZON, dtype=torch.float32)
    for seg in ground_v2.segments_from_recorded(rec):
        idx = seg["index"]
        state = torch.from_numpy(ground_v2.start_states(seg["executed"], ensemble.law, geo)).float()
        past = ground_v2.past_poses(seg["speed"], seg["executed"][:, 0], geo)
        maps = ensemble.frame_maps(seg["images"])  # (K, n, 2, X, Y)
        fused, seen = [], []
        for t in range(len(idx)):
            per = []
            for j in range(len(ensemble.members)):
                hist = [maps[j, t - i] for i in range(ground_v2.FUSE) if t - i >= 0]
                f, s_ = ground_v2.fuse(
                    ensemble.grid, hist, visible, list(past[t, : len(hist) - 1]), ensemble.base
                )
                per.append(f)
            fused.append(torch.stack(per))
            seen.append(s_)
        fused, seen = torch.stack(fused, dim=1), torch.stack(seen)
        for b in range(0, len(idx), batch):
            sl = slice(b, b + batch)
            ii = idx[sl]
            plans = torch.from_numpy(rec["plans"][ii]).float()
            # the executed commands as a plan: the next H recorded commands (for the speed error)
            ex = seg["executed"]
            execp = np.stack(
                [
                    ex[np.minimum(np.arange(t, t + HORIZON), len(ex) - 1)]
                    for t in range(sl.start, min(sl.stop, len(ex)))
                ]
            )
            allp = torch.cat([plans, torch.from_numpy(execp).float()[:, None]], dim=1)
            v0 = torch.from_numpy(seg["speed"][sl]).float()
            im = ensemble.imagine(fused[:, sl], seen[sl], v0, state[sl], allp)
            m_ = allp.shape[1]
            line_pts = line(torch.from_numpy(np.ascontiguousarray(seg["images"][sl])))
            prog = progress_along(
                line_pts.repeat_interleave(m_, dim=0), im["poses"][..., :2].reshape(-1, HORIZON, 2)
            )
            prog = prog.view(len(ii), m_, HORIZON)
            sc = survival_scores(im, prog, w)[:, :, :-1]  # (K, n, P)
            mean, std = sc.mean(0), sc.std(0) if sc.shape[0] > 1 else torch.zeros_like(sc[0])
            cost = -mean + W_UNC * std
            best = cost.argmin(dim=1)
            agree = (
                sc.gather(2, best[None, :, None].expand(sc.shape[0], -1, 1))[..., 0] > sc[..., 0]
            ).all(0)
            out["mean"][ii], out["std"][ii], out["cost"][ii] = (
                mean.numpy(),
                std.numpy(),
                cost.numpy(),
            )
            out["agree"][ii] = agree.numpy()
            out["u_evid"][ii] = (im["u_evidential"][:, :-1] * discount).sum(-1).numpy()
            out["unseen"][ii] = (im["unseen"][:, :-1] * discount).sum(-1).numpy()
            # speeds: only where the next H steps exist inside the segment
            full = np.arange(sl.start, min(sl.stop, len(ex))) + HORIZON < len(ex)
            out["speed_exec"][ii[full]] = im["speed"][full, -1].numpy()
    return out


def auroc(score: np.ndarray, label: np.ndarray) -> float:
    """P(score of a positive > score of a negative), ties half."""
    pos, neg = score[label], score[~label]
    if len(pos) == 0 or len(neg) == 0:
        return float("nan")
    allv = np.concatenate([pos, neg])
    ranks = np.argsort(np.argsort(allv, kind="mergesort"), kind="mergesort") + 1.0
    # average ranks for ties
    _, inv, counts = np.unique(allv, return_inverse=True, return_counts=True)
    sums = np.bincount(inv, weights=ranks)
    ranks = (sums / counts)[inv]
    return float((ranks[: len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg)))


def offline_check(rec: dict, learnt: dict) -> dict:
    """Precision of the learnt moves by margin (needs the simulator's scores: the check only),
    the margin the rule fixes, and the uncertainty's AUROC at telling wrong moves."""
    sim = rec["sim_survival"]
    cost = learnt["cost"]
    best = cost.argmin(1)
    n = np.arange(len(best))
    adv = cost[:, 0] - cost[n, best]
    moved = best != 0
    truly = sim[n, best] > sim[:, 0] + ceiling.TIE_TOLERANCE
    sim_best = np.argmax(sim, axis=1)
    sim_moves = sim[n, sim_best] > sim[:, 0] + ceiling.TIE_TOLERANCE
    rows = []
    for m in MARGINS:
        sel = moved & (adv > m)
        sel_agree = sel & learnt["agree"]
        rows.append(
            {
                "margin": m,
                "moves": int(sel.sum()),
                "precision": float(truly[sel].mean()) if sel.any() else float("nan"),
                "moves_agreed": int(sel_agree.sum()),
                "precision_agreed": float(truly[sel_agree].mean())
                if sel_agree.any()
                else float("nan"),
            }
        )
    chosen = next(
        (r["margin"] for r in rows if r["moves_agreed"] and r["precision_agreed"] >= PRECISION_BAR),
        MARGINS[-1],
    )
    wrong = ~truly[moved]
    u = {}
    for name in ("std", "u_evid", "unseen"):
        excess = learnt[name][n, best] - learnt[name][:, 0]
        u[name] = auroc(excess[moved], wrong)
    speed_ok = ~np.isnan(learnt["speed_exec"][:, -1])
    return {
        "frames": len(best),
        "learnt_moves": int(moved.sum()),
        "sim_moves": int(sim_moves.sum()),
        "precision_all_moves": float(truly[moved].mean()) if moved.any() else float("nan"),
        "by_margin": rows,
        "margin": chosen,
        "uncertainty_auroc_wrong": u,
        "speed_frames": int(speed_ok.sum()),
    }


def targets(
    rec: dict, learnt: dict | None, arm: str, margin: float
) -> tuple[np.ndarray, np.ndarray]:
    """(N, H, 2) the distillation targets of an arm and (N,) whether each moved from μ."""
    plans, n = rec["plans"], np.arange(len(rec["plans"]))
    if arm == "T0":
        return plans[:, 0].copy(), np.zeros(len(n), bool)
    if arm == "T1":
        sim = rec["sim_survival"]
        best = np.argmax(sim, 1)
        best[sim[n, best] <= sim[:, 0] + ceiling.TIE_TOLERANCE] = 0
        return plans[n, best], best != 0
    cost = learnt["cost"]
    if arm == "T2":
        best = cost.argmin(1)
        return plans[n, best], best != 0
    if arm == "T3":
        out = [
            gated_target(plans[i], cost[i], bool(learnt["agree"][i]), margin, LAMBDA_M) for i in n
        ]
        return np.stack([o[0] for o in out]), np.array([o[1] for o in out])
    raise UserError(f"unknown arm {arm}")


def gains(rec: dict, learnt: dict | None, arm: str) -> np.ndarray:
    """(N,) how much the arm's best plan beats μ at each frame (m; 0 for T0): the simulator's
    score for T1, the learnt cost for T2 and T3."""
    n = np.arange(len(rec["plans"]))
    if arm == "T0":
        return np.zeros(len(n))
    if arm == "T1":
        sim = rec["sim_survival"]
        return np.maximum(sim.max(1) - sim[:, 0], 0)
    cost = learnt["cost"]
    return np.maximum(cost[:, 0] - cost.min(1), 0)


def distil(
    policy,
    rec: dict,
    target: np.ndarray,
    anchor_episodes: list[str],
    out: Path,
    steps: int = 300,
    seed: int = 0,
    lr: float = 3e-4,
    weight: np.ndarray | None = None,
) -> Path:
    """Fine-tune the policy's whole μ on the recorded frames' targets (L1) with imitation's L1
    on the demonstrations as the anchor (one batch of each per step); σ untouched (fixed).
    Batch norms keep their statistics (eval mode): the recorded set is small."""
    from training.data import ImitationDataset
    from training.episodes import load_episodes
    from training.imitation import imitation_loss

    torch.manual_seed(seed)
    net = policy.net
    demos = ImitationDataset(load_episodes(anchor_episodes), HORIZON)
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam([p for n_, p in net.named_parameters()], lr=lr)
    images, speeds = (
        torch.from_numpy(rec["image"]),
        torch.from_numpy(rec["speed"].astype(np.float32)),
    )
    tgt = torch.from_numpy(target.astype(np.float32))
    wt = torch.ones(len(images)) if weight is None else torch.from_numpy(weight.astype(np.float32))
    net.eval()
    for step in range(steps):
        pick = torch.randint(len(images), (32,), generator=gen)
        mu, _ = net(images[pick], speeds[pick].view(-1, 1))
        per = (mu - tgt[pick]).abs().mean(dim=(1, 2))
        loss_t = (wt[pick] * per).sum() / wt[pick].sum()
        dpick = torch.randint(len(demos), (32,), generator=gen).tolist()
        items = [demos[i] for i in dpick]
        batch = {k: torch.stack([it[k] for it in items]) for k in items[0]}
        loss_a, _ = imitation_loss(net, batch)
        loss = loss_t + loss_a
        opt.zero_grad()
        loss.backward()
        opt.step()
        if (step + 1) % 100 == 0:
            print(
                f"distil {out.name}: step {step + 1}/{steps} target L1 {loss_t.item():.4f} "
                f"anchor L1 {loss_a.item():.4f}",
                flush=True,
            )
    out.parent.mkdir(parents=True, exist_ok=True)
    torch.save(
        {
            "policy": net.state_dict(),
            "profile": net.profile.name,
            "low": policy.action_low.tolist(),
            "high": policy.action_high.tolist(),
        },
        out,
    )
    return out


def to_onnx(pt: Path, base_onnx: Path, frames: np.ndarray, speeds: np.ndarray) -> Path:
    """The distilled policy as an ONNX file carrt's OnnxPolicy loads (the base file's metadata
    and action bounds), parity with torch checked on recorded frames."""
    from types import SimpleNamespace

    import onnx

    from carrt.policy import OnnxPolicy
    from export.graph import declare_outputs, get_metadata, set_metadata
    from export.onnx_export import torch_to_onnx

    policy = load_policy(f"x={pt}")
    ex = SimpleNamespace(images=frames[:2], speeds=speeds[:2].astype(np.float32).reshape(-1, 1))
    model, _ = torch_to_onnx(policy.net, ex)
    declare_outputs(model, HORIZON)
    meta = get_metadata(onnx.load(str(base_onnx)))
    meta["carrt.stage"] = "plan_distil"
    set_metadata(model, meta)
    path = pt.with_suffix(".onnx")
    onnx.save(model, str(path))
    o = OnnxPolicy(str(path), intra_op_threads=1)
    worst = max(
        float(np.abs(o.predict(f, float(v)).mu - policy.predict(f, float(v)).mu).max())
        for f, v in zip(frames[:8], speeds[:8], strict=True)
    )
    if worst > 1e-3:
        raise UserError(f"{path}: ONNX differs from torch by {worst:.2g}")
    return path


# -- driving the check ---------------------------------------------------------------------


class TrueMapPlanner:
    """G0's planner: v2's motion (the speed law, the start state from the executed commands
    since the reset) and the placement's true hazard and progress (a ceiling on the motion
    alone: what the learnt map and line cost is measured elsewhere). The ceiling's 13 plans,
    the survival form."""

    def __init__(self, law, edge: float = 0.02) -> None:
        from research.ground_model import CarGeometry, body_points

        self.law, self.geo, self.edge = law, CarGeometry(), edge
        self.points = body_points(self.geo)
        self.w = ceiling.Weights.from_training()

    @torch.no_grad()
    def __call__(self, world, image, v, plans, throttle_now, history) -> int:
        from research import ground_v2
        from research.ground_model import points_at

        plans = plans[: len(ceiling.CANDIDATES)]
        past = np.array([(s, t) for s, t, _ in history] + [(0.0, 0.0)], np.float64)
        state = ground_v2.start_states(past, self.law, self.geo)[-1]
        k = len(plans)
        speeds, poses = ground_v2.drive(
            self.geo,
            self.law,
            torch.full((k,), float(v)),
            torch.from_numpy(plans).float(),
            torch.from_numpy(state).float().expand(k, 3),
        )
        pts = points_at(poses, self.points)
        car, track = world.car, world.track
        c, s_ = math.cos(car.yaw), math.sin(car.yaw)
        wx = car.x + c * pts[..., 0] - s_ * pts[..., 1]
        wy = car.y + s_ * pts[..., 0] + c * pts[..., 1]
        width, height = track.arena
        d = torch.minimum(torch.minimum(wx, width - wx), torch.minimum(wy, height - wy))
        for o in track.obstacles:
            d = torch.minimum(d, torch.hypot(wx - o.x, wy - o.y) - o.radius)
        p_here = torch.sigmoid(-d / self.edge).max(dim=2).values  # (K, H)
        alive = torch.cumprod(1 - p_here, dim=1)
        before = torch.cat([torch.ones_like(alive[:, :1]), alive[:, :-1]], dim=1)
        out = {"survival": alive[None], "p_collision": (before * p_here)[None], "speed": speeds}
        prog = torch.from_numpy(
            ceiling.true_progress(world, poses[..., :2].double().numpy())
        ).float()
        sc = survival_scores(out, prog, self.w)[0].numpy()
        best = int(np.argmax(sc))
        return 0 if sc[best] <= sc[0] + ceiling.TIE_TOLERANCE else best


def evaluate(
    name: str, policy, tracks, seeds, seconds: float, out: Path, planner=None, light: bool = False
) -> list[dict]:
    """Drives on validation placements, one JSON per run under OUT/NAME (kept: resumable);
    with `light` the speeds, commands and segments of each run beside it (the held-out set of
    G0's speed error)."""
    rows = []
    for track in tracks:
        if track in ceiling.EVALUATION_TRACKS:
            raise UserError("the test placements 100-199 are never driven here")
        for seed in seeds:
            f = out / name / f"{track}-s{seed}.json"
            if f.is_file():
                rows.append(json.loads(f.read_text()))
                continue
            row, rec = drive(
                policy,
                track=track,
                seed=seed,
                seconds=seconds,
                record="light" if light else False,
                planner=planner,
            )
            row = {"arm": name, **row}
            f.parent.mkdir(parents=True, exist_ok=True)
            if light:
                np.savez_compressed(
                    f.with_suffix(".npz"),
                    **{k: np.asarray(v) for k, v in rec.items() if v and k != "mu"},
                )
            f.with_suffix(".part").write_text(json.dumps(row) + "\n")
            f.with_suffix(".part").replace(f)
            rows.append(row)
            print(
                f"{name} {track} s{seed}: completion {row['completion_ratio']:.2f}, "
                f"{row['collisions_per_min']:.1f}/min, {row['laps_per_min']:.2f} laps/min "
                f"({row['wall_s']:.0f} s)",
                flush=True,
            )
    return rows


def speed_error(folder: Path, law, geo=None) -> dict:
    """G0's held-out speed error: over every recorded frame of the light runs under `folder`
    with 10 steps ahead inside its segment, mean |imagined − recorded speed| over those steps
    of the executed commands, from the frame's start state (v2) — and v1's way (servo at the
    first command, motor at the speed's steady state, no rise limit) with v1's fit."""
    from research import ground_model, ground_v2

    geo = geo or ground_model.CarGeometry()
    errs = {"v2": [], "v2_steady_start": []}
    for f in sorted(folder.glob("*.npz")):
        r = dict(np.load(f))
        for s_ in np.unique(r["segment"]):
            i = np.nonzero(r["segment"] == s_)[0]
            ex, v = r["executed"][i].astype(np.float64), r["speed"][i].astype(np.float64)
            if len(i) <= HORIZON:
                continue
            state = ground_v2.start_states(ex, law, geo)
            ts = np.arange(len(i) - HORIZON)
            acts = torch.from_numpy(np.stack([ex[t : t + HORIZON] for t in ts])).float()
            truth = np.stack([v[t + 1 : t + 1 + HORIZON] for t in ts])
            v0 = torch.from_numpy(v[ts]).float()
            sp, _ = ground_v2.drive(geo, law, v0, acts, torch.from_numpy(state[ts]).float())
            errs["v2"].append(np.abs(sp.numpy() - truth).mean(1))
            a, _, c, d = law.coef
            steady = np.clip((c * v[ts] + d) / a, 0, 1)
            st = np.stack([-np.clip(ex[ts, 0], -1, 1) * geo.max_steer, steady, steady], 1)
            st[:, 1] = 1.0  # no rise limit from the start: the board at full
            sp2, _ = ground_v2.drive(geo, law, v0, acts, torch.from_numpy(st).float())
            errs["v2_steady_start"].append(np.abs(sp2.numpy() - truth).mean(1))
    return {k: float(np.concatenate(e).mean()) for k, e in errs.items() if e} | {
        "frames": int(sum(len(e) for e in errs["v2"]))
    }


def summarise(rows: list[dict]) -> dict:
    out = {}
    for k in ("completion_ratio", "collisions_per_min", "laps_per_min"):
        x = np.array([r[k] for r in rows])
        out[k] = {
            "mean": float(x.mean()),
            "std": float(x.std()),
            "se": float(x.std(ddof=1) / math.sqrt(len(x))) if len(x) > 1 else 0.0,
        }
    out["runs"] = len(rows)
    return out


def paired(a: list[dict], b: list[dict], key: str) -> dict:
    """b − a per run (same placement and seed): mean and standard error."""
    ka = {(r["track"], r["seed"]): r[key] for r in a}
    d = np.array([r[key] - ka[(r["track"], r["seed"])] for r in b if (r["track"], r["seed"]) in ka])
    return {"mean": float(d.mean()), "se": float(d.std(ddof=1) / math.sqrt(len(d))), "n": len(d)}


def load_rows(folder: Path, name: str) -> list[dict]:
    return [json.loads(f.read_text()) for f in sorted((folder / name).glob("*.json"))]


def verdicts(ev: Path, law, offline: dict | None) -> dict:
    """G0–G3 by the rules in research/LOG.md (2026-12-02), from the runs under `ev`."""
    rows = {n.name: load_rows(ev, n.name) for n in sorted(ev.iterdir()) if n.is_dir()}
    cell = {n: summarise(r) for n, r in rows.items() if r}
    out: dict = {"cells": cell}
    speed = speed_error(ev / "weak-plain", law)
    g0 = rows.get("weak-g0-truemap", [])
    g0_laps = summarise(g0)["laps_per_min"]["mean"] if g0 else float("nan")
    out["G0"] = {
        "speed_error_mps": speed,
        "truemap_laps_per_min": g0_laps,
        "met": bool(speed["v2"] <= 0.18 and g0_laps >= 8.0),
    }
    plain = rows.get("weak-plain", [])

    def cut(arm_rows, base_rows):
        return (
            summarise(base_rows)["collisions_per_min"]["mean"]
            - summarise(arm_rows)["collisions_per_min"]["mean"]
        )

    def g1(arm_rows):
        laps = paired(plain, arm_rows, "laps_per_min")
        c = cut(arm_rows, plain)
        base = summarise(plain)["collisions_per_min"]["mean"]
        met = c >= 0.5 * base and laps["mean"] >= -laps["se"]
        return {"collision_cut": c, "plain_collisions": base, "laps_paired": laps, "met": bool(met)}

    if plain and rows.get("weak-T2"):
        out["T2_minus_plain"] = {
            k: paired(plain, rows["weak-T2"], k) for k in ("collisions_per_min", "laps_per_min")
        }
    if plain and rows.get("weak-T1"):
        t1 = rows["weak-T1"]
        out["G1"] = g1(t1)
        c1 = out["G1"]["collision_cut"]
        if rows.get("weak-T1r2"):
            out["G1"]["round2"] = g1(rows["weak-T1r2"])
            out["G1"]["met"] = bool(out["G1"]["met"] or out["G1"]["round2"]["met"])
        if rows.get("weak-T3") and rows.get("weak-T0"):
            t3, t0 = rows["weak-T3"], rows["weak-T0"]
            c3 = cut(t3, plain)
            l3 = paired(plain, t3, "laps_per_min")
            d0c, d0l = paired(plain, t0, "collisions_per_min"), paired(plain, t0, "laps_per_min")
            level = abs(d0c["mean"]) <= 2 * d0c["se"] and abs(d0l["mean"]) <= 2 * d0l["se"]
            out["G2"] = {
                "collision_cut_T3": c3,
                "share_of_T1_cut": c3 / c1 if c1 > 0 else float("nan"),
                "laps_paired": l3,
                "T0_minus_plain": {"collisions": d0c, "laps": d0l},
                "met": bool(c1 > 0 and c3 >= 0.5 * c1 and l3["mean"] >= -l3["se"] and level),
            }
    sp, s3 = rows.get("shipped-plain", []), rows.get("shipped-T3", [])
    if sp and s3:
        dc, dl = paired(sp, s3, "collisions_per_min"), paired(sp, s3, "laps_per_min")
        out["G3"] = {
            "collisions_paired": dc,
            "laps_paired": dl,
            "met": bool(dc["mean"] <= 0.2 and dl["mean"] >= -dl["se"]),
        }
    if offline:
        out["offline"] = offline
    return out


def report(ev: Path, law, offline: dict | None, path: Path) -> dict:
    arms = {
        "weak-plain": ("plain", "weak"),
        "weak-T0": ("T0", "weak"),
        "weak-T1": ("T1", "weak"),
        "weak-T2": ("T2", "weak"),
        "weak-T3": ("T3", "weak"),
        "weak-T1r2": ("T1-round2", "weak"),
        "weak-g0-truemap": ("G0-truemap-planning", "weak"),
        "shipped-plain": ("plain", "shipped"),
        "shipped-T0": ("T0", "shipped"),
        "shipped-T3": ("T3", "shipped"),
    }
    rows = []
    for name, (arm, pol) in arms.items():
        for r in load_rows(ev, name):
            rows.append(
                {
                    "arm": arm,
                    "policy": pol,
                    "track": r["track"],
                    "seed": r["seed"],
                    **{k: r[k] for k in ("completion_ratio", "collisions_per_min", "laps_per_min")},
                }
            )
    v = verdicts(ev, law, offline)
    payload = {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "command": "python -m research.plan_distil " + " ".join(sys.argv[1:]),
        "rows": rows,
        "verdicts": {k: v[k] for k in ("G0", "G1", "G2", "G3") if k in v},
        "cells": v["cells"],
        "offline": v.get("offline"),
    }
    payload["T2_minus_plain"] = v.get("T2_minus_plain")
    payload = _no_nan(payload)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=1) + "\n")
    return payload


def _no_nan(x):
    """NaN → null: the results file is strict JSON."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _no_nan(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_no_nan(v) for v in x]
    return x


def main(argv: list[str] | None = None) -> int:
    from carrt.arg_types import parse_int_list

    p = argparse.ArgumentParser(
        prog="python -m research.plan_distil", description=__doc__.split("\n")[0]
    )
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record", help="the policy drives training placements plain, recorded")
    r.add_argument("--policy", required=True, help="NAME=CKPT.pt:POLICY.onnx or NAME=POLICY.onnx")
    r.add_argument("--tracks", default="1024-1047")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--seconds", type=float, default=30.0)
    r.add_argument("--out", required=True)
    r.add_argument("--teacher", action="store_true", help="the simulator scores every plan too")
    sc = sub.add_parser("score", help="the learnt ensemble scores every recorded plan")
    sc.add_argument("--rec", required=True)
    sc.add_argument("--ensemble", required=True)
    sc.add_argument("--line", required=True)
    sc.add_argument("--out", required=True)
    d = sub.add_parser("distil", help="fine-tune the policy on an arm's targets")
    d.add_argument("--policy", required=True)
    d.add_argument("--rec", required=True)
    d.add_argument("--learnt", default="")
    d.add_argument("--arm", required=True, choices=("T0", "T1", "T2", "T3"))
    d.add_argument("--margin", type=float, default=0.0)
    d.add_argument("--anchor", nargs="+", required=True)
    d.add_argument("--base-onnx", required=True)
    d.add_argument("--steps", type=int, default=300)
    d.add_argument(
        "--weight-by-gain",
        action="store_true",
        help="weight each frame by 1 + the target plan's gain over μ (m), at most 10",
    )
    d.add_argument("--out", required=True)
    e = sub.add_parser("eval", help="drive plain (or with G0's planner) on validation")
    e.add_argument("--name", required=True)
    e.add_argument("--onnx", required=True)
    e.add_argument("--tracks", default="200-259")
    e.add_argument("--seeds", default="0,1")
    e.add_argument("--seconds", type=float, default=30.0)
    e.add_argument("--out", required=True)
    e.add_argument("--light", action="store_true")
    e.add_argument("--true-map-planner", default="", help="a v2 run folder: plan in its motion")
    e.add_argument("--edge", type=float, default=0.02, help="the true map's soft edge, m")
    rp = sub.add_parser("report", help="the results file with G0–G3's verdicts")
    rp.add_argument("--eval", required=True)
    rp.add_argument("--ensemble", required=True)
    rp.add_argument("--offline", default="")
    rp.add_argument("--out", default="research/results/plan_distil_check.json")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    try:
        if a.cmd == "record":
            policy = load_policy(a.policy)
            record(
                policy,
                parse_int_list(a.tracks, "tracks"),
                a.seed,
                a.seconds,
                Path(a.out),
                a.teacher,
            )
        elif a.cmd == "score":
            from research import ground_v2, person_line

            rec = load_recorded(Path(a.rec))
            learnt = score_recorded(
                rec, ground_v2.load(Path(a.ensemble)), person_line.load(Path(a.line))
            )
            np.savez_compressed(a.out, **learnt)
            if "sim_survival" in rec:
                check = offline_check(rec, learnt)
                Path(a.out).with_suffix(".json").write_text(json.dumps(check, indent=1) + "\n")
                print(json.dumps(check, indent=1))
        elif a.cmd == "distil":
            rec = load_recorded(Path(a.rec))
            learnt = dict(np.load(a.learnt)) if a.learnt else None
            tgt, moved = targets(rec, learnt, a.arm, a.margin)
            print(
                f"{a.arm}: {int(moved.sum())} of {len(moved)} targets moved from μ, "
                f"mean |Δ| {float(np.abs(tgt - rec['plans'][:, 0]).mean()):.4f}",
                flush=True,
            )
            weight = None
            if a.weight_by_gain:
                weight = np.clip(1 + gains(rec, learnt, a.arm), 1, 10)
                print(f"weights: mean {weight.mean():.2f}, share > 2: {(weight > 2).mean():.2f}")
            pt = distil(
                load_policy(a.policy), rec, tgt, a.anchor, Path(a.out), a.steps, weight=weight
            )
            to_onnx(pt, Path(a.base_onnx), rec["image"][:8], rec["speed"][:8])
        elif a.cmd == "eval":
            from carrt.policy import OnnxPolicy
            from carrt.shipped import resolve_model

            policy = OnnxPolicy(str(resolve_model(a.onnx)), intra_op_threads=1)
            planner = None
            if a.true_map_planner:
                from research import ground_v2

                planner = TrueMapPlanner(ground_v2.load(Path(a.true_map_planner)).law, a.edge)
            rows = evaluate(
                a.name,
                policy,
                parse_int_list(a.tracks, "tracks"),
                parse_int_list(a.seeds, "seeds"),
                a.seconds,
                Path(a.out),
                planner,
                a.light,
            )
            print(json.dumps({a.name: summarise(rows)}))
        elif a.cmd == "report":
            from research import ground_v2

            offline = json.loads(Path(a.offline).read_text()) if a.offline else None
            payload = report(
                Path(a.eval), ground_v2.load(Path(a.ensemble)).law, offline, Path(a.out)
            )
            print(
                json.dumps({"verdicts": payload["verdicts"], "cells": payload["cells"]}, indent=1)
            )
        return 0
    except UserError as exc:
        print(f"plan_distil: error: {exc}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    raise SystemExit(main())
