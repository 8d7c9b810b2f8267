"""Held-out metrics: is the world model better than doing nothing, and does it see collisions?

Each number is set beside the baseline that makes it mean something:
- speed: the world model's mean absolute error (m/s) over the next H steps against the
  constant-speed baseline (speed_t predicted for every future step) — a model that cannot beat
  "the car keeps its speed" has not learned the dynamics;
- collision: AUROC of p̂(collision) over all future steps (0.5 = chance), computed by hand
  (Mann–Whitney U with average ranks for ties; no sklearn in the training extra);
- imitation: L1 between μ and a* on the held-out collision-free windows;
- uncertainty: Spearman correlation between each uncertainty and its error — evidential
  uncertainty is only useful to refinement if it is high where the model is wrong.
Windows are taken evenly spaced over the held-out set (up to `limit`), never at random, so two
runs on the same data report comparable numbers.
"""

from __future__ import annotations

import numpy as np
import torch

from training.data import take
from training.losses import dirichlet_probability


def auroc(scores, labels) -> float:
    """P(score of a random positive > score of a random negative), ties counting ½; NaN if a
    class is absent."""
    scores = np.asarray(scores, dtype=np.float64).ravel()
    labels = np.asarray(labels).ravel().astype(bool)
    n_pos = int(labels.sum())
    n_neg = len(labels) - n_pos
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    _, inverse, counts = np.unique(scores, return_inverse=True, return_counts=True)
    average_rank = np.cumsum(counts) - (counts - 1) / 2.0  # 1-based rank, ties averaged
    ranks = average_rank[inverse]
    u = ranks[labels].sum() - n_pos * (n_pos + 1) / 2.0
    return float(u / (n_pos * n_neg))


def spearman(x, y) -> float:
    x = np.asarray(x, dtype=np.float64).ravel()
    y = np.asarray(y, dtype=np.float64).ravel()
    if len(x) < 3:
        return float("nan")

    def ranks(v):
        _, inv, counts = np.unique(v, return_inverse=True, return_counts=True)
        return (np.cumsum(counts) - (counts - 1) / 2.0)[inv]

    rx, ry = ranks(x), ranks(y)
    if rx.std() == 0 or ry.std() == 0:
        return float("nan")
    return float(np.corrcoef(rx, ry)[0, 1])


def spread_indices(n: int, limit: int) -> np.ndarray:
    if n <= limit:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, limit).round().astype(np.int64))


def _batches(dataset, limit: int, batch_size: int, device):
    idx = spread_indices(len(dataset), limit)
    for start in range(0, len(idx), batch_size):
        batch = take(dataset, [int(i) for i in idx[start : start + batch_size]])
        yield {k: v.to(device) for k, v in batch.items()}


@torch.no_grad()
def collect_world_model(world_model, dataset, device, *, limit=2048, batch_size=32) -> dict:
    """Per (window, future step) arrays (N, H): predictions, truths, uncertainties, mask."""
    world_model.eval()
    parts: dict[str, list[np.ndarray]] = {}
    for batch in _batches(dataset, limit, batch_size, device):
        pred = world_model(batch["image"], batch["speed"], batch["actions"])
        u_image, u_speed, u_coll = world_model.uncertainties(pred)
        target = world_model.normalise_image(batch["future_images"])
        got = {
            "speed_pred": world_model.denormalise_speed(pred.speed.gamma[..., 0]),
            "speed_true": batch["future_speeds"][..., 0],
            "speed_now": batch["speed"].expand_as(batch["future_speeds"][..., 0]),
            "p_collision": dirichlet_probability(pred.collision)[..., 1],
            "collision": batch["collisions"],
            "image_error": (pred.image.gamma - target).abs().flatten(2).mean(-1),
            "u_image": u_image,
            "u_speed": u_speed,
            "u_collision": u_coll,
            "mask": batch["mask"],
        }
        for k, v in got.items():
            parts.setdefault(k, []).append(v.float().cpu().numpy())
    return {k: np.concatenate(v) for k, v in parts.items()}


def world_model_metrics(a: dict) -> dict:
    if not a or a["mask"].sum() == 0:
        return {"windows": 0}
    m = a["mask"] > 0
    err = np.abs(a["speed_pred"] - a["speed_true"])
    base = np.abs(a["speed_now"] - a["speed_true"])
    steps = m.shape[1]
    per_step = [
        float(err[:, k][m[:, k]].mean()) if m[:, k].any() else float("nan") for k in range(steps)
    ]
    base_step = [
        float(base[:, k][m[:, k]].mean()) if m[:, k].any() else float("nan") for k in range(steps)
    ]
    mae, base_mae = float(err[m].mean()), float(base[m].mean())
    return {
        "windows": len(m),
        "steps": int(m.sum()),
        "speed_mae_mps": mae,
        "baseline_speed_mae_mps": base_mae,
        "speed_mae_over_baseline": mae / base_mae if base_mae > 0 else float("nan"),
        "speed_mae_per_step": per_step,
        "baseline_mae_per_step": base_step,
        "collision_auroc": auroc(a["p_collision"][m], a["collision"][m] > 0.5),
        "collision_steps": int((a["collision"][m] > 0.5).sum()),
        "image_error": float(a["image_error"][m].mean()),
        "mean_u_image": float(a["u_image"][m].mean()),
        "mean_u_speed": float(a["u_speed"][m].mean()),
        "mean_u_collision": float(a["u_collision"][m].mean()),
        "spearman_u_speed_vs_error": spearman(a["u_speed"][m], err[m]),
        "spearman_u_image_vs_error": spearman(a["u_image"][m], a["image_error"][m]),
    }


STEERING_SHIFT = 0.6  # the counterfactual check's far steering shift


def _shifted(actions: torch.Tensor, steering: float | None = None, throttle: float | None = None):
    """The executed actions with the steering moved by `steering` or the throttle set to
    `throttle` (clamped to the action range)."""
    out = actions.clone()
    if steering is not None:
        out[..., 0] = (out[..., 0] + steering).clamp(-1.0, 1.0)
    if throttle is not None:
        out[..., 1] = throttle
    return out


@torch.no_grad()
def action_response(world_model, dataset, device, *, limit=512, batch_size=32) -> dict:
    """Does the world model's imagination depend on the actions at all? On held-out windows,
    the same start imagined under the executed actions with the steering moved by ±0.6 (mean
    |Δ| of the risk max_t p̂(collision) and of the predicted images, beside the images' error
    under the executed actions), and under full throttle against full braking (mean |Δ|
    speed, m/s). Why: refinement follows how the imagination changes with the actions; a
    collision head that reads only the frame answers 0 here, whatever its AUROC on recorded
    windows. Recorded frames only, so a car's episodes can be checked too."""
    world_model.eval()
    sums = {"steering_risk": 0.0, "steering_image": 0.0, "image_error": 0.0, "throttle_speed": 0.0}
    n = 0
    for batch in _batches(dataset, limit, batch_size, device):
        image, speed, actions = batch["image"], batch["speed"], batch["actions"]
        preds = {name: world_model(image, speed, _shifted(actions, **change)) for name, change in
                 (("left", {"steering": -STEERING_SHIFT}), ("right", {"steering": STEERING_SHIFT}),
                  ("full", {"throttle": 1.0}), ("brake", {"throttle": -1.0}))}  # fmt: skip
        risk = {k: dirichlet_probability(p.collision)[..., 1].amax(dim=1) for k, p in preds.items()}
        executed = world_model(image, speed, actions).image.gamma
        target = world_model.normalise_image(batch["future_images"])
        speed_of = {k: world_model.denormalise_speed(preds[k].speed.gamma[..., 0]) for k in
                    ("full", "brake")}  # fmt: skip
        sums["steering_risk"] += float((risk["right"] - risk["left"]).abs().sum())
        sums["steering_image"] += float(
            (preds["right"].image.gamma - preds["left"].image.gamma).abs().flatten(1).mean(1).sum()
        )
        sums["image_error"] += float((executed - target).abs().flatten(1).mean(1).sum())
        sums["throttle_speed"] += float((speed_of["full"] - speed_of["brake"]).abs().mean(1).sum())
        n += len(image)
    if n == 0:
        return {}
    return {f"response_{k}": v / n for k, v in sums.items()}


@torch.no_grad()
def imitation_metrics(policy, dataset, device, *, limit=2048, batch_size=64) -> dict:
    """L1 between μ and a* over the held-out imitation targets (MANUAL, collision-free)."""
    if dataset is None or len(dataset) == 0:
        return {"imitation_windows": 0}
    policy.eval()
    total = np.zeros(2)
    count = 0.0
    for batch in _batches(dataset, limit, batch_size, device):
        mu, _sigma = policy(batch["image"], batch["speed"])
        # The imitation targets: labelled steps (weight > 0), the episode's last one included.
        w = batch.get("weight", batch["action_mask"])
        mask = (w > 0).to(mu.dtype).unsqueeze(-1)
        total += ((mu - batch["expert_actions"]).abs() * mask).sum(dim=(0, 1)).cpu().numpy()
        count += float(mask.sum())
    return {
        "imitation_windows": min(len(dataset), limit),
        "imitation_l1": float(total.sum() / (2 * count)),
        "imitation_l1_steering": float(total[0] / count),
        "imitation_l1_throttle": float(total[1] / count),
    }


def held_out_metrics(policy, world_model, episodes, profile, device, *, limit: int = 2048,
             takeovers_as_collisions: bool = False):  # fmt: skip
    """(metrics, arrays) on the given (held-out) episodes, the world model's collision labels
    as it was trained on them (takeovers_as_collisions); arrays feed figures.py. Without a
    world model (None: a run of imitation alone) the policy's metrics only, and no arrays."""
    from training.data import FrameStore, ImitationDataset, WindowDataset

    h, size = profile.horizon, profile.predict_size
    store = FrameStore(episodes)
    free = ImitationDataset(episodes, h, store=store)
    policy.to(device)
    metrics = {"episodes": len(episodes), "frames": int(sum(ep.n for ep in episodes))}
    arrays: dict = {}
    if world_model is not None:
        windows = WindowDataset(
            episodes, h, predict_size=size, takeovers_as_collisions=takeovers_as_collisions,
            store=store,
        )  # fmt: skip
        world_model.to(device)
        if len(windows):
            arrays = collect_world_model(world_model, windows, device, limit=limit)
        metrics.update(world_model_metrics(arrays))
        metrics.update(action_response(world_model, windows, device, limit=min(limit, 512)))
    metrics.update(imitation_metrics(policy, free, device, limit=limit))
    return metrics, arrays
