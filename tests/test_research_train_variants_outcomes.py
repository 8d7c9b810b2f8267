"""research/variants/refine_outcomes.py: refinement from the drives' recorded outcomes.

The return of a window is the paper's objective over the next H recorded steps (a take-over
counts as a collision); the baseline is cross-fitted, so a window's own outcome never sets it;
the weights grow with the advantage and are capped; the dataset's targets are the executed
actions of the steps the policy drove, nothing else; refinement pulls the plan toward the
actions that went better, and the uniform control does not; iterate.py runs it as stage 3.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from episode_factory import make_step, write_episode  # noqa: E402

from carrt.episodes.reader import read_episode  # noqa: E402
from carrt.interfaces import Mode  # noqa: E402
from research.variants.config import ResearchConfig  # noqa: E402
from research.variants.refine_outcomes import (  # noqa: E402
    OutcomeDataset,
    advantage_weights,
    cross_fitted_baseline,
    train_refine_outcomes,
    window_returns,
)
from research.variants.train import main  # noqa: E402
from training import checkpoint as ck  # noqa: E402
from training.models import PolicyNet  # noqa: E402
from training.profiles import get_profile  # noqa: E402


def test_a_window_s_return_is_speed_less_events_over_the_next_h_steps():
    speed = np.array([1.0, 2.0, 3.0, 4.0])
    crashed = np.array([0, 0, 0, 1], dtype=bool)
    g = window_returns(speed, crashed, horizon=2, w_speed=1.0, w_collision=10.0)
    # t=2: v3 − 10·event3 + (after the crash the car stands: 0)
    assert g.tolist() == [2 + 3, 3 + 4 - 10, 4 - 10 + 0, 0.0]
    on_time = window_returns(speed, np.zeros(4, dtype=bool), 2, 1.0, 10.0)
    assert on_time.tolist() == [5.0, 7.0, 8.0, 8.0], "a drive that ended on time goes on as it was"


def test_the_baseline_is_cross_fitted_so_a_window_never_sets_its_own():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(400, 3))
    y = 2.0 * x[:, 0] - x[:, 2] + 0.1 * rng.normal(size=400)
    fold = np.arange(400) % 2
    v = cross_fitted_baseline(x, y, fold)
    assert np.corrcoef(v, y)[0, 1] > 0.98, "the baseline learns what the features say"
    changed = y.copy()
    changed[0] += 100.0
    moved = cross_fitted_baseline(x, changed, fold)
    assert moved[0] == pytest.approx(v[0]), "row 0's own return does not enter its baseline"
    assert not np.allclose(moved[fold == 1], v[fold == 1]), "it enters the other half's"


def test_weights_grow_with_the_advantage_are_capped_and_uniform_when_off():
    a = np.array([-2.0, -1.0, 0.0, 1.0, 2.0, 50.0])
    w = advantage_weights(a, temperature=1.0, weight_max=5.0)
    assert np.all(np.diff(w) > 0), "more advantage, more weight"
    assert w[-1] == 5.0 and w[:-1].max() < 5.0 and w.min() > 0
    assert w[2] == pytest.approx(1.0), "no advantage: weight 1"
    assert advantage_weights(a, 1.0, 20.0, use_advantage=False).tolist() == [1.0] * 6


def drive_episode(root, seed: int, n: int = 30, *, override_at: int | None = None,
                  steering=None, speeds=None):  # fmt: skip
    """A drive: AUTO steps, or MANUAL from a take-over at `override_at` on."""
    steps = []
    for i in range(n):
        manual = override_at is not None and i >= override_at
        extra = {}
        if steering is not None:
            extra["executed_action"] = (float(steering), 0.5)
        if speeds is not None:
            extra["speed_mps"] = float(speeds[i])
        steps.append(make_step(i, seed=seed, mode=Mode.MANUAL if manual else Mode.AUTO,
                               override=override_at == i, **extra))  # fmt: skip
    return read_episode(write_episode(root, steps))


def test_the_dataset_targets_the_executed_actions_of_the_steps_the_policy_drove(tmp_path):
    ep = drive_episode(tmp_path, 0, n=20, override_at=12)
    data = OutcomeDataset([ep], horizon=4, w_speed=1.0, w_collision=10.0)
    assert [int(t) for t in data.index[:, 1]] == list(range(12)), "AUTO steps only"
    batch = data.get_batch([10])
    executed = np.asarray(ep.steps["executed_action"], dtype=np.float32)
    assert np.allclose(batch["expert_actions"].numpy(), executed[10:14])
    assert batch["weight"][0].tolist() == [1.0, 1.0, 0.0, 0.0], "the take-over's steps weigh 0"
    # the take-over at step 12 is an event for the 0.5 s before it (steps 8-12)
    speed = np.asarray(ep.steps["speed_mps"], dtype=np.float64)
    event = np.zeros(20)
    event[8:13] = 1
    assert data.returns[3] == pytest.approx(speed[4:8].sum(), rel=1e-5)
    assert data.returns[5] == pytest.approx(speed[6:10].sum() - 10 * 2, rel=1e-5)
    assert data.returns[5] == pytest.approx((speed - 10 * event)[6:10].sum(), rel=1e-5)


def refined_steering(tmp_path, use_advantage: bool) -> float:
    """Drives in which steering +0.8 was followed by speed and −0.8 by standing still; the
    mean first-step steering of the plan after refinement from a fresh policy."""
    eps = []
    for k in range(8):
        good = k % 2 == 0
        speeds = np.full(30, 2.0 if good else 0.1)
        eps.append(drive_episode(tmp_path / str(k), k, steering=0.8 if good else -0.8,
                                 speeds=speeds))  # fmt: skip
    cfg = ResearchConfig(profile="tiny", refine_steps=40, refine_batch_size=16, refine_lr=3e-3,
                         refine_w_imitation=0.0, outcome_advantage=use_advantage,
                         ckpt_every=0, seed=0)  # fmt: skip
    torch.manual_seed(0)
    policy = PolicyNet(get_profile("tiny"))
    data = OutcomeDataset(eps, get_profile("tiny").horizon, 1.0, 10.0)
    train_refine_outcomes(cfg, policy, data)
    with torch.no_grad():
        b = data.get_batch(np.arange(len(data)))
        policy.eval()
        return float(policy(b["image"], b["speed"])[0][:, 0, 0].mean())


def test_refinement_pulls_the_plan_toward_the_actions_that_went_better(tmp_path, one_thread):
    weighted = refined_steering(tmp_path / "a", use_advantage=True)
    uniform = refined_steering(tmp_path / "u", use_advantage=False)
    assert weighted > 0.3, "toward the steering that was followed by speed"
    assert abs(uniform) < 0.25, "without outcomes: the average of what was executed"


SMALL = [
    "--profile", "tiny", "--set", "threads=1", "--set", "progress=false",
    "--set", "imitation_batch_size=8", "--set", "refine_batch_size=4", "--set", "eval_windows=64",
    "--set", "export=false", "--set", "figures=false", "--set", "ckpt_every=2",
]  # fmt: skip


def test_iterate_refines_from_outcomes_as_stage_3(sim_episodes, tmp_path, one_thread):
    """A run with --init and refine_outcomes: no world model trained, the policy moved, the
    diagnostics and the weights (for a resume) written; episodes without drives: one line."""
    first = tmp_path / "il"
    base = ["--set", "world_model_steps=0"]
    assert main(["--episodes", str(sim_episodes), "--out", str(first), *SMALL, *base,
                 "--set", "imitation_steps=4", "--set", "refine_steps=0"]) == 0  # fmt: skip
    out = tmp_path / "outcomes"
    argv = ["--episodes", str(sim_episodes), "--out", str(out), "--init", str(first), *SMALL,
            *base, "--set", "refine_steps=4", "--set", "refine_outcomes=true"]  # fmt: skip
    assert main(argv) == 0
    diagnostics = json.loads((out / "outcomes.json").read_text())
    assert diagnostics["windows"] > 0 and 0 < diagnostics["effective_share"] <= 1
    assert (out / "outcome_weights.npy").is_file()
    before = ck.load_checkpoint(first / "policy.pt")["policy"]
    after = ck.load_checkpoint(out / "policy.pt")
    assert after["stage"] == "refine" and after["step"] == 4
    assert any(not torch.equal(v, before[k]) for k, v in after["policy"].items())
    assert not (out / "checkpoints" / "world_model.pt").exists(), "no world model trained"


def test_outcome_refinement_without_drives_is_one_line_and_exit_2(tmp_path, capsys, one_thread):
    demos = tmp_path / "demos"
    write_episode(demos, [make_step(i, mode=Mode.MANUAL) for i in range(12)])
    write_episode(demos, [make_step(i, seed=1, mode=Mode.MANUAL) for i in range(12)])
    first = tmp_path / "il"
    assert main(["--episodes", str(demos), "--out", str(first), *SMALL, "--set",
                 "val_fraction=0", "--set", "imitation_steps=2", "--set", "world_model_steps=0",
                 "--set", "refine_steps=0"]) == 0  # fmt: skip
    capsys.readouterr()
    rc = main(["--episodes", str(demos), "--out", str(tmp_path / "r"), "--init", str(first),
               *SMALL, "--set", "val_fraction=0", "--set", "world_model_steps=0",
               "--set", "refine_steps=2", "--set", "refine_outcomes=true"])  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "no steps the policy drove" in err[0]
