"""Refinement by search in imagination: the plan pulled toward the imagined-best alternative.

The paper's refinement follows the gradient of the imagined objective at the policy's plan.
That direction is what the world model knows least: on the counterfactual check (2026-11-24,
3 seeds, counterfactual.py here) the objective's gradient at the plan had the sign of the
true difference 0.47-0.63 of the time (a coin by iteration 3), while the same world models
ordered whole alternatives against the plan as reality did 0.86-0.93 of the time for braking,
lifting and a 0.6 steering shift. Search uses what the model knows: from each start frame the
world model imagines the plan and a fixed set of alternatives (the check's own: steering
shifted by ±0.3 / ±0.6, throttle lifted, a short brake, full throttle), and where one beats
the plan by more than `refine_search_margin` (objective units: one m/s for one step) the
policy's μ is pulled toward it by L1, weighed like imitation's (`refine_w_search`). Where none
does, the plan is its own target and that start adds nothing. No gradient flows through the
world model. σ is not trained (nothing samples with it).

`refine_search` (ResearchConfig) switches it on in place of the gradient; off is the paper's
form. The other safeguards (anchor, imitation on the demonstrations) apply as they do to the
gradient. The check reports how often the search's move is right (`search` in its output),
per margin, so a margin can be chosen on the check's placements rather than the test ones.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from training.refine import sequence_objective

if TYPE_CHECKING:
    from research.variants.config import ResearchConfig

# The alternatives, in the order and with the names of carrt.sim.counterfactual's sequences
# (its "random" left out: a search needs no baseline), so the check can score exactly this set.
STEERING_SHIFTS = (-0.6, -0.3, 0.3, 0.6)
BRAKE_STEPS = 3
BRAKE_THROTTLE = -0.5
SEARCH_SEQUENCES = ("plan", *(f"steer{d:+.1f}" for d in STEERING_SHIFTS), "lift", "brake", "full")


def alternatives(plan: torch.Tensor) -> torch.Tensor:
    """(N, H, 2) plans → (N, K, H, 2) sequences in SEARCH_SEQUENCES order, the plan first."""
    out = [plan]
    for shift in STEERING_SHIFTS:
        seq = plan.clone()
        seq[..., 0] = (seq[..., 0] + shift).clamp(-1.0, 1.0)
        out.append(seq)
    lift, brake, full = plan.clone(), plan.clone(), plan.clone()
    lift[..., 1] = 0.0
    brake[..., 1] = 0.0
    brake[:, :BRAKE_STEPS, 1] = BRAKE_THROTTLE
    full[..., 1] = 1.0
    out += [lift, brake, full]
    return torch.stack(out, dim=1)


def best_moves(objective: torch.Tensor, margin: float) -> torch.Tensor:
    """(N, K) objectives (lower is better, the plan in column 0) → (N,) the chosen column: the
    best one where it beats the plan by more than `margin`, else 0 (stay)."""
    best = objective.argmin(dim=1)
    gain = objective[:, 0] - objective.gather(1, best[:, None])[:, 0]
    return torch.where(gain > margin, best, torch.zeros_like(best))


@torch.no_grad()
def search_targets(world_model, image, speed, plan, score, clip: float, correct: bool, margin):
    """Imagine every alternative from each start; → ((N, H, 2) targets, (N,) chosen column).

    `score` maps imagine()'s output to the (N·K,) sequence objectives (refine.sequence_objective
    with the run's weights)."""
    seqs = alternatives(plan.detach())
    n, k = seqs.shape[:2]  # each start frame encoded once for its k sequences (imagine)
    imagined = world_model.imagine(image, speed, seqs.flatten(0, 1), clip, correct)
    chosen = best_moves(score(imagined).view(n, k), margin)
    return seqs[torch.arange(n, device=seqs.device), chosen], chosen


def search_loss(mu: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Mean |μ − target| over starts, steps and both actions (imitation's L1, unweighted): zero
    and without gradient where the target is the plan itself."""
    return (mu - targets).abs().mean()


def search_step(cfg: ResearchConfig, world_model, batch: dict, actions, mu, weights: tuple):
    """`refine_search`: L1 from μ to the imagined-best alternative (this module).
    0·Σ actions keeps σ in the graph, as imitation does, for DistributedDataParallel."""
    targets, chosen = search_targets(
        world_model, batch["image"], batch["speed"], mu,
        lambda imagined: sequence_objective(imagined, *weights),
        cfg.uncertainty_clip, cfg.collision_prior_correction, cfg.refine_search_margin,
    )  # fmt: skip
    pull = search_loss(mu, targets)
    loss = cfg.refine_w_search * pull + 0.0 * actions.sum()
    return loss, {"search_l1": pull.detach(), "moved": (chosen > 0).float().mean()}
