"""research.variants.refine_drift: where refinement moved the plan, and what the world model (and an
ensemble of them) imagined there."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from types import SimpleNamespace  # noqa: E402

from research.variants import refine_drift as rd  # noqa: E402
from research.variants.train import main  # noqa: E402
from training import checkpoint as ck  # noqa: E402
from training.config import TrainingConfig  # noqa: E402
from training.data import Normalisation  # noqa: E402
from training.models import PolicyNet, WorldModel  # noqa: E402


class _ConstantPolicy:
    """μ = (steering, throttle) at every step, whatever the frame."""

    def __init__(self, steering: float, throttle: float, horizon: int = 3) -> None:
        self.mu = torch.tensor([steering, throttle]).expand(horizon, 2)

    def eval(self):
        return self

    def __call__(self, image, speed):
        mu = self.mu.expand(len(image), *self.mu.shape)
        return mu, torch.ones_like(mu)


class _SteeringWorld:
    """Imagined speed = scale·throttle, uncertainty = |steering| per step (u_speed), no risk."""

    def __init__(self, scale: float = 1.0, uncertain: bool = True) -> None:
        self.scale, self.uncertain = scale, uncertain

    def eval(self):
        return self

    def imagine(self, image, speed, actions, clip, correct):
        zero = torch.zeros_like(actions[..., 0])
        u = actions[..., 0].abs() if self.uncertain else zero
        return {"speed": self.scale * actions[..., 1], "p_collision": zero, "u_image": zero,
                "u_speed": u, "u_collision": zero}  # fmt: skip


def _frames(n: int = 4):
    return torch.zeros(n, 8, 8, 3, dtype=torch.uint8), torch.ones(n, 1)


def test_drift_reports_the_move_and_what_the_world_model_imagined_of_it():
    """The plan moved from steering −0.2 to +0.1 (|Δ| 0.3) and throttle 0.9 to 1.0 over 3
    steps: imagined Σ speed +0.3, Σ uncertainty |0.1|·3 − |0.2|·3 = −0.3."""
    image, speed = _frames()
    out = rd.drift(_SteeringWorld(), _ConstantPolicy(-0.2, 0.9), _ConstantPolicy(0.1, 1.0),
                   image, speed, clip=10.0, correct=True)  # fmt: skip
    assert out["moved"]["steering_abs"] == pytest.approx(0.3)
    assert out["moved"]["throttle_abs"] == pytest.approx(0.1)
    assert out["start"]["steering"] == pytest.approx(-0.2)
    assert out["refined"]["throttle"] == pytest.approx(1.0)
    assert out["change"]["speed"] == pytest.approx(0.3)
    assert out["change"]["u_total"] == pytest.approx(-0.3)
    assert out["change"]["p_collision"] == 0.0
    assert out["frames"] == 4 and out["members"] == 1
    assert "speed_spread" not in out["start"]  # one world model: no ensemble spread


def test_members_spread_grows_where_they_disagree():
    """Members that imagine speed as 1×, 2× and 3× the throttle: their spread is std(1, 2, 3)·Σ
    throttle, so it grows with the throttle the plan asks for."""
    image, speed = _frames()
    members = [_SteeringWorld(2.0), _SteeringWorld(3.0)]
    out = rd.drift(_SteeringWorld(1.0), _ConstantPolicy(0.0, 0.5), _ConstantPolicy(0.0, 1.0),
                   image, speed, clip=10.0, correct=True, members=members)  # fmt: skip
    spread = float(torch.tensor([1.0, 2.0, 3.0]).std())
    assert out["members"] == 3
    assert out["start"]["speed_spread"] == pytest.approx(spread * 0.5 * 3)
    assert out["refined"]["speed_spread"] == pytest.approx(spread * 1.0 * 3)
    assert out["start"]["p_collision_spread"] == 0.0


def _run(folder, policy, world_model, norm, cfg):
    common = {"config": dataclasses.asdict(cfg), "profile": "tiny", "stage": "refine",
              "step": 0, "optimizer": None, "normalisation": norm.to_dict(),
              "data_digest": "test", "iteration": 1, "code_version": ck.code_version(),
              "episodes": []}  # fmt: skip
    ck.save_checkpoint(folder / "policy.pt", **common, policy=policy.state_dict(),
                       world_model=None)  # fmt: skip
    ck.save_checkpoint(folder / "world_model.pt", **common, policy=policy.state_dict(),
                       world_model=world_model.state_dict())  # fmt: skip
    return folder


@pytest.fixture
def runs(tmp_path):
    """Two tiny runs (a start and a "refined" copy with a nudged policy head) and a set of
    four frames as the counterfactual check stores them."""
    cfg, norm = TrainingConfig(profile="tiny"), Normalisation()
    torch.manual_seed(0)
    policy, world_model = PolicyNet(cfg.profile_obj), WorldModel(cfg.profile_obj)
    for model in (policy, world_model):
        model.set_normalisation(norm)
    start = _run(tmp_path / "start", policy, world_model, norm, cfg)
    with torch.no_grad():
        for name, p in policy.named_parameters():
            if name.startswith("head"):
                p.add_(0.3)
    refined = _run(tmp_path / "refined", policy, world_model, norm, cfg)
    rng = np.random.default_rng(0)
    frames = {"image": rng.integers(0, 255, (4, 96, 96, 3), dtype=np.uint8),
              "speed": np.ones(4, np.float32), "meta": json.dumps({})}  # fmt: skip
    np.savez(start / "counterfactual.npz", **frames)
    return start, refined, frames


def test_the_command_compares_two_runs_on_the_start_runs_frames(runs, tmp_path, capsys):
    start, refined, _ = runs
    out = tmp_path / "drift.json"
    argv = ["--run", str(refined), "--start", str(start), "--members", str(start)]
    assert rd.main([*argv, "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["frames"] == 4 and result["members"] == 2
    assert result["moved"]["steering_abs"] + result["moved"]["throttle_abs"] > 0
    # the same world model twice: the members cannot disagree
    assert result["refined"]["speed_spread"] == pytest.approx(0.0, abs=1e-6)
    assert "plan moved |Δsteering|" in capsys.readouterr().out


@pytest.mark.parametrize("bad", ["no-run", "not-npz", "nan-speed", "no-world-model"])
def test_bad_input_is_one_line_and_exit_2(runs, tmp_path, capsys, bad):
    start, refined, frames = runs
    argv = ["--run", str(refined), "--start", str(start)]
    if bad == "no-run":
        argv[1] = str(tmp_path / "missing")
    elif bad == "not-npz":
        (tmp_path / "cf.npz").write_text("not a set")
        argv += ["--data", str(tmp_path / "cf.npz")]
    elif bad == "nan-speed":
        np.savez(tmp_path / "cf.npz", **{**frames, "speed": np.full(4, np.nan, np.float32)})
        argv += ["--data", str(tmp_path / "cf.npz")]
    else:
        (refined / "world_model.pt").write_bytes(b"junk")
    assert rd.main(argv) == 2
    err = capsys.readouterr().err
    assert (
        err.startswith("python -m research.variants.refine_drift: error: ") and err.count("\n") == 1
    )


SMALL = [
    "--profile", "tiny", "--set", "threads=1", "--set", "progress=false",
    "--set", "imitation_batch_size=8", "--set", "world_model_batch_size=4",
    "--set", "refine_batch_size=4", "--set", "eval_windows=64",
]  # fmt: skip
QUICK = [*SMALL, "--set", "export=false", "--set", "figures=false", "--set", "ckpt_every=2"]


def steps(imitation: int, world_model: int, refine: int) -> list[str]:
    return ["--set", f"imitation_steps={imitation}", "--set", f"world_model_steps={world_model}",
            "--set", f"refine_steps={refine}"]  # fmt: skip


@pytest.fixture(scope="module")
def iteration1(sim_episodes, tmp_path_factory):
    """One iteration through research/variants/train.py (carrt-train with the variants)."""
    out = tmp_path_factory.mktemp("runs") / "iter1"
    before = torch.get_num_threads()
    rc = main(["--episodes", str(sim_episodes), "--out", str(out), *QUICK, *steps(6, 6, 4)])
    torch.set_num_threads(before)
    return rc, out


def test_the_report_says_where_refinement_moved_the_plan(iteration1, sim_episodes, tmp_path):
    """From the world-model stage's policy in iteration 1, from --init's policy in a run that
    only refines; a run that refines nothing has no such section."""
    _, first = iteration1
    record = json.loads((first / "metrics.json").read_text())["refine_drift"]
    assert record["frames"] > 0 and record["members"] == 1
    before = ck.load_policy(first / "checkpoints" / "world_model.pt")[0]
    after = ck.load_policy(first / "policy.pt")[0]
    moved_weights = after.state_dict()
    changed = any(not torch.equal(v, moved_weights[k]) for k, v in before.state_dict().items())
    assert changed == (record["moved"]["steering_abs"] + record["moved"]["throttle_abs"] > 0)
    assert "## Where refinement moved the plan" in (first / "report.md").read_text()
    for refine, has in ((2, True), (0, False)):
        out = tmp_path / f"refine{refine}"
        argv = ["--episodes", str(sim_episodes), "--out", str(out), "--init", str(first)]
        assert main([*argv, *QUICK, *steps(0, 0, refine)]) == 0
        record = json.loads((out / "metrics.json").read_text())["refine_drift"]
        assert (record is not None) == has
        if has:  # no earlier stage in this run: the start is --init's policy
            start = rd.policy_before_refinement(SimpleNamespace(init=str(first)), out)
            init = ck.load_checkpoint(first / "policy.pt")["policy"]
            assert all(torch.equal(v, init[k]) for k, v in start.state_dict().items())


def test_carrt_train_itself_reports_no_drift(sim_episodes, tmp_path):
    """The product's carrt-train runs without the research variants: no drift section."""
    from training.one_run import main as carrt_train

    out = tmp_path / "run"
    argv = ["--episodes", str(sim_episodes), "--out", str(out), *QUICK, *steps(2, 2, 2)]
    assert carrt_train(argv) == 0
    assert "refine_drift" not in json.loads((out / "metrics.json").read_text())
    assert "## Where refinement moved the plan" not in (out / "report.md").read_text()
