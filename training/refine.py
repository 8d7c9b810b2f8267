"""Stage 3, policy refinement in the world model's imagination (the paper's "reveries").

From real start frames the policy samples a = μ + σ·ε for H steps (reparameterised, so the
gradient reaches μ and σ), the FROZEN world model imagines the speeds, collision signals and
uncertainties those actions lead to, and the policy descends

    Σ_t [ −w_spd·ŝ_t + w_coll·p̂(collision)_t + w_unc·(u_i + u_s + u_c)_t ]

ŝ is in m/s (de-normalised), p̂ = (e₁+1)/S is the Dirichlet's expected collision probability,
and each uncertainty is clipped at `uncertainty_clip` because u = (1+1/ν)β/(α−1) explodes as
α → 1 and a single such step would otherwise own the whole gradient. w_unc = 0 is the paper's
"-unc" ablation (`--no-uncertainty`).

carrt's safeguards (TrainingConfig's safeguard group; all off is the paper's pure form):

- `collision_prior_correction`: p̂ with the world model's collision class weight divided back
  out of its odds (WorldModel.imagine), so the objective sees a probability, not a weighted one.
- `refine_w_anchor`·Σ_t |μ_t − μ⁰_t|² keeps the plan near the policy refinement started from
  (μ⁰, frozen): a world model wrong about some actions cannot drag the policy far from what it
  learned on real data. The anchor is this refinement's start, so over iterations drift adds up.
- `refine_w_imitation`·(imitation's L1 on a batch of demonstrations, drawn each step) keeps μ
  near what the person did: the objective rewards speed without collisions, not progress along
  the track, and the demonstrations are what says "this is the track".
- `refine_center_gradient` subtracts from the world model's gradient on the sampled actions its
  mean over the batch of start frames: what is left tells each start's plan how to differ from
  the others' (brake before this obstacle); what goes is the part that would move every plan
  alike (a preference that belongs to the track, not to the situation).
- `refine_steering` False keeps the world model's gradient off the steering channel, so only
  the throttle moves through it (True is the paper's form).

What was measured behind each lives in research/ (research/variants/NOTES.md, research/LOG.md).
Other refinements (by search, from recorded outcomes) are research variants: they replace the
loss of one step through `step_loss` (research/variants/).

Frozen means eval() + requires_grad False (WorldModel.freeze()): no parameter moves and the
BatchNorm running statistics stay those learned on real data — in train mode the imagined
batches would overwrite them. The gradient still flows through the world model to the actions.
ε is drawn from a generator seeded by (seed, step, rank), so a resumed run draws the same noise.

The policy itself is refined in eval() mode (our choice; the paper does not say): its BatchNorm
keeps the statistics of the real frames it saw during imitation, the network being optimised
is exactly the one exported to the car, and the objective is not perturbed by the statistics
of each small batch of start frames.
"""

from __future__ import annotations

import copy
from typing import TYPE_CHECKING

import torch
from torch import nn

from training.checkpoint import save_checkpoint
from training.data import take
from training.held_out import held_out
from training.imitation import imitation_loss
from training.models import sample_actions
from training.trainer import RunContext, StageLoop, StageResult, StageSpec, per_rank_batch

if TYPE_CHECKING:
    from training.config import TrainingConfig
    from training.data import Normalisation


class PolicySampler(nn.Module):
    """forward() → (sampled actions, μ), so DistributedDataParallel sees the sampling pass."""

    def __init__(self, policy: nn.Module) -> None:
        super().__init__()
        self.policy = policy

    def forward(self, image, speed, eps):
        mu, sigma = self.policy(image, speed)
        return sample_actions(mu, sigma, eps), mu


def anchor_penalty(mu: torch.Tensor, mu_start: torch.Tensor) -> torch.Tensor:
    """Σ over the horizon of |μ − μ_start|², mean over the batch: how far refinement has moved
    the plan from the policy it started from (the safeguard `refine_w_anchor` weighs)."""
    return (mu - mu_start).pow(2).sum(dim=-1).sum(dim=1).mean()


def sequence_objective(
    imagined: dict[str, torch.Tensor], w_speed: float, w_collision: float, w_uncertainty: float
) -> torch.Tensor:
    """(N,): each imagined sequence's objective, summed over the horizon (lower is better)."""
    u = imagined["u_image"] + imagined["u_speed"] + imagined["u_collision"]
    per_step = (
        -w_speed * imagined["speed"] + w_collision * imagined["p_collision"] + w_uncertainty * u
    )
    return per_step.sum(dim=1)


def refine_objective(
    imagined: dict[str, torch.Tensor], w_speed: float, w_collision: float, w_uncertainty: float
) -> tuple[torch.Tensor, dict]:
    """Sum over the horizon, mean over the batch."""
    metrics = {k: v.detach().mean() for k, v in imagined.items()}
    return sequence_objective(imagined, w_speed, w_collision, w_uncertainty).mean(), metrics


def step_generator(seed: int, step: int, rank: int, stream: int) -> torch.Generator:
    """A generator fixed by (seed, step, rank): a resumed run draws what the uninterrupted one
    did. `stream` (a prime) keeps the ε draws and the demonstration draws independent."""
    return torch.Generator().manual_seed((seed * 1_000_003 + step) * stream + rank)


def action_noise(shape, seed: int, step: int, rank: int, device) -> torch.Tensor:
    """ε of the sampled actions a = μ + σ·ε, drawn by (seed, step, rank)."""
    return torch.randn(shape, generator=step_generator(seed, step, rank, 1009)).to(device)


def demonstration_batch(demos, cfg: TrainingConfig, step: int, ctx: RunContext) -> dict:
    """This rank's share of refine_batch_size demonstration windows, drawn by (seed, step, rank)."""
    gen = step_generator(cfg.seed, step, ctx.dist.rank, 1019)
    size = per_rank_batch(cfg.refine_batch_size, ctx.dist)
    items = torch.randint(len(demos), (size,), generator=gen).tolist()
    return {k: v.to(ctx.dist.device) for k, v in take(demos, items).items()}


def centered(grad: torch.Tensor) -> torch.Tensor:
    """The world model's gradient on the actions (N, H, 2) less its mean over the N starts of
    the batch (per step ahead and per channel): a hook on the sampled actions, so the anchor
    and imitation terms, which reach μ by other paths, are untouched."""
    return grad - grad.mean(dim=0, keepdim=True)


def throttle_only(grad: torch.Tensor) -> torch.Tensor:
    """The world model's gradient on the actions (N, H, 2) with its steering channel zeroed: a
    hook on the sampled actions, so the anchor and imitation terms still reach the steering."""
    return torch.stack([torch.zeros_like(grad[..., 0]), grad[..., 1]], dim=-1)


def imagined_objective(cfg: TrainingConfig, world_model, batch: dict, actions, weights: tuple):
    """The paper's loss: the objective the world model imagines for the sampled actions (its
    gradient centred over the starts with `refine_center_gradient`, kept off the steering
    without `refine_steering`)."""
    if cfg.refine_center_gradient and actions.requires_grad:
        actions.register_hook(centered)
    if not cfg.refine_steering and actions.requires_grad:
        actions.register_hook(throttle_only)
    imagined = world_model.imagine(
        batch["image"], batch["speed"], actions, cfg.uncertainty_clip,
        cfg.collision_prior_correction,
    )  # fmt: skip
    return refine_objective(imagined, *weights)


def uncertainty_weight(cfg: TrainingConfig) -> float:
    return 0.0 if cfg.no_uncertainty else cfg.refine_w_uncertainty


def refine_loss(
    cfg: TrainingConfig, world_model, batch: dict, actions, mu, *, weights: tuple, step: int,
    ctx: RunContext, step_loss=None, start=None, demonstrations=None, policy=None,
):  # fmt: skip
    """The loss of one refinement step: the imagined objective of the sampled actions (the
    paper's, or a research variant's `step_loss`), plus the safeguards' terms: the anchor to
    `start` (the policy refinement began from) and imitation's L1 on a batch of
    `demonstrations`, through `policy` itself."""
    if step_loss is not None:
        loss, metrics = step_loss(cfg, world_model, batch, actions, mu, weights)
    else:
        loss, metrics = imagined_objective(cfg, world_model, batch, actions, weights)
    if start is not None:
        with torch.no_grad():
            mu_start = start(batch["image"], batch["speed"])[0]
        anchor = anchor_penalty(mu, mu_start)
        loss = loss + cfg.refine_w_anchor * anchor
        metrics["anchor"] = anchor.detach()
    if demonstrations is not None:
        # the policy itself, not the loop's model: under torchrun that is DDP's wrapper; the
        # gradient reaches the same parameters and DDP reduces their summed gradient
        bc, _ = imitation_loss(policy, demonstration_batch(demonstrations, cfg, step, ctx))
        loss = loss + cfg.refine_w_imitation * bc
        metrics["imitation_l1"] = bc.detach()
    return loss, metrics


def train_refine(
    cfg: TrainingConfig,
    policy: nn.Module,
    world_model: nn.Module,
    dataset,
    norm: Normalisation,
    ctx: RunContext | None = None,
    *,
    resume: dict | None = None,
    val_dataset=None,
    demonstrations=None,
    step_loss=None,
    start_policy: dict | None = None,
) -> StageResult:
    """Refine `policy` in place against the frozen `world_model` from the dataset's start frames;
    `demonstrations` (an ImitationDataset) feeds the `refine_w_imitation` term. `step_loss(cfg,
    world_model, batch, actions, mu, weights)` → (loss, metrics) replaces the paper's imagined
    objective (a research variant); the safeguard terms are added to either. `start_policy`
    (a state dict): the policy refinement started from, when `resume` continues it (`policy`
    then holds the resumed weights), so the anchor is the same as in a run never stopped."""
    ctx = ctx or RunContext()
    device = ctx.dist.device
    policy.to(device)
    world_model.to(device)
    world_model.freeze()
    horizon = cfg.profile_obj.horizon
    weights = (cfg.refine_w_speed, cfg.refine_w_collision, uncertainty_weight(cfg))
    sampler = PolicySampler(policy)
    # The policy as refinement found it (imitation's, or the previous iteration's), frozen:
    # the anchor term measures every step's plan against it.
    start = copy.deepcopy(policy).eval().requires_grad_(False) if cfg.refine_w_anchor else None
    if start is not None and start_policy is not None:
        start.load_state_dict(start_policy)
    demos = demonstrations if cfg.refine_w_imitation and demonstrations is not None else None
    if demos is not None and len(demos) == 0:
        demos = None  # nothing a person drove in this data: the term has nothing to hold on to
    val_fn = None
    if val_dataset is not None and len(val_dataset) > 0:

        def val_fn() -> dict:
            return held_out_objective(cfg, policy, world_model, val_dataset, device)

    loop = StageLoop(
        StageSpec.of(cfg, "refine"), ctx, dataset=dataset, trainable=policy, forward=sampler,
        checkpoint_fields=lambda: {
            "policy": policy.state_dict(), "world_model": world_model.state_dict()
        },
        resume=resume, val_fn=val_fn,
    )  # fmt: skip
    optimizer = loop.optimizer
    with loop.running() as steps:
        for step, batch in steps:
            eps = action_noise((len(batch["speed"]), horizon, 2), cfg.seed, step, ctx.dist.rank,
                               device)  # fmt: skip
            actions, mu = loop.model(batch["image"], batch["speed"], eps)
            loss, metrics = refine_loss(
                cfg, world_model, batch, actions, mu, weights=weights, step=step, ctx=ctx,
                step_loss=step_loss, start=start, demonstrations=demos, policy=policy,
            )  # fmt: skip
            loop.check_finite(loss, step)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            clip = loop.clip_and_schedule(step)
            optimizer.step()
            loop.record(step, batch, loss, metrics, clip)
            keep_candidate(cfg, policy, ctx, step + 1)
            loop.checkpoint_or_stop(step)
    return loop.result


def keep_candidate(cfg: TrainingConfig, policy: nn.Module, ctx: RunContext, done: int) -> None:
    """Every `refine_candidates_every` steps (on rank 0, in a run that keeps files), the policy
    as it is then, as a checkpoint export and `--init` read (OUT/candidates/refine<step>.pt).
    Why: the imagined objective is not the track, so how many steps of it help can be decided
    by driving the candidates (research/variants/select_by_driving.py)."""
    every = cfg.refine_candidates_every
    if not every or ctx.ckpt_dir is None or not ctx.dist.is_main or done % every:
        return
    fields = {"stage": "refine", "step": done, "optimizer": None, "world_model": None}
    path = ctx.ckpt_dir.parent / "candidates" / f"refine{done}.pt"
    save_checkpoint(path, **{**ctx.common, **fields, "policy": policy.state_dict()})


@torch.no_grad()
def held_out_objective(
    cfg: TrainingConfig, policy, world_model, dataset, device, batch_size=32, limit=256
) -> dict:
    """The refinement objective with ε = 0 (the μ the car would drive) on fixed windows, mean
    over batches (training/held_out.py)."""
    weights = (cfg.refine_w_speed, cfg.refine_w_collision, uncertainty_weight(cfg))

    def measure(batch: dict) -> dict:
        mu, _sigma = policy(batch["image"], batch["speed"])
        imagined = world_model.imagine(
            batch["image"], batch["speed"], mu, cfg.uncertainty_clip,
            cfg.collision_prior_correction,
        )  # fmt: skip
        loss, metrics = refine_objective(imagined, *weights)
        return {k: (v, 1.0) for k, v in {"loss": loss, **metrics}.items()}

    return held_out(
        [policy, world_model], dataset, device, measure, batch_size=batch_size, limit=limit
    )
