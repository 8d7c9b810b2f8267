"""Stage 1, imitation learning: the policy's mean μ learns the human's actions a*.

The paper's loss is L1 between μ and a* over the next H steps, on collision-free frames only.
Two details matter and are easy to get wrong:
- the target is a* (what the human commanded), never the executed action a: during
  collection half the time carries injected noise, and a = a* + noise would teach the policy to
  reproduce the noise instead of the recovery the human made against it;
- windows that lead into a collision are left out (WindowDataset(collision_free_only=True)),
  and steps past an episode's end are masked, so the padding never becomes a target.
σ is not trained here (L1 on μ says nothing about it); it keeps its floor-bounded initial value
until refinement samples with it.

Targets are a* of mode-MANUAL steps only (ImitationDataset's per-step `weight`): in AUTO the
sticks are untouched and a* would be "do nothing". A person's take-over from the policy is
MANUAL too, and its steps may weigh more (config intervention_weight). Frames are colour-
jittered per sample (config augment, training/augment.py) because obstacle colours vary by
placement.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import nn

from training.augment import augment_images, mirror_batch
from training.held_out import held_out
from training.trainer import RunContext, StageLoop, StageResult, StageSpec

if TYPE_CHECKING:
    from training.config import TrainingConfig


def imitation_loss(policy: nn.Module, batch: dict) -> tuple[torch.Tensor, dict]:
    """Weighted mean |μ − a*| over steps and both actions.

    The per-step weight is the batch's `weight` (ImitationDataset: 0 where a* is no person's
    command) or else its `action_mask` (1 where step t+k exists): a*_{t+k} is a target for
    k < n − t, the episode's last action included (`mask`, the world model's t+1+k < n, would
    drop it).
    """
    mu, sigma = policy(batch["image"], batch["speed"])
    target = batch["expert_actions"].to(mu.dtype)
    weight = batch.get("weight", batch["action_mask"])
    mask = weight.to(mu.dtype).unsqueeze(-1).expand_as(mu)
    err = (mu - target).abs() * mask
    denom = mask.sum().clamp(min=1e-6)
    steer = err[..., 0].sum() / (mask[..., 0].sum().clamp(min=1e-6))
    throttle = err[..., 1].sum() / (mask[..., 1].sum().clamp(min=1e-6))
    # 0·Σσ keeps every parameter in the graph (σ is finite by construction), so
    # DistributedDataParallel needs no find_unused_parameters should σ get its own head.
    loss = err.sum() / denom + 0.0 * sigma.sum()
    return loss, {"l1_steering": steer.detach(), "l1_throttle": throttle.detach()}


def augmented(cfg: TrainingConfig, batch: dict, step: int, rank: int) -> dict:
    """The batch colour-jittered (`augment`) and mirrored (`mirror_imitation`), each drawn from
    a generator seeded by (seed, step, rank): a resumed run draws what the unstopped one did."""
    if cfg.augment:
        gen = torch.Generator().manual_seed((cfg.seed * 1_000_003 + step) * 1009 + rank)
        image = augment_images(batch["image"].cpu(), gen, hue=cfg.augment_hue,
                               saturation=cfg.augment_saturation,
                               brightness=cfg.augment_brightness,
                               contrast=cfg.augment_contrast)  # fmt: skip
        batch = {**batch, "image": image.to(batch["image"].device)}
    if cfg.mirror_imitation:
        gen = torch.Generator().manual_seed((cfg.seed * 1_000_003 + step) * 1013 + rank)
        batch = mirror_batch(batch, gen)
    return batch


def train_imitation(
    cfg: TrainingConfig,
    policy: nn.Module,
    dataset,
    ctx: RunContext | None = None,
    *,
    resume: dict | None = None,
    val_dataset=None,
) -> StageResult:
    """Train `policy` in place on an ImitationDataset (or a collision-free WindowDataset)."""
    ctx = ctx or RunContext()
    policy.to(ctx.dist.device)
    val_fn = None
    if val_dataset is not None and len(val_dataset) > 0:
        val_fn = lambda: {"loss": held_out_l1(policy, val_dataset, ctx.dist.device)}  # noqa: E731
    loop = StageLoop(
        StageSpec.of(cfg, "imitation"), ctx, dataset=dataset, trainable=policy, forward=policy,
        checkpoint_fields=lambda: {"policy": policy.state_dict(), "world_model": None},
        resume=resume, val_fn=val_fn,
    )  # fmt: skip
    optimizer = loop.optimizer
    with loop.running() as steps:
        for step, batch in steps:
            loss, metrics = imitation_loss(loop.model, augmented(cfg, batch, step, ctx.dist.rank))
            loop.check_finite(loss, step)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            clip = loop.clip_and_schedule(step)
            optimizer.step()
            loop.record(step, batch, loss, metrics, clip)
            loop.checkpoint_or_stop(step)
    return loop.result


@torch.no_grad()
def held_out_l1(
    policy: nn.Module, dataset, device, batch_size: int = 256, limit: int = 512
) -> float:
    """Imitation L1 over (up to `limit`) windows, in eval mode (training/held_out.py).

    Unweighted over the labelled steps (weight > 0), so it reads as an L1 whatever the
    intervention weight; without `weight`, over `action_mask`.
    """

    def measure(batch: dict) -> dict:
        mu, _ = policy(batch["image"], batch["speed"])
        w = batch.get("weight", batch["action_mask"])
        mask = (w > 0).to(mu.dtype).unsqueeze(-1).expand_as(mu)
        return {"l1": (((mu - batch["expert_actions"]).abs() * mask).sum(), mask.sum())}

    got = held_out([policy], dataset, device, measure, batch_size=batch_size, limit=limit)
    return got.get("l1", float("nan"))
