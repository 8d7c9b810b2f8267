"""Stage 2, the world model ("Reveries-net"): from image_t, speed_t and the H executed actions,
predict the next H images, speeds and collision signals, each with evidential uncertainty.

L_w = w_i·L_image + w_s·L_speed + w_c·L_collision (the DIRL paper). The input actions are the
EXECUTED actions a (noise included): the world model learns what the car does under the
commands it actually received, which is what the policy's sampled actions stand for during
refinement. Targets are normalised with the run's stored Normalisation (evidential NLLs are
scale-sensitive and NaN-prone on raw pixel values); future images come from the dataset already
resized to profile.predict_size. Collisions are a few percent of the steps, so the collision
class is weighted (config collision_weight; 0 = the inverse frequency in the training data).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from training.augment import mirror_batch
from training.held_out import held_out
from training.losses import evidential_classification_loss, evidential_regression_loss
from training.trainer import RunContext, StageLoop, StageResult, StageSpec

if TYPE_CHECKING:
    from training.config import TrainingConfig
    from training.data import Normalisation


class Targets(nn.Module):
    """Turns a batch's raw futures into the world model's normalised target units (and back)."""

    def __init__(self, norm: Normalisation) -> None:
        super().__init__()
        mean = torch.tensor(norm.image_mean, dtype=torch.float32).view(3, 1, 1)
        std = torch.tensor(norm.image_std, dtype=torch.float32).view(3, 1, 1)
        self.register_buffer("image_mean", mean)
        self.register_buffer("image_std", std)
        self.speed_mean = float(norm.speed_mean)
        self.speed_std = float(norm.speed_std)

    def images(self, uint8_nhwc: torch.Tensor) -> torch.Tensor:
        """(…, P, P, 3) uint8 → (…, 3, P, P) float, normalised like the models' inputs."""
        x = uint8_nhwc.float().div(255.0).movedim(-1, -3)
        return (x - self.image_mean) / self.image_std

    def images_to_unit(self, normalised: torch.Tensor) -> torch.Tensor:
        """Normalised (…, 3, P, P) → (…, P, P, 3) in [0, 1] for display."""
        return (normalised * self.image_std + self.image_mean).clamp(0, 1).movedim(-3, -1)

    def speeds(self, mps: torch.Tensor) -> torch.Tensor:
        return (mps.float() - self.speed_mean) / self.speed_std

    def speeds_to_mps(self, normalised: torch.Tensor) -> torch.Tensor:
        return normalised * self.speed_std + self.speed_mean


def collision_class_weight(labels, max_weight: float = 100.0) -> float:
    """n_safe / n_collision over every step's collision label, in [1, max_weight]."""
    pos = float(np.sum(labels))
    if pos == 0:
        return 1.0
    return float(np.clip((len(labels) - pos) / pos, 1.0, max_weight))


def world_model_loss(
    model: nn.Module,
    batch: dict,
    targets: Targets,
    *,
    w_image: float,
    w_speed: float,
    w_collision: float,
    collision_weight: float,
    evidential_lambda: float,
) -> tuple[torch.Tensor, dict]:
    pred = model(batch["image"], batch["speed"], batch["actions"])
    mask = batch["mask"]
    l_image = evidential_regression_loss(
        targets.images(batch["future_images"]), pred.image, evidential_lambda, mask=mask
    )
    l_speed = evidential_regression_loss(
        targets.speeds(batch["future_speeds"]), pred.speed, evidential_lambda, mask=mask
    )
    onehot = nn.functional.one_hot(batch["collisions"].long(), 2).float()
    weights = torch.tensor([1.0, collision_weight], device=onehot.device)
    l_coll = evidential_classification_loss(onehot, pred.collision, weights, mask=mask)
    loss = w_image * l_image + w_speed * l_speed + w_collision * l_coll
    metrics = {"image": l_image.detach(), "speed": l_speed.detach(), "collision": l_coll.detach()}
    return loss, metrics


def train_world_model(
    cfg: TrainingConfig,
    world_model: nn.Module,
    dataset,
    norm: Normalisation,
    ctx: RunContext | None = None,
    *,
    collision_weight: float = 1.0,
    policy: nn.Module | None = None,
    resume: dict | None = None,
    val_dataset=None,
) -> StageResult:
    """Train `world_model` in place on a WindowDataset of all windows (collisions included).

    `policy` is only carried into the checkpoints (its weights are not touched here).
    """
    ctx = ctx or RunContext()
    device = ctx.dist.device
    world_model.to(device)
    with torch.no_grad():  # imagine() divides it back out of the collision odds
        world_model.collision_class_weight.fill_(float(collision_weight))
    targets = Targets(norm).to(device)
    weights = {
        "w_image": cfg.w_image,
        "w_speed": cfg.w_speed,
        "w_collision": cfg.w_collision,
        "collision_weight": collision_weight,
        "evidential_lambda": cfg.evidential_lambda,
    }

    val_fn = None
    if val_dataset is not None and len(val_dataset) > 0:
        val_fn = lambda: held_out_loss(world_model, val_dataset, targets, weights, device)  # noqa: E731

    def fields() -> dict:
        return {
            "policy": policy.state_dict() if policy is not None else {},
            "world_model": world_model.state_dict(),
        }

    loop = StageLoop(
        StageSpec.of(cfg, "world_model"), ctx, dataset=dataset, trainable=world_model,
        forward=world_model, checkpoint_fields=fields, resume=resume, val_fn=val_fn,
    )  # fmt: skip
    optimizer = loop.optimizer
    with loop.running() as steps:
        for step, batch in steps:
            loss, metrics = world_model_loss(loop.model, mirrored(cfg, batch, step, ctx.dist.rank),
                                             targets, **weights)  # fmt: skip
            loop.check_finite(loss, step)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            clip = loop.clip_and_schedule(step)
            optimizer.step()
            loop.record(step, batch, loss, metrics, clip)
            loop.checkpoint_or_stop(step)
    return loop.result


def mirrored(cfg: TrainingConfig, batch: dict, step: int, rank: int) -> dict:
    """The batch mirrored (`mirror_world_model`), drawn from a generator seeded by (seed, step,
    rank): a resumed run draws what the unstopped one did."""
    if not cfg.mirror_world_model:
        return batch
    gen = torch.Generator().manual_seed((cfg.seed * 1_000_003 + step) * 1013 + rank)
    return mirror_batch(batch, gen)


@torch.no_grad()
def held_out_loss(model, dataset, targets, weights, device, batch_size=32, limit=256) -> dict:
    """The world model's loss and its parts on fixed windows, mean over batches."""

    def measure(batch: dict) -> dict:
        loss, metrics = world_model_loss(model, batch, targets, **weights)
        return {k: (v, 1.0) for k, v in {"loss": loss, **metrics}.items()}

    return held_out([model], dataset, device, measure, batch_size=batch_size, limit=limit)
