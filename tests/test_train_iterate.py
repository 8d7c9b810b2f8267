"""training/iterate.py end to end on the simulator's episodes (tiny profile, a handful of steps).

One iteration is imitation alone: the policy, its checkpoint, report.md with held-out metrics,
figures and an ONNX policy carrt loads, and no world model anywhere. --dirl adds OUT/refined/
(the world model, refinement, their report) beside it and leaves OUT/policy.onnx byte for byte,
printing its measured status once; the numbers in that line are the committed results'. The
next iteration is a take-over round from it; an interrupted run resumes exactly where it
stopped; torchrun with two gloo processes trains the same way; bad input is one line and exit
status 2.
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
from training.iterate import DIRL_MEASURED, DIRL_STATUS, main  # noqa: E402

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
def runs(sim_episodes, tmp_path_factory):
    """One iteration as carrt-train runs it by default (imitation alone, export and figures on),
    what it wrote then, and the same command again with --dirl into the same folder."""
    out = tmp_path_factory.mktemp("runs") / "iter1"
    before = torch.get_num_threads()
    argv = ["--episodes", str(sim_episodes), "--out", str(out), *SMALL, *steps(6, 6, 4)]
    rc = main(argv)
    plain = {
        "rc": rc,
        "files": sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()),
        "report": (out / "report.md").read_text(),
        "metrics": json.loads((out / "metrics.json").read_text()),
        "onnx": (out / "policy.onnx").read_bytes(),
    }
    with _captured() as said:
        rc = main([*argv, "--dirl"])
    torch.set_num_threads(before)
    return out, plain, {"rc": rc, "said": said.getvalue()}


class _captured:
    """stdout of a block (the module fixture cannot take capsys)."""

    def __enter__(self):
        import contextlib
        import io

        self.buffer = io.StringIO()
        self._redirect = contextlib.redirect_stdout(self.buffer)
        self._redirect.__enter__()
        return self.buffer

    def __exit__(self, *exc):
        self._redirect.__exit__(*exc)


def test_a_run_is_imitation_alone_and_writes_no_world_model(runs, sim_episodes):
    out, plain, _ = runs
    assert plain["rc"] == 0
    for name in ("policy.pt", "report.md", "metrics.json", "policy.onnx"):
        assert name in plain["files"], name
    assert "world_model.pt" not in plain["files"]
    assert [f for f in plain["files"] if f.startswith("checkpoints/")] == [
        "checkpoints/imitation.pt"
    ]
    assert not any(f.startswith("refined/") for f in plain["files"])
    assert any((out / "tensorboard").iterdir())

    policy, saved = ck.load_policy(out / "policy.pt")
    assert saved["stage"] == "imitation" and saved["step"] == 6 and saved["iteration"] == 0
    assert saved["optimizer"] is None and saved["world_model"] is None

    report = plain["report"]
    for needle in ("imitation L1", "training data digest", "held out", "imitation"):
        assert needle in report, needle
    for absent in ("world model", "world_model", "speed MAE", "AUROC", "Reveries", "refine"):
        assert absent not in report, absent
    assert (out / "figures" / "loss_curves.png").stat().st_size > 10_000
    assert "](figures/loss_curves.png)" in report  # relative links
    assert [f for f in plain["files"] if f.startswith("figures/")] == ["figures/loss_curves.png"]
    record = plain["metrics"]
    m = record["metrics"]
    assert m["held_out"] and np.isfinite(m["imitation_l1"])
    assert not any(k.startswith(("speed_", "collision_", "response_", "spearman")) for k in m)
    assert list(record["stages"]) == ["imitation"] and record["stages"]["imitation"]["steps"] == 6
    assert record["data"]["episodes"] == 7
    # the export ran as carrt-export's process; its report is in metrics.json and report.md
    import hashlib

    assert record["export"]["sha256"] == hashlib.sha256(plain["onnx"]).hexdigest()
    assert f"wrote {out / 'policy.onnx'}" in report and "parity" in report

    from carrt.policy import OnnxPolicy

    onnx_policy = OnnxPolicy(out / "policy.onnx")
    assert onnx_policy.horizon == 10
    assert onnx_policy.metadata["carrt.iteration"] == "0"
    assert onnx_policy.metadata["carrt.training_data_digest"] == saved["data_digest"]
    from carrt.episodes.reader import list_episodes, read_episode

    ep = read_episode(list_episodes(sim_episodes)[0])
    frame, speed = np.array(ep.frames[3]), float(ep.steps["speed_mps"][3])
    with torch.no_grad():
        mu, _ = policy(torch.from_numpy(frame)[None], torch.tensor([[speed]]))
    assert np.allclose(onnx_policy.predict(frame, speed).mu, mu[0].numpy(), atol=1e-4)


def test_dirl_writes_the_refined_policy_beside_the_imitated_one_never_over_it(runs):
    """--dirl: the status line once; OUT/refined/ is the world model and refinement's run (its
    report with the world model's held-out metrics); OUT/policy.onnx is byte for byte the
    imitation export, and OUT/report.md says how far refinement moved the plan."""
    out, plain, dirl = runs
    assert dirl["rc"] == 0
    said = dirl["said"]
    assert said.count(DIRL_STATUS) == 1 and said.count("not validated") == 1
    assert (out / "policy.onnx").read_bytes() == plain["onnx"]
    assert not (out / "world_model.pt").exists()
    assert ck.load_checkpoint(out / "policy.pt")["stage"] == "imitation"
    refined = out / "refined"
    for name in ("policy.pt", "policy.onnx", "world_model.pt", "report.md", "metrics.json"):
        assert (refined / name).is_file(), name
    assert {p.name for p in (refined / "checkpoints").iterdir()} == {
        "world_model.pt",
        "refine.pt",
    }  # no imitation again: refinement starts from OUT's policy
    saved = ck.load_checkpoint(refined / "policy.pt")
    assert saved["stage"] == "refine" and saved["step"] == 4 and saved["iteration"] == 1
    imitated = ck.load_checkpoint(out / "policy.pt")
    assert saved["normalisation"] == imitated["normalisation"]
    assert any(not torch.equal(v, imitated["policy"][k]) for k, v in saved["policy"].items())
    assert (refined / "policy.onnx").read_bytes() != plain["onnx"]

    report = (refined / "report.md").read_text()
    for needle in ("speed MAE", "constant speed", "collision AUROC", "imitation L1",
                   "to steering ±0.6"):  # fmt: skip
        assert needle in report, needle
    for png in ("loss_curves.png", "uncertainty_vs_error.png", "reveries.png"):
        assert (refined / "figures" / png).stat().st_size > 10_000
        assert f"](figures/{png})" in report
    m = json.loads((refined / "metrics.json").read_text())["metrics"]
    assert m["held_out"] and m["windows"] > 0 and np.isfinite(m["speed_mae_mps"])
    assert m["response_steering_image"] >= 0 and m["response_throttle_speed"] >= 0
    if m["collision_steps"] > 0:  # which episodes are held out depends on their names
        assert 0.0 <= m["collision_auroc"] <= 1.0
    else:
        assert m["collision_auroc"] is None  # NaN is written as null

    top = (out / "report.md").read_text()
    assert top.count("## The world model and refinement (--dirl)") == 1
    assert "](refined/report.md)" in top and "|Δμ| on" in top and "not validated" in top
    assert top.index("(--dirl)") < top.index("## Figures") < top.index("## Export")
    change = json.loads((out / "metrics.json").read_text())["refined"]
    assert change["frames"] > 0 and change["held_out"]
    moved = change["steering"]["mean_abs"] + change["throttle"]["mean_abs"]
    assert moved > 0 and change["steering"]["max_abs"] >= change["steering"]["mean_abs"]
    assert "refinement moved the plan: |Δμ|" in said


@pytest.mark.parametrize("what, path, pair, sigma, value", DIRL_MEASURED)
def test_the_status_line_quotes_the_committed_results(what, path, pair, sigma, value, capsys):
    """Each number the --dirl line prints is what research.paired_table computes from the
    results file it names, for that pair."""
    from research.paired_table import main as paired_table

    assert (ROOT / path).is_file(), path
    assert paired_table([str(ROOT / path), "--sigma", str(sigma), "--pair", pair]) == 0
    model, base = pair.split(":")
    row = next(line for line in capsys.readouterr().out.splitlines()
               if line.startswith(f"| {model} | {base} |"))  # fmt: skip
    assert row.split(" | ")[2] == value, row
    assert f"{value} {what} ({Path(path).name})" in DIRL_STATUS


def test_a_next_iteration_is_a_take_over_round(runs, sim_episodes, tmp_path):
    """--init: the previous policy imitates again, with its input scaling, reimitation_steps at
    reimitation_lr (the rounds' measured fine-tune), and no world model is made."""
    prev, _, _ = runs
    out = tmp_path / "iter2"
    argv = ["--episodes", str(sim_episodes), "--out", str(out), "--init", str(prev)]
    flags = ["--set", "reimitation_steps=3", "--set", "reimitation_lr=2e-4"]
    assert main([*argv, *QUICK, *steps(6, 2, 2), *flags]) == 0
    imitated = ck.load_checkpoint(out / "checkpoints" / "imitation.pt")
    first = ck.load_checkpoint(prev / "policy.pt")
    assert imitated["step"] == 3 and imitated["iteration"] == 1 and imitated["profile"] == "tiny"
    assert imitated["config"]["imitation_lr"] == 2e-4
    assert imitated["normalisation"] == first["normalisation"], "the previous policy's scaling"
    changed = [k for k, v in imitated["policy"].items() if not torch.equal(v, first["policy"][k])]
    assert changed, "imitation trained the previous policy further"
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == ["imitation.pt"]
    assert not (out / "world_model.pt").exists() and not (out / "refined").exists()
    assert "iteration 1: imitation" in (out / "report.md").read_text()


def test_research_runs_keep_one_dirl_iteration_in_place(runs, sim_episodes, tmp_path):
    """The machinery with `dirl` (research/variants/train.py's every run): --init continues the
    previous policy and world model (or the world model's own initialisation with
    world_model_fresh), reimitate imitates first, and policy.pt is the last stage's."""
    from training.one_run import main as one_run

    prev = runs[0] / "refined"
    before = ck.load_checkpoint(prev / "world_model.pt")["world_model"]
    first = ck.load_checkpoint(prev / "policy.pt")["policy"]
    saved = {}
    for fresh in (False, True):
        out = tmp_path / f"fresh-{fresh}"
        argv = ["--episodes", str(sim_episodes), "--out", str(out), "--init", str(prev)]
        flag = ["--set", f"world_model_fresh={str(fresh).lower()}", "--seed", "7"]
        assert one_run([*argv, *QUICK, *steps(0, 0, 0), *flag], dirl=True) == 0
        saved[fresh] = ck.load_checkpoint(out / "world_model.pt")
    for c in saved.values():
        assert all(torch.equal(v, first[k]) for k, v in c["policy"].items())
    assert all(torch.equal(v, before[k]) for k, v in saved[False]["world_model"].items())
    differ = [k for k, v in saved[True]["world_model"].items() if not torch.equal(v, before[k])]
    assert any(k.startswith("gru") for k in differ), "the fresh one is not --init's"

    out = tmp_path / "reimitated"
    argv = ["--episodes", str(sim_episodes), "--out", str(out), "--init", str(prev)]
    assert one_run([*argv, *QUICK, *steps(6, 2, 2), "--set", "reimitate=true"], dirl=True) == 0
    imitated = ck.load_checkpoint(out / "checkpoints" / "imitation.pt")
    assert imitated["step"] == 6 and imitated["iteration"] == 2
    wm = ck.load_checkpoint(out / "checkpoints" / "world_model.pt")
    assert all(torch.equal(v, imitated["policy"][k]) for k, v in wm["policy"].items())
    assert [h["step"] for h in wm["history"]] == [1, 2]
    assert ck.load_checkpoint(out / "policy.pt")["stage"] == "refine"


def test_world_episodes_teach_the_world_model_and_refinement_starts_from_episodes(
    runs, sim_episodes, tmp_path, monkeypatch
):
    """--dirl --world-episodes: the world model learns those episodes (weight for weight what
    a --dirl run on them alone learns), and refinement starts from --episodes' states in it."""
    import shutil

    from training import refine

    prev = runs[0]
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
    same = ["--init", str(prev), "--dirl", "--set", "reimitation_steps=0"]
    one = tmp_path / "one-run"
    argv = ["--episodes", str(sim_episodes), "--world-episodes", str(world), *same]
    assert main([*argv, "--out", str(one), *QUICK, *steps(0, 3, 2)]) == 0
    world_run = tmp_path / "world-run"
    argv = ["--episodes", str(world), "--out", str(world_run), *same]
    assert main([*argv, *QUICK, *steps(0, 3, 0)]) == 0

    learnt = ck.load_checkpoint(world_run / "refined" / "world_model.pt")["world_model"]
    saved = ck.load_checkpoint(one / "refined" / "world_model.pt")["world_model"]
    assert all(torch.equal(v, learnt[k]) for k, v in saved.items())
    names, refined_in = starts[0]  # the one run's (the world-model run calls it for 0 steps)
    assert all(torch.equal(v, learnt[k]) for k, v in refined_in.items())
    policy_eps = {p.name for p in sim_episodes.iterdir() if p.is_dir()}
    assert names <= policy_eps and names - {p.name for p in world.iterdir()}
    record = json.loads((one / "refined" / "metrics.json").read_text())["data"]
    learnt_eps = load_episodes([str(world)])
    assert record["world_model_episodes"]["episodes"] == len(learnt_eps) > 0
    assert record["world_model_episodes"]["frames"] == sum(ep.n for ep in learnt_eps)
    assert "--world-episodes" in (one / "refined" / "report.md").read_text()
    assert json.loads((one / "metrics.json").read_text())["data"]["world_model_episodes"] is None


def test_an_interrupted_run_resumes_where_it_stopped(sim_episodes, tmp_path, capsys):
    """stop_after stops imitation part way, and the same command again ends bit-identical to the
    run that never stopped; with --dirl, refinement stopped part way resumes the same way, its
    imitation untouched."""
    argv = ["--episodes", str(sim_episodes), *QUICK, *steps(4, 3, 3), "--dirl"]
    straight = tmp_path / "straight"
    assert main([*argv, "--out", str(straight)]) == 0

    out = tmp_path / "interrupted"
    capsys.readouterr()
    assert main([*argv, "--out", str(out), "--set", "stop_after=2"]) == 0
    assert "run the same command to resume" in capsys.readouterr().out
    assert not (out / "policy.pt").exists() and not (out / "refined").exists()
    assert ck.load_checkpoint(out / "checkpoints" / "imitation.pt")["step"] == 2
    assert main([*argv, "--out", str(out), "--set", "stop_after=5"]) == 0  # imitation ends
    refined = out / "refined"
    assert ck.load_checkpoint(refined / "checkpoints" / "refine.pt")["step"] == 2
    assert not (refined / "policy.pt").exists()
    imitation_bytes = (out / "checkpoints" / "imitation.pt").read_bytes()

    assert main([*argv, "--out", str(out)]) == 0
    assert (out / "checkpoints" / "imitation.pt").read_bytes() == imitation_bytes  # not redone
    wm = ck.load_checkpoint(refined / "checkpoints" / "world_model.pt")
    assert wm["step"] == 3 and [h["step"] for h in wm["history"]] == [1, 2, 3]
    for name in ("policy.pt", "refined/policy.pt"):
        resumed = ck.load_checkpoint(out / name)
        reference = ck.load_checkpoint(straight / name)
        assert resumed["step"] == reference["step"] > 0
        for k, v in reference["policy"].items():  # bit-identical to the run that never stopped
            assert torch.equal(v, resumed["policy"][k]), (name, k)


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
    assert ck.load_checkpoint(out / "policy.pt")["step"] == 3
    assert not (out / "world_model.pt").exists()
    assert len(list((out / "tensorboard").iterdir())) == 1  # only rank 0 writes
    assert proc.stdout.count("wrote ") == 1


def test_dirl_under_torchrun_is_refused_in_one_line(sim_episodes, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "2")
    assert main(["--episodes", str(sim_episodes), "--out", str(tmp_path / "o"), "--dirl"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not under torchrun" in err, err


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
            [
                "--out",
                "{tmp}/o",
                "--episodes",
                "{sim}",
                "--world-episodes",
                "{tmp}/missing",
                "--dirl",
            ],
            "--world-episodes {tmp}/missing: no such directory",
        ),
        (
            ["--out", "{tmp}/o", "--episodes", "{sim}", "--world-episodes", "{tmp}", "--dirl"],
            "no episodes",
        ),
        (
            [
                "--out",
                "{tmp}/o",
                "--episodes",
                "{sim}",
                "--world-episodes",
                "{sim}",
                "--dirl",
                "--set",
                "world_model_steps=0",
            ],
            "world_model_steps is 0",
        ),
        (
            ["--out", "{tmp}/o", "--episodes", "{sim}", "--world-episodes", "{sim}"],
            "--world-episodes is what the world model learns: it needs --dirl",
        ),
        (["--out", "{tmp}/o", "--episodes", "{sim}", "--no-uncertainty"], "it needs --dirl"),
        (["--out", "{tmp}/o", "--episodes", "{sim}", "--set", "dirl=true"], "use --dirl"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(args, message, sim_episodes, tmp_path, capsys):
    argv = [a.format(tmp=tmp_path, sim=sim_episodes) for a in args]
    assert main(argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and message.format(tmp=tmp_path) in lines[0], captured.err
    assert captured.out == ""


def test_resuming_into_a_run_of_another_profile_is_refused(runs, sim_episodes, capsys):
    out = runs[0]
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


def test_demo_policy_refines_its_last_network_with_dirl(sim_episodes, tmp_path, monkeypatch):
    """training/demo_policy.py --sloppy-world asks carrt-train for --dirl explicitly, refining
    the last network itself (reimitation_steps=0), and ships what refined/ holds."""
    from types import SimpleNamespace

    from training import demo_policy
    from training.iterate import parse

    (tmp_path / "sloppy").symlink_to(sim_episodes)
    seen = []
    monkeypatch.setattr(demo_policy, "run", lambda argv, done=None: seen.append(argv))
    a = SimpleNamespace(episodes=1, jobs=1, seed=0, threads=1)
    shipped = demo_policy.sloppy_world_refinement(
        sys.executable, [sim_episodes], tmp_path / "il3", tmp_path, a
    )
    assert shipped == tmp_path / "refined" / "refined"
    asked, cfg = parse(seen[-1][2:])  # after `python training/iterate.py`
    assert asked.dirl and cfg.init == str(tmp_path / "il3")
    assert (cfg.reimitation_steps, cfg.world_model_steps, cfg.refine_steps) == (0, 3000, 300)


def test_the_export_names_its_training_placements_and_carrt_eval_warns_on_them(runs, tmp_path):
    import subprocess
    import sys

    import onnx

    from carrt import model_contract as mc

    out, _, _ = runs
    _, saved = ck.load_policy(out / "policy.pt")
    assert saved["sim_placements"] and set(saved["sim_placements"]) == {"easy"}
    seeds = saved["sim_placements"]["easy"]
    assert set(seeds) <= {0, 1} and len(seeds) == 1, "one placement held out, one trained on"
    meta = {p.key: p.value for p in onnx.load(out / "policy.onnx").metadata_props}
    assert mc.trained_on(meta, "easy", [0, 1]) == seeds and mc.trained_on(meta, "hard", [0]) == []
    done = subprocess.run(
        [sys.executable, "-m", "carrt", "eval", "--model", str(out / "policy.onnx"), "--layout",
         "easy", "--tracks", "0-1", "--seconds", "2", "--seeds", "0"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    said = f"1 of the 2 placements ({seeds[0]}, layout easy) are ones policy.onnx was trained on"
    assert said in done.stderr
