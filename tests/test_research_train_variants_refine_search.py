"""research.variants.refine_search: refinement that pulls the plan toward the alternative the world
model
imagines best (refine_search), instead of following its gradient at the plan."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from carrt.sim.counterfactual import SEQUENCE_NAMES, sequences  # noqa: E402
from research.variants.config import ResearchConfig  # noqa: E402
from research.variants.refine_search import (  # noqa: E402
    SEARCH_SEQUENCES,
    alternatives,
    best_moves,
    search_step,
)
from training.config import PRESETS  # noqa: E402
from training.data import WindowDataset, compute_normalisation, load_episodes, take  # noqa: E402
from training.models import PolicyNet  # noqa: E402
from training.refine import train_refine  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def test_the_alternatives_are_the_counterfactual_checks_own():
    """The check scores exactly the set the search chooses from (its "random" aside), so its
    `search` numbers are about what refinement does."""
    assert SEQUENCE_NAMES[:-1] == SEARCH_SEQUENCES
    plan = np.random.default_rng(0).uniform(-1, 1, (10, 2)).astype(np.float32)
    checked = sequences(plan, np.random.default_rng(1))[:-1]
    searched = alternatives(torch.from_numpy(plan)[None])[0].numpy()
    np.testing.assert_allclose(searched, checked)


def test_the_plan_moves_only_where_an_alternative_beats_it_by_the_margin():
    objective = torch.tensor([[5.0, 4.0, 3.0], [1.0, 2.0, 3.0], [5.0, 4.9, 6.0]])
    assert best_moves(objective, 0.0).tolist() == [2, 0, 1]
    assert best_moves(objective, 0.5).tolist() == [2, 0, 0]  # a gain of 0.1 is not enough
    assert best_moves(objective, 2.5).tolist() == [0, 0, 0]


class _SteeringRisk(torch.nn.Module):
    """A stand-in world model: constant speed, collision certain when the sequence's mean
    steering is right of −0.2 and impossible left of it, no uncertainty: of the alternatives,
    a steering shift to the left is imagined best wherever the plan steers right of −0.2."""

    horizon = 10

    def __init__(self) -> None:
        super().__init__()
        self.unused = torch.nn.Parameter(torch.zeros(1))

    def freeze(self) -> None:
        self.eval().requires_grad_(False)

    def imagine(self, image, speed, actions, clip, correct):
        risky = (actions[..., 0].mean(dim=1, keepdim=True) > -0.2).float()
        p = risky.expand(-1, actions.shape[1])
        zero = torch.zeros_like(p)
        return {"speed": zero + 1.0, "p_collision": p, "u_image": zero, "u_speed": zero,
                "u_collision": zero}  # fmt: skip


def _setup(sim_episodes):
    episodes = load_episodes([sim_episodes])
    norm = compute_normalisation(episodes)
    windows = WindowDataset(episodes, 10, predict_size=16)
    torch.manual_seed(0)
    cfg = dataclasses.replace(ResearchConfig(profile="tiny"), **PRESETS["tiny"], progress=False)
    policy = PolicyNet(cfg.profile_obj)
    policy.set_normalisation(norm)
    return cfg, policy, windows, norm


def _steering(policy, batch) -> float:
    with torch.no_grad():
        return float(policy.eval()(batch["image"], batch["speed"])[0][..., 0].mean())


def test_search_pulls_the_plan_toward_the_alternative_imagined_best(sim_episodes):
    cfg, policy, windows, norm = _setup(sim_episodes)
    batch = take(windows, range(16))
    before = _steering(policy, batch)
    assert before > -0.2  # the untrained policy steers where the stand-in imagines a crash
    cfg = dataclasses.replace(cfg, refine_search=True, refine_steps=30, refine_batch_size=8,
                              refine_lr=3e-3, refine_w_anchor=0.0)  # fmt: skip
    result = train_refine(cfg, policy, _SteeringRisk(), windows, norm, step_loss=search_step)
    assert result.steps == 30
    assert result.history[0]["moved"] == 1.0  # every start had a safer alternative at first
    after = _steering(policy, batch)
    assert after < before - 0.2, (before, after)
    assert after < -0.2  # now left of the line: the search stops moving it
    assert result.history[-1]["moved"] < 1.0


def test_a_margin_no_alternative_beats_leaves_the_policy_as_it_was(sim_episodes):
    cfg, policy, windows, norm = _setup(sim_episodes)
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    cfg = dataclasses.replace(cfg, refine_search=True, refine_search_margin=1e6, refine_steps=5,
                              refine_batch_size=8, refine_lr=3e-3, refine_w_anchor=0.0)  # fmt: skip
    result = train_refine(cfg, policy, _SteeringRisk(), windows, norm, step_loss=search_step)
    assert all(h["moved"] == 0.0 for h in result.history)
    assert all(torch.equal(before[k], v) for k, v in policy.state_dict().items())
