"""Refinement from what truly happened: advantage-weighted imitation of the car's own drives.

`refine_outcomes` replaces stage 3's imagination with the recorded outcomes of the policy's own
drives. Why: the world models' judgement of the small changes refinement makes is a coin (the
gradient's sign at the plan agreed with the simulator 0.50-0.53 of the time) and no refinement
through them drove better than random moves of the same size (docs/dirl_study.md, "null
candidates"). The iteration's exploration drives already hold what imagination is asked to
predict: the car's own actions, perturbed (noise.during_auto), and the speeds, collisions and
take-overs that followed them, recorded as on a real car (no simulator state).

For each AUTO step t of the drives (the policy, with its exploration noise, chose the action):

    G_t = Σ_{k=1..H} [ w_spd·v_{t+k} − w_coll·c_{t+k} ]

the paper's refinement objective with recorded speeds v (m/s) and collision labels c in place
of imagined ones (a person's take-over counts as a collision: the paper's e-stop = collision).
How good the situation itself is, V(o_t), is a ridge regression of G on the policy's own
features and speed, cross-fitted (each half of the episodes predicted by a fit on the other
half, so a window's own outcome never sets its baseline). The advantage A_t = G_t − V(o_t)
says whether what the car did from there went better or worse than usual from such a place;
the policy imitates the executed actions a_t..a_{t+H−1}, weighted exp(A_t / (τ·std A)) capped
at `outcome_weight_max` (advantage-weighted regression, Peng et al. 2019), plus imitation's L1
on the demonstrations (refine_w_imitation), which keeps μ on the track as in refine.py.

`outcome_advantage` False weighs every window alike: imitation of the noisy drives with no
outcome in it, the control that says whether the advantage carries the signal.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from carrt.interfaces import Mode
from training.data import WindowDataset
from training.imitation import imitation_loss
from training.refine import demonstration_batch, keep_candidate
from training.trainer import RunContext, StageLoop, StageResult, StageSpec

if TYPE_CHECKING:
    from research.variants.config import ResearchConfig

RIDGE = 1.0  # ridge penalty of the value baseline, on standardised features


def window_returns(
    speed: np.ndarray, event: np.ndarray, horizon: int, w_speed: float, w_collision: float
) -> np.ndarray:
    """(n,) G_t = Σ_{k=1..H} w_spd·v_{t+k} − w_coll·event_{t+k} within one episode.

    Past the episode's end the last step repeats when it was no event (a drive that ended on
    time goes on as it was) and counts as standing still otherwise (the car crashed)."""
    n = len(speed)
    if n == 0:
        return np.zeros(0, dtype=np.float64)
    ended_in_event = bool(event[-1])
    pad_v = 0.0 if ended_in_event else float(speed[-1])
    v = np.concatenate([speed.astype(np.float64), np.full(horizon, pad_v)])
    e = np.concatenate([event.astype(np.float64), np.zeros(horizon)])
    per_step = w_speed * v - w_collision * e
    csum = np.concatenate([[0.0], np.cumsum(per_step)])
    t = np.arange(n)
    return csum[t + 1 + horizon] - csum[t + 1]


def cross_fitted_baseline(
    features: np.ndarray, returns: np.ndarray, fold: np.ndarray, ridge: float = RIDGE
) -> np.ndarray:
    """V for every row, each fold predicted by a ridge fit on the other folds (standardised
    features plus an intercept); a single fold is fitted on itself."""
    features = np.asarray(features, dtype=np.float64)
    out = np.empty(len(returns), dtype=np.float64)
    folds = np.unique(fold)
    for f in folds:
        test = fold == f
        train = ~test if len(folds) > 1 else test
        mean, std = features[train].mean(0), features[train].std(0) + 1e-6
        x = (features[train] - mean) / std
        x = np.hstack([x, np.ones((len(x), 1))])
        y = returns[train]
        reg = ridge * np.eye(x.shape[1])
        reg[-1, -1] = 0.0  # the intercept is not shrunk
        coef = np.linalg.solve(x.T @ x + reg, x.T @ y)
        xt = np.hstack([(features[test] - mean) / std, np.ones((int(test.sum()), 1))])
        out[test] = xt @ coef
    return out


def advantage_weights(
    advantage: np.ndarray, temperature: float, weight_max: float, use_advantage: bool = True
) -> np.ndarray:
    """exp(A / (τ·std A)) capped at weight_max; ones without `use_advantage` (the control)."""
    if not use_advantage or len(advantage) == 0:
        return np.ones(len(advantage), dtype=np.float32)
    scale = temperature * max(float(np.std(advantage)), 1e-6)
    return np.minimum(np.exp(np.clip(advantage / scale, -50, 50)), weight_max).astype(np.float32)


class OutcomeDataset(WindowDataset):
    """The drives' AUTO windows: frame t, speed t, the executed actions a_t..a_{t+H−1} as
    targets (`expert_actions`, so imitation_loss reads them), a per-step `weight` that is the
    window's advantage weight on AUTO steps and 0 elsewhere, and the window's real return.
    Events are the collision labels and the 0.5 s before each take-over (override edge)."""

    fields = ("image", "speed", "expert_actions", "action_mask")

    def __init__(self, episodes, horizon: int, w_speed: float, w_collision: float, *, store=None):
        self._w = (float(w_speed), float(w_collision))
        self._auto_masks = [_auto_steps(ep) for ep in episodes]  # read by _build_index
        super().__init__(episodes, horizon, store=store)
        per_step = np.concatenate(
            [self._episode_returns(ep, a) for ep, a in zip(episodes, self._eps, strict=True)]
        )
        self.returns = per_step[self._start.numpy()]  # each window's start, global step
        self.fold = (self.index[:, 0] % 2).astype(np.int64)  # episodes alternate halves
        self._auto = torch.from_numpy(np.concatenate(self._auto_masks).astype(np.float32))
        self.window_weight = torch.ones(len(self.index))

    def _episode_returns(self, ep, a) -> np.ndarray:
        event = np.maximum(a.collision, a.takeover).astype(bool)
        return window_returns(a.speed, event, self.horizon, *self._w)

    def _build_index(self) -> np.ndarray:
        index = [(i, t) for i, auto in enumerate(self._auto_masks) for t in np.flatnonzero(auto)]
        return np.asarray(index, dtype=np.int64).reshape(-1, 2)

    def set_advantage_weights(self, weights: np.ndarray) -> None:
        self.window_weight = torch.as_tensor(np.asarray(weights, dtype=np.float32))

    def get_batch(self, items) -> dict[str, torch.Tensor]:
        batch = super().get_batch(items)
        rows = torch.as_tensor(np.asarray(items, dtype=np.int64).reshape(-1))
        now = self._steps(items)[2]
        batch["expert_actions"] = self._executed[now]
        auto = self._auto[now] * batch["action_mask"]
        batch["weight"] = auto * self.window_weight[rows][:, None]
        return batch


def _auto_steps(ep) -> np.ndarray:
    """Steps where the policy chose the action: mode AUTO and no take-over edge."""
    mode = np.asarray(ep.steps["mode"], dtype=np.int64)
    override = np.asarray(ep.steps["override"], dtype=bool)
    return (mode == int(Mode.AUTO)) & ~override


@torch.no_grad()
def policy_features(policy: nn.Module, dataset: OutcomeDataset, device, batch: int = 256):
    """(N, F) the policy's own features of every window's frame and speed, in eval mode."""
    was_training = policy.training
    policy.eval()
    out = []
    for s in range(0, len(dataset), batch):
        b = dataset.get_batch(np.arange(s, min(s + batch, len(dataset))))
        out.append(policy._encode(b["image"].to(device), b["speed"].to(device)).cpu().numpy())
    policy.train(was_training)
    return np.concatenate(out) if out else np.zeros((0, 0), dtype=np.float32)


def outcome_weights(cfg: ResearchConfig, policy: nn.Module, dataset: OutcomeDataset, device):
    """(weights (N,), diagnostics): the advantage weights of the drives' windows under the
    policy refinement starts from, and how well the baseline explains the returns."""
    features = policy_features(policy, dataset, device)
    returns = dataset.returns
    baseline = cross_fitted_baseline(features, returns, dataset.fold)
    advantage = returns - baseline
    weights = advantage_weights(
        advantage, cfg.outcome_temperature, cfg.outcome_weight_max, cfg.outcome_advantage
    )
    var = float(np.var(returns))
    diagnostics = {
        "windows": len(returns),
        "return_mean": float(np.mean(returns)),
        "return_std": float(np.std(returns)),
        # cross-fitted R² of the baseline: ~0 means V knows nothing and A is the return itself
        "baseline_r2": 1.0 - float(np.var(advantage)) / var if var > 0 else float("nan"),
        "advantage_std": float(np.std(advantage)),
        # Kish's effective sample size of the weights, as a share of the windows
        "effective_share": float(weights.sum() ** 2 / max((weights**2).sum(), 1e-12))
        / max(len(weights), 1),
        "weight_capped_share": float(np.mean(weights >= cfg.outcome_weight_max)),
    }
    return weights, diagnostics


def train_refine_outcomes(
    cfg: ResearchConfig,
    policy: nn.Module,
    dataset: OutcomeDataset,
    ctx: RunContext | None = None,
    *,
    resume: dict | None = None,
    demonstrations=None,
    weights: np.ndarray | None = None,
) -> StageResult:
    """Refine `policy` in place by advantage-weighted imitation of the drives' executed actions
    (dataset), with imitation's L1 on `demonstrations` weighted refine_w_imitation. `weights`:
    the advantage weights computed before the first step (outcome_weights), so a resumed run
    weighs the windows as the first invocation did."""
    ctx = ctx or RunContext()
    device = ctx.dist.device
    policy.to(device)
    if weights is None:
        weights, _ = outcome_weights(cfg, policy, dataset, device)
    dataset.set_advantage_weights(weights)
    demos = demonstrations if cfg.refine_w_imitation and demonstrations is not None else None
    if demos is not None and len(demos) == 0:
        demos = None

    loop = StageLoop(
        StageSpec.of(cfg, "refine"), ctx, dataset=dataset, trainable=policy, forward=policy,
        checkpoint_fields=lambda: {"policy": policy.state_dict(), "world_model": None},
        resume=resume,
    )  # fmt: skip
    optimizer = loop.optimizer
    with loop.running() as steps:
        for step, batch in steps:
            loss, metrics = imitation_loss(loop.model, batch)
            metrics = {"outcome_l1": loss.detach(), **metrics}
            if demos is not None:
                # the policy itself: one forward through DDP's wrapper per step (as refine.py)
                bc, _ = imitation_loss(policy, demonstration_batch(demos, cfg, step, ctx))
                loss = loss + cfg.refine_w_imitation * bc
                metrics["imitation_l1"] = bc.detach()
            loop.check_finite(loss, step)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            clip = loop.clip_and_schedule(step)
            optimizer.step()
            loop.record(step, batch, loss, metrics, clip)
            keep_candidate(cfg, policy, ctx, step + 1)
            loop.checkpoint_or_stop(step)
    return loop.result


def refine_by_outcomes(cfg: ResearchConfig, policy, data, ctx: RunContext, resume, demonstrations):
    """The refinement stage with `refine_outcomes` (research/variants/train.py): the drives'
    windows of the training episodes (data: stage_data.StageData), their weights computed once
    under the policy the stage starts from and kept in OUT/outcome_weights.npy (a resumed run
    reads them back, since the policy it loads has already moved), the diagnostics in
    OUT/outcomes.json."""
    import json
    from pathlib import Path

    from training.config import UsageError

    h = cfg.profile_obj.horizon
    dataset = OutcomeDataset(
        data.train_eps, h, cfg.refine_w_speed, cfg.refine_w_collision, store=data.store
    )
    if len(dataset) == 0 and cfg.refine_steps > 0:
        raise UsageError(
            "refine_outcomes: the training episodes hold no steps the policy drove (AUTO); "
            "give the iteration's drives with --episodes"
        )
    out = Path(cfg.out)
    saved = out / "outcome_weights.npy"
    if resume is not None and saved.is_file():
        weights = np.load(saved)
    else:
        weights, diagnostics = outcome_weights(cfg, policy, dataset, ctx.dist.device)
        if ctx.dist.is_main:
            out.mkdir(parents=True, exist_ok=True)
            np.save(saved, weights)
            (out / "outcomes.json").write_text(json.dumps(diagnostics, indent=1) + "\n")
    return train_refine_outcomes(
        cfg, policy, dataset, ctx, resume=resume, demonstrations=demonstrations, weights=weights
    )
