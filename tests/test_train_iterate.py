"""training/iterate.py end to end on the simulator's episodes (tiny profile, a handful of steps).

One iteration writes the policy, the world model, checkpoints, report.md with held-out metrics,
figures and an ONNX policy carrt loads; the next iteration starts from it; an interrupted run
resumes exactly where it stopped; torchrun with two gloo processes trains the same way; bad
input is one line and exit status 2.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from training import checkpoint as ck  # noqa: E402
from training.data import load_episodes  # noqa: E402
from training.iterate import main  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SMALL = [
    "--profile", "tiny", "--set", "threads=1", "--set", "progress=false",
    "--set", "imitation_batch_size=8", "--set", "world_model_batch_size=4",
    "--set", "refine_batch_size=4", "--set", "eval_windows=64",
]  # fmt: skip


@pytest.fixture(autouse=True)
def restore_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def steps(imitation: int, world_model: int, refine: int) -> list[str]:
    return ["--set", f"imitation_steps={imitation}", "--set", f"world_model_steps={world_model}",
            "--set", f"refine_steps={refine}"]  # fmt: skip


QUICK = [*SMALL, "--set", "export=false", "--set", "figures=false", "--set", "ckpt_every=2"]


@pytest.fixture(scope="module")
def iteration1(sim_episodes, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "iter1"
    before = torch.get_num_threads()
    rc = main(["--episodes", str(sim_episodes), "--out", str(out), *SMALL, *steps(6, 6, 4)])
    torch.set_num_threads(before)
    return rc, out


def test_iteration_writes_policy_report_figures_and_onnx(iteration1, sim_episodes):
    rc, out = iteration1
    assert rc == 0
    for name in ("policy.pt", "world_model.pt", "report.md", "metrics.json", "policy.onnx"):
        assert (out / name).is_file(), name
    assert {p.name for p in (out / "checkpoints").iterdir()} == {
        "imitation.pt",
        "world_model.pt",
        "refine.pt",
    }
    assert any((out / "tensorboard").iterdir())

    policy, saved = ck.load_policy(out / "policy.pt")
    assert saved["stage"] == "refine" and saved["step"] == 4 and saved["iteration"] == 1
    assert saved["optimizer"] is None and saved["world_model"] is None
    assert ck.load_checkpoint(out / "world_model.pt")["world_model"] is not None

    report = (out / "report.md").read_text()
    for needle in ("speed MAE", "constant speed", "collision AUROC", "imitation L1",
                   "training data digest", "held out", "to steering ±0.6"):  # fmt: skip
        assert needle in report, needle
    for png in ("loss_curves.png", "uncertainty_vs_error.png", "reveries.png"):
        assert (out / "figures" / png).stat().st_size > 10_000
        assert f"](figures/{png})" in report  # relative links
    record = json.loads((out / "metrics.json").read_text())
    m = record["metrics"]
    assert m["held_out"] and m["windows"] > 0
    assert np.isfinite(m["speed_mae_mps"]) and np.isfinite(m["baseline_speed_mae_mps"])
    assert np.isfinite(m["imitation_l1"])
    assert m["response_steering_image"] >= 0 and m["response_throttle_speed"] >= 0
    if m["collision_steps"] > 0:  # which episodes are held out depends on their names
        assert 0.0 <= m["collision_auroc"] <= 1.0
    else:
        assert m["collision_auroc"] is None  # NaN is written as null
    assert record["stages"]["imitation"]["steps"] == 6
    assert record["data"]["episodes"] == 7
    # the export ran as carrt-export's process; its report is in metrics.json and report.md
    import hashlib

    assert (
        record["export"]["sha256"] == hashlib.sha256((out / "policy.onnx").read_bytes()).hexdigest()
    )
    assert f"wrote {out / 'policy.onnx'}" in report and "parity" in report

    from carrt.policy import OnnxPolicy

    onnx_policy = OnnxPolicy(out / "policy.onnx")
    assert onnx_policy.horizon == 10
    assert onnx_policy.metadata["carrt.iteration"] == "1"
    assert onnx_policy.metadata["carrt.training_data_digest"] == saved["data_digest"]
    from carrt.episodes.reader import list_episodes, read_episode

    ep = read_episode(list_episodes(sim_episodes)[0])
    frame, speed = np.array(ep.frames[3]), float(ep.steps["speed_mps"][3])
    with torch.no_grad():
        mu, _ = policy(torch.from_numpy(frame)[None], torch.tensor([[speed]]))
    assert np.allclose(onnx_policy.predict(frame, speed).mu, mu[0].numpy(), atol=1e-4)


def test_next_iteration_starts_from_the_previous_one(iteration1, sim_episodes, tmp_path):
    _, prev = iteration1
    out = tmp_path / "iter2"
    argv = ["--episodes", str(sim_episodes), "--out", str(out), "--init", str(prev)]
    assert main([*argv, *QUICK, *steps(6, 2, 2)]) == 0
    assert not (out / "checkpoints" / "imitation.pt").exists()  # imitation runs once
    saved = ck.load_checkpoint(out / "policy.pt")
    assert saved["iteration"] == 2 and saved["profile"] == "tiny"  # profile taken from --init
    first = ck.load_checkpoint(prev / "policy.pt")
    assert saved["normalisation"] == first["normalisation"]
    wm = ck.load_checkpoint(out / "checkpoints" / "world_model.pt")
    assert [h["step"] for h in wm["history"]] == [1, 2]
    assert "iteration 2" in (out / "report.md").read_text()


def test_a_fresh_world_model_starts_from_its_own_initialisation_not_inits(
    iteration1, sim_episodes, tmp_path
):
    """world_model_fresh (an ensemble member): the policy still comes from --init, the world
    model from its seeded initialisation; without it both come from --init."""
    _, prev = iteration1
    before = ck.load_checkpoint(prev / "world_model.pt")["world_model"]
    saved = {}
    for fresh in (False, True):
        out = tmp_path / f"fresh-{fresh}"
        argv = ["--episodes", str(sim_episodes), "--out", str(out), "--init", str(prev)]
        flag = ["--set", f"world_model_fresh={str(fresh).lower()}", "--seed", "7"]
        assert main([*argv, *QUICK, *steps(0, 0, 0), *flag]) == 0
        saved[fresh] = ck.load_checkpoint(out / "world_model.pt")
    first = ck.load_checkpoint(prev / "policy.pt")["policy"]
    for ckpt in saved.values():
        assert all(torch.equal(v, first[k]) for k, v in ckpt["policy"].items())
    assert all(torch.equal(v, before[k]) for k, v in saved[False]["world_model"].items())
    differ = [k for k, v in saved[True]["world_model"].items() if not torch.equal(v, before[k])]
    assert any(k.startswith("gru") for k in differ), "the fresh one is not --init's"


def test_reimitate_learns_again_from_the_previous_policy_before_the_world_model(
    iteration1, sim_episodes, tmp_path
):
    """reimitate (the study's take-overs): a later iteration first learns by imitation, from
    the previous policy and with its input scaling, and the world model and refinement start
    from what that imitation made."""
    _, prev = iteration1
    out = tmp_path / "iter2"
    argv = ["--episodes", str(sim_episodes), "--out", str(out), "--init", str(prev)]
    assert main([*argv, *QUICK, *steps(6, 2, 2), "--set", "reimitate=true"]) == 0
    imitated = ck.load_checkpoint(out / "checkpoints" / "imitation.pt")
    first = ck.load_checkpoint(prev / "policy.pt")
    assert imitated["step"] == 6 and imitated["iteration"] == 2
    assert imitated["normalisation"] == first["normalisation"], "the previous policy's scaling"
    changed = [k for k, v in imitated["policy"].items() if not torch.equal(v, first["policy"][k])]
    assert changed, "imitation trained the previous policy further"
    wm = ck.load_checkpoint(out / "checkpoints" / "world_model.pt")
    assert all(torch.equal(v, imitated["policy"][k]) for k, v in wm["policy"].items())


def test_world_episodes_teach_the_world_model_and_refinement_starts_from_episodes(
    iteration1, sim_episodes, tmp_path, monkeypatch
):
    """--world-episodes: the world model learns those episodes (weight for weight what a run
    on them alone learns), and refinement starts from --episodes' states in that world model."""
    import shutil

    from training import refine

    _, prev = iteration1
    world = tmp_path / "sloppy"
    for ep in sorted(p for p in sim_episodes.iterdir() if p.is_dir())[-4:]:
        shutil.copytree(ep, world / ep.name)
    starts = []
    real = refine.train_refine

    def recording(cfg, policy, world_model, windows, *a, **kw):
        starts.append(
            (set(windows.names), {k: v.clone() for k, v in world_model.state_dict().items()})
        )
        return real(cfg, policy, world_model, windows, *a, **kw)

    monkeypatch.setattr(refine, "train_refine", recording)
    one = tmp_path / "one-run"
    argv = ["--episodes", str(sim_episodes), "--world-episodes", str(world), "--init", str(prev)]
    assert main([*argv, "--out", str(one), *QUICK, *steps(0, 3, 2)]) == 0
    world_run = tmp_path / "world-run"
    argv = ["--episodes", str(world), "--out", str(world_run), "--init", str(prev)]
    assert main([*argv, *QUICK, *steps(0, 3, 0)]) == 0

    learnt = ck.load_checkpoint(world_run / "world_model.pt")["world_model"]
    saved = ck.load_checkpoint(one / "world_model.pt")["world_model"]
    assert all(torch.equal(v, learnt[k]) for k, v in saved.items())
    names, refined_in = starts[0]  # the one run's (the world-model run calls it for 0 steps)
    assert all(torch.equal(v, learnt[k]) for k, v in refined_in.items())
    policy_eps = {p.name for p in sim_episodes.iterdir() if p.is_dir()}
    assert names <= policy_eps and names - {p.name for p in world.iterdir()}
    record = json.loads((one / "metrics.json").read_text())["data"]
    learnt_eps = load_episodes([str(world)])
    assert record["world_model_episodes"]["episodes"] == len(learnt_eps) > 0
    assert record["world_model_episodes"]["frames"] == sum(ep.n for ep in learnt_eps)
    assert "--world-episodes" in (one / "report.md").read_text()


def test_an_interrupted_run_resumes_where_it_stopped(sim_episodes, tmp_path, capsys):
    argv = ["--episodes", str(sim_episodes), *QUICK, *steps(4, 4, 4)]
    straight = tmp_path / "straight"
    assert main([*argv, "--out", str(straight)]) == 0

    out = tmp_path / "interrupted"
    capsys.readouterr()
    assert main([*argv, "--out", str(out), "--set", "stop_after=5"]) == 0
    assert "run the same command to resume" in capsys.readouterr().out
    assert not (out / "policy.pt").exists()
    assert ck.load_checkpoint(out / "checkpoints" / "imitation.pt")["step"] == 4
    assert ck.load_checkpoint(out / "checkpoints" / "world_model.pt")["step"] == 1
    imitation_bytes = (out / "checkpoints" / "imitation.pt").read_bytes()

    assert main([*argv, "--out", str(out)]) == 0
    assert (out / "checkpoints" / "imitation.pt").read_bytes() == imitation_bytes  # not redone
    wm = ck.load_checkpoint(out / "checkpoints" / "world_model.pt")
    assert wm["step"] == 4 and [h["step"] for h in wm["history"]] == [1, 2, 3, 4]
    resumed = ck.load_checkpoint(out / "policy.pt")
    reference = ck.load_checkpoint(straight / "policy.pt")
    assert resumed["step"] == 4
    for k, v in reference["policy"].items():  # bit-identical to the run that never stopped
        assert torch.equal(v, resumed["policy"][k]), k


def test_two_processes_with_gloo(sim_episodes, tmp_path):
    out = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "training/iterate.py", "--episodes", str(sim_episodes), "--out", str(out),
           *QUICK, *steps(3, 3, 2)]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
    record = json.loads((out / "metrics.json").read_text())
    assert record["world_size"] == 2
    assert ck.load_checkpoint(out / "policy.pt")["step"] == 2
    assert len(list((out / "tensorboard").iterdir())) == 1  # only rank 0 writes
    assert proc.stdout.count("wrote ") == 1


@pytest.mark.parametrize(
    "args, message",
    [
        (["--out", "{tmp}/o", "--episodes", "{tmp}/missing"], "no such directory"),
        (["--out", "{tmp}/o", "--episodes", "{tmp}"], "no episodes"),
        (["--out", "{tmp}/o", "--episodes", "{sim}", "--profile", "huge"], "unknown profile"),
        (["--out", "{tmp}/o", "--episodes", "{sim}", "--set", "nosuch=1"], "unknown field"),
        (["--out", "{tmp}/o", "--episodes", "{sim}", "--set", "seed=abc"], "not a valid int"),
        (["--out", "{tmp}/o", "--episodes", "{sim}", "--set", "refine_lr=0"], "refine_lr"),
        (["--out", "{tmp}/o", "--episodes", "{sim}", "--set", "novalue"], "field=value"),
        (
            ["--out", "{tmp}/o", "--episodes", "{sim}", "--set", "refine_search=true"],
            "research variant",
        ),
        (["--episodes", "{sim}"], "--out"),
        (["--out", "{tmp}/o", "--episodes", "{sim}", "--device", "gpu"], "not a device"),
        (["--out", "{tmp}/o", "--episodes", "{sim}", "--init", "{tmp}/nothing"], "--init"),
        (
            ["--out", "{tmp}/o", "--episodes", "{sim}", "--world-episodes", "{tmp}/missing"],
            "--world-episodes {tmp}/missing: no such directory",
        ),
        (["--out", "{tmp}/o", "--episodes", "{sim}", "--world-episodes", "{tmp}"], "no episodes"),
        (
            [
                "--out",
                "{tmp}/o",
                "--episodes",
                "{sim}",
                "--world-episodes",
                "{sim}",
                "--set",
                "world_model_steps=0",
            ],
            "world_model_steps is 0",
        ),
    ],
)
def test_bad_input_is_one_line_and_exit_2(args, message, sim_episodes, tmp_path, capsys):
    argv = [a.format(tmp=tmp_path, sim=sim_episodes) for a in args]
    assert main(argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and message.format(tmp=tmp_path) in lines[0], captured.err
    assert captured.out == ""


def test_resuming_into_a_run_of_another_profile_is_refused(iteration1, sim_episodes, capsys):
    _, out = iteration1
    assert main(["--episodes", str(sim_episodes), "--out", str(out), "--profile", "cpu"]) == 2
    assert "holds a run with profile tiny" in capsys.readouterr().err


def test_resume_ignores_checkpoints_stale_behind_an_unfinished_stage(tmp_path):
    common = {"config": {}, "policy": {}, "world_model": None, "optimizer": None,
              "normalisation": {}, "iteration": 1, "code_version": "x", "episodes": []}  # fmt: skip
    for stage in ("imitation", "world_model", "refine"):
        ck.save_checkpoint(tmp_path / f"{stage}.pt", **common, profile="tiny", data_digest="d",
                           stage=stage, step=4)  # fmt: skip

    def plan(imitation, world_model=4, refine=4, digest="d"):
        targets = {"imitation": imitation, "world_model": world_model, "refine": refine}
        return list(ck.resumable(tmp_path, targets, profile="tiny", digest=digest))

    assert plan(4) == ["imitation", "world_model", "refine"]
    assert plan(8) == ["imitation"]  # imitation raised to 8: the later stages are stale
    (tmp_path / "imitation.pt").unlink()
    assert plan(0) == ["world_model", "refine"]  # a skipped stage leaves no checkpoint
    assert plan(4) == []
    with pytest.raises(ck.CheckpointError, match="other episodes"):
        plan(0, digest="other")


def test_script_mode_reports_bad_input_in_one_line(tmp_path):
    cmd = [sys.executable, "training/iterate.py", "--episodes", str(tmp_path), "--out",
           str(tmp_path / "o"), "--profile", "nope"]  # fmt: skip
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "carrt-train: error: unknown profile 'nope'; choose one of tiny, cpu, paper"
    ]


def test_a_refused_export_fails_the_run_in_one_report_line(sim_episodes, tmp_path, capsys):
    """The export runs as a process (training/ never imports export/); its refusal is the
    run's exit status 1, policy.pt kept, the reason in the report."""
    out = tmp_path / "refused"
    argv = ["--episodes", str(sim_episodes), "--out", str(out), *SMALL, *steps(2, 0, 0),
            "--set", "figures=false"]  # fmt: skip
    (out / "policy.onnx").mkdir(parents=True)  # a directory where the file must go
    assert main(argv) == 1
    said = capsys.readouterr().out
    assert "export FAILED: " in said and (out / "policy.pt").is_file()
    assert "export FAILED: " in (out / "report.md").read_text()
