"""The report's figures (matplotlib, Agg: no display needed on a training box).

- loss_curves: each stage's loss (and its parts) against the step, so a run that diverged or
  stalled is visible at a glance;
- uncertainty_vs_error: each held-out (window, step) as a point — evidential uncertainty is
  worth its cost in refinement only if it rises where the world model is wrong;
- reveries: the paper's figure — for held-out start frames, the real future frames beside the
  frames the world model predicts under the actions that were executed, and its per-pixel
  uncertainty, with true/predicted speed and p(collision) per step.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch
from torch.utils.data import default_collate

from training.losses import dirichlet_probability, nig_uncertainty

PARTS = {
    "imitation": ("l1_steering", "l1_throttle"),
    "world_model": ("image", "speed", "collision"),
    "refine": ("speed", "p_collision", "u_image", "u_speed", "u_collision"),
}


def loss_curves(histories: dict[str, list[dict]], path: Path) -> Path:
    stages = [s for s, h in histories.items() if h]
    fig, axes = plt.subplots(1, max(1, len(stages)), figsize=(5 * max(1, len(stages)), 3.6))
    axes = np.atleast_1d(axes)
    for ax, stage in zip(axes, stages, strict=False):
        hist = histories[stage]
        steps = [h["step"] for h in hist]
        ax.plot(steps, [h["loss"] for h in hist], color="black", lw=1.6, label="loss")
        val = [(h["step"], h["val_loss"]) for h in hist if "val_loss" in h]
        if val:
            ax.plot(*zip(*val, strict=True), "o--", color="tab:red", ms=3, label="held-out loss")
        # The parts live on their own axis: the refinement loss sums H steps of them.
        right = ax.twinx()
        for i, part in enumerate(p for p in PARTS.get(stage, ()) if any(p in h for h in hist)):
            right.plot(steps, [h.get(part, np.nan) for h in hist], lw=0.8, alpha=0.8,
                       color=f"C{i}", label=part)  # fmt: skip
        ax.set_title(stage.replace("_", " "))
        ax.set_xlabel("step")
        ax.set_ylabel("loss")
        right.set_ylabel("parts", fontsize=8)
        ax.grid(alpha=0.3)
        handles = ax.get_legend_handles_labels()
        more = right.get_legend_handles_labels()
        ax.legend(handles[0] + more[0], handles[1] + more[1], fontsize=7)
    if not stages:
        axes[0].text(0.5, 0.5, "no steps taken", ha="center", va="center")
    fig.tight_layout()
    return _save(fig, path)


def uncertainty_vs_error(arrays: dict, path: Path) -> Path:
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), layout="constrained")
    if arrays and arrays["mask"].sum() > 0:
        m = arrays["mask"] > 0
        step = np.broadcast_to(np.arange(m.shape[1])[None] + 1, m.shape)[m]
        pairs = [
            ("u_speed", np.abs(arrays["speed_pred"] - arrays["speed_true"]), "|speed error| (m/s)"),
            ("u_image", arrays["image_error"], "mean |image error| (normalised)"),
        ]
        for ax, (u, err, label) in zip(axes, pairs, strict=True):
            x = arrays[u][m]
            sc = ax.scatter(x, err[m], c=step, s=6, cmap="viridis", alpha=0.6)
            if x.min() > 0 and x.max() / x.min() > 20:
                ax.set_xscale("log")
            ax.set_xlabel(f"{u} (evidential)")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        fig.colorbar(sc, ax=axes, label="steps ahead")
    else:
        axes[0].text(0.5, 0.5, "no held-out windows", ha="center", va="center")
    return _save(fig, path)


def _pick_windows(dataset, count: int, scan: int = 256) -> list[int]:
    """One window whose future holds a collision (if any), then evenly spread safe ones."""
    picks: list[int] = []
    for i in np.unique(np.linspace(0, len(dataset) - 1, scan).round().astype(int)):
        item = dataset[int(i)]
        if float((item["collisions"] * item["mask"]).max()) > 0.5:
            picks.append(int(i))
            break
    spread = np.linspace(0, len(dataset) - 1, count + 2)[1:-1].round().astype(int).tolist()
    picks += [i for i in spread if i not in picks]
    return picks[:count]


@torch.no_grad()
def reveries(world_model, dataset, device, path: Path, count: int = 2) -> Path:
    """Rows per window: real frames t+1..t+H, predicted γ, per-pixel uncertainty."""
    if len(dataset) == 0:
        fig = plt.figure(figsize=(4, 2))
        fig.text(0.5, 0.5, "no held-out windows", ha="center")
        return _save(fig, path)
    world_model.eval()
    picks = _pick_windows(dataset, count)
    batch = {k: v.to(device) for k, v in default_collate([dataset[i] for i in picks]).items()}
    pred = world_model(batch["image"], batch["speed"], batch["actions"])
    mean, std = world_model.image_mean.squeeze(0), world_model.image_std.squeeze(0)
    frames = (pred.image.gamma * std + mean).clamp(0, 1).movedim(-3, -1).cpu().numpy()
    unc = nig_uncertainty(pred.image).mean(2).cpu().numpy()  # (N, H, P, P)
    speed = world_model.denormalise_speed(pred.speed.gamma[..., 0]).cpu().numpy()
    p_coll = dirichlet_probability(pred.collision)[..., 1].cpu().numpy()
    real = batch["future_images"].cpu().numpy()
    h = real.shape[1]
    fig, axes = plt.subplots(3 * len(picks), h + 1, figsize=(1.3 * (h + 1), 1.45 * 3 * len(picks)))
    axes = np.asarray(axes).reshape(3 * len(picks), h + 1)
    for w in range(len(picks)):
        r = 3 * w
        mask = batch["mask"][w].cpu().numpy()
        axes[r, 0].imshow(batch["image"][w].cpu().numpy())
        axes[r, 0].set_title(f"t  {float(batch['speed'][w]):.2f} m/s", fontsize=7)
        axes[r + 1, 0].text(0.5, 0.5, "predicted\nγ", ha="center", va="center", fontsize=8)
        axes[r + 2, 0].text(0.5, 0.5, "uncertainty\nu_i", ha="center", va="center", fontsize=8)
        vmax = float(np.percentile(unc[w], 99)) or 1.0
        for k in range(h):
            true_speed = float(batch["future_speeds"][w, k, 0])
            crash = "  COLLISION" if batch["collisions"][w, k] > 0.5 else ""
            title = f"t+{k + 1} {true_speed:.2f}{crash}" if mask[k] else f"t+{k + 1} (past end)"
            axes[r, k + 1].imshow(real[w, k])
            axes[r, k + 1].set_title(title, fontsize=6, color="red" if crash else "black")
            axes[r + 1, k + 1].imshow(frames[w, k])
            axes[r + 1, k + 1].set_title(f"{speed[w, k]:.2f} m/s p={p_coll[w, k]:.2f}", fontsize=6)
            axes[r + 2, k + 1].imshow(unc[w, k], cmap="magma", vmin=0, vmax=vmax)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(
        "real future (top) · world model's reverie (middle) · its uncertainty (bottom)", fontsize=9
    )
    fig.tight_layout()
    return _save(fig, path)


def _save(fig, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
