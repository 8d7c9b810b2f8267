"""Null candidates (research/null_candidates.py): the start policy moved as far as a refined
candidate moved it, in random directions, so that selection by driving can be judged against
policies that only moved."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from export.parity import sample_frames  # noqa: E402
from research import null_candidates as null  # noqa: E402
from training import checkpoint as ck  # noqa: E402
from training.config import TrainingConfig  # noqa: E402
from training.data import compute_normalisation, load_episodes  # noqa: E402
from training.models import PolicyNet  # noqa: E402


@pytest.fixture(scope="module")
def start_and_like(sim_episodes, tmp_path_factory):
    """A tiny policy checkpoint (untrained: what is measured is how far plans move, not how
    well they drive), and a "refined" copy whose policy head was nudged."""
    episodes = load_episodes([sim_episodes])
    cfg = TrainingConfig(profile="tiny")
    torch.manual_seed(0)
    policy = PolicyNet(cfg.profile_obj)
    norm = compute_normalisation(episodes)
    policy.set_normalisation(norm)
    common = {"config": dataclasses.asdict(cfg), "profile": "tiny", "stage": "imitation",
              "step": 0, "world_model": None, "optimizer": None,
              "normalisation": norm.to_dict(), "data_digest": "test", "iteration": 0,
              "code_version": ck.code_version(),
              "episodes": [ep.name for ep in episodes]}  # fmt: skip
    folder = tmp_path_factory.mktemp("null")
    ck.save_checkpoint(folder / "policy.pt", **common, policy=policy.state_dict())
    gen = torch.Generator().manual_seed(1)
    nudged = {k: v + 0.02 * torch.randn(v.shape, generator=gen) if k.startswith("head") else v
              for k, v in policy.state_dict().items()}  # fmt: skip
    assert any(k.startswith("head") for k in nudged)
    ck.save_checkpoint(folder / "like.pt", **common, policy=nudged)
    return folder / "policy.pt", folder / "like.pt"


def test_null_candidates_move_the_plan_as_far_as_the_like_candidate(
    start_and_like, sim_episodes, tmp_path, one_thread
):
    start, like = start_and_like
    argv = ["--start", str(start), "--like", str(like), "--episodes", str(sim_episodes),
            "--count", "2", "--out", str(tmp_path)]  # fmt: skip
    assert null.main(argv) == 0
    summary = json.loads((tmp_path / "null.json").read_text())
    target = summary["like_move"]["both"]
    assert target > 0 and summary["frames"] > 0
    start_state = ck.load_checkpoint(start)["policy"]
    frames = sample_frames([sim_episodes], max_frames=64)
    plans = []
    for entry in summary["null"]:
        assert abs(entry["move"]["both"] - target) <= 0.02 * target, entry
        policy, ckpt = ck.load_policy(entry["checkpoint"])  # a policy checkpoint like any other
        assert ckpt["profile"] == "tiny"
        moved = ckpt["policy"]
        parameters = dict(policy.named_parameters())
        buffers = [k for k in moved if k not in parameters]  # BatchNorm statistics, normalisation
        assert any("running_" in k for k in buffers) and "image_mean" in buffers
        assert all(torch.equal(moved[k], start_state[k]) for k in buffers)
        assert all(not torch.equal(moved[k], start_state[k]) for k in parameters)
        plans.append(null.plan(policy, frames))
    assert not np.allclose(plans[0], plans[1])  # two directions, not one


def test_bad_input_is_one_line_and_exit_2(start_and_like, sim_episodes, tmp_path, capsys):
    start, like = start_and_like
    common = ["--episodes", str(sim_episodes), "--out", str(tmp_path / "out")]
    cases = {
        "--count must be >= 1": ["--start", str(start), "--like", str(like), "--count", "0"],
        "no such file": ["--start", str(tmp_path / "missing.pt"), "--like", str(like)],
        "nothing to match": ["--start", str(start), "--like", str(start)],
    }
    for expected, argv in cases.items():
        assert null.main([*argv, *common]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and expected in err[0], err


def test_the_throttle_only_candidate_shifts_the_throttle_as_far_and_leaves_the_steering(
    start_and_like, sim_episodes, tmp_path, one_thread
):
    """--throttle-only: one candidate whose mean signed throttle shift is the --like one's
    (within 2 %), with the steering plan and every weight but the head's last bias unchanged."""
    start, like = start_and_like
    argv = ["--start", str(start), "--like", str(like), "--episodes", str(sim_episodes),
            "--out", str(tmp_path), "--throttle-only"]  # fmt: skip
    assert null.main(argv) == 0
    summary = json.loads((tmp_path / "throttle.json").read_text())
    target, made = summary["like_throttle_shift"], summary["throttle"]
    assert target != 0 and abs(made["throttle_shift"] - target) <= 0.02 * abs(target), summary
    policy, ckpt = ck.load_policy(made["checkpoint"])
    start_policy, _ = ck.load_policy(start)
    changed = [k for k, v in ckpt["policy"].items()
               if not torch.equal(v, ck.load_checkpoint(start)["policy"][k])]  # fmt: skip
    assert len(changed) == 1 and changed[0].startswith("head") and changed[0].endswith("bias")
    frames = sample_frames([sim_episodes], max_frames=64)
    moved, before = null.plan(policy, frames), null.plan(start_policy, frames)
    assert np.array_equal(moved[..., 0], before[..., 0])  # steering untouched
    shift = (moved - before)[..., 1]
    assert np.sign(shift.mean()) == np.sign(target) and (np.sign(shift) == np.sign(target)).all()
