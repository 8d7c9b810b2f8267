"""training.sim_data: simulator recordings over many placements, in parallel and resumable,
never on the evaluation placements."""

from __future__ import annotations

import json

import numpy as np
import pytest

from carrt.episodes.reader import list_episodes, read_episode
from carrt.errors import UserError
from carrt.session import DriveConfig
from training import sim_data


def test_tracks_parse_ranges_and_refuse_the_evaluation_placements():
    assert sim_data.parse_tracks("1000-1002,7, 5-5") == [5, 7, 1000, 1001, 1002]
    for bad in ("", "3-1", "a-b"):
        with pytest.raises(UserError):
            sim_data.parse_tracks(bad)
    with pytest.raises(UserError, match=r"\[100, 101\] are held out"):
        sim_data.parse_tracks("95-101")


def test_demos_record_each_placement_once_on_both_layouts(tmp_path):
    out = tmp_path / "expert"
    argv = ["demos", "--out", str(out), "--tracks", "1000-1001", "--layouts", "mixed,hard",
            "--episodes", "1", "--jobs", "2"]  # fmt: skip
    assert sim_data.main(argv) == 0
    episodes = [read_episode(p) for p in list_episodes([str(out)])]
    assert len(episodes) == 2 and all(ep.n > 20 for ep in episodes)
    placements = sorted((ep.meta["sim"]["layout"], ep.meta["sim"]["track_seed"]) for ep in episodes)
    assert placements == [("hard", 1001), ("mixed", 1000)]
    # Resumed: every placement has its marker, nothing is recorded again.
    assert sim_data.main(argv) == 0
    assert len(list_episodes([str(out)])) == 2


def test_a_lasting_error_reaches_the_recorded_demonstrations(tmp_path):
    """`demos --noise-tau τ`: through `carrt teleop` and the rig to the simulated person, and
    into the labels: with a lasting error the recorded a* changes far less from one step to the
    next than with a fresh error each step, at the same σ."""
    jumps = {}
    for tau in ("0", "0.5"):
        out = tmp_path / f"tau{tau}"
        argv = ["demos", "--out", str(out), "--tracks", "1000", "--layouts", "hard",
                "--episodes", "2", "--noise", "0.5", "--noise-tau", tau, "--jobs", "1"]  # fmt: skip
        assert sim_data.main(argv) == 0
        steering = [read_episode(p).steps["human_action"][:, 0] for p in list_episodes([str(out)])]
        jumps[tau] = float(np.concatenate([np.diff(s) for s in steering]).std())
    # fresh: std of a* differences ≈ σ·√2 (0.7), a lasting one ≈ σ·√(2(1 − e^(−0.2))) (0.3)
    assert jumps["0.5"] < 0.6 * jumps["0"], jumps


def test_an_out_recorded_by_another_person_is_refused_not_mixed(tmp_path, capsys):
    """Finished placements are skipped on resume, so an OUT recorded with another --noise or
    --noise-tau must be refused (one line, exit 2) rather than topped up by another person."""
    out = tmp_path / "expert"
    out.mkdir()
    (out / ".done-1000").write_text("")  # a finished placement, recorded before --noise-tau
    argv = ["demos", "--out", str(out), "--tracks", "1000-1001", "--noise", "0.5"]
    assert sim_data.main([*argv, "--noise-tau", "0.5"]) == 2
    err = capsys.readouterr().err.strip()
    assert "recorded with --noise 0.5 --noise-tau 0, not 0.5 and 0.5: use another --out" in err
    assert len(err.splitlines()) == 1
    assert not list(out.iterdir())[1:], "placement 1001 was not recorded"
    sim_data.same_person(out, 0.5, 0.0)  # the same person: accepted, and now written down
    assert json.loads((out / sim_data.PERSON).read_text()) == {"noise": 0.5, "noise_tau": 0.0}
    with pytest.raises(UserError, match="not 1 and 0"):
        sim_data.same_person(out, 1.0, 0.0)
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    sim_data.same_person(fresh, 1.0, 0.5)
    sim_data.same_person(fresh, 1.0, 0.5)
    with pytest.raises(UserError, match=r"--noise-tau 0\.5, not 1 and 0:"):
        sim_data.same_person(fresh, 1.0, 0.0)
    (fresh / sim_data.PERSON).write_text('{"noise": 1.0')  # edited by hand, say
    with pytest.raises(UserError, match=r"person\.json: not a person record"):
        sim_data.same_person(fresh, 1.0, 0.5)


def test_interventions_need_a_model(tmp_path, capsys):
    argv = ["interventions", "--out", str(tmp_path), "--model", str(tmp_path / "none.onnx")]
    assert sim_data.main(argv) == 2
    assert "no such model" in capsys.readouterr().err


@pytest.mark.parametrize("what", ["demos", "interventions"])
@pytest.mark.parametrize("sigma", ["-0.5", "nan", "inf"])
def test_a_noise_that_is_not_a_finite_sigma_is_refused_by_name(tmp_path, capsys, what, sigma):
    """Checked before any placement runs: one line naming --noise and exit 2, not a failure of
    every placement's own `carrt` command."""
    model = tmp_path / "p.onnx"
    model.write_bytes(b"")
    extra = ["--model", str(model)] if what == "interventions" else []
    with pytest.raises(SystemExit) as exit_:
        sim_data.main([what, "--out", str(tmp_path / "out"), "--noise", sigma, *extra])
    assert exit_.value.code == 2
    assert "argument --noise: expected a finite number >= 0" in capsys.readouterr().err
    assert not (tmp_path / "out").exists(), "nothing recorded"
    with pytest.raises(SystemExit) as exit_:
        sim_data.main([what, "--out", str(tmp_path / "out"), "--noise-tau", sigma, *extra])
    assert exit_.value.code == 2
    assert "argument --noise-tau: expected a finite number >= 0" in capsys.readouterr().err


@pytest.mark.parametrize("what", ["drives", "interventions"])
@pytest.mark.parametrize("seconds", ["0", "-3", "nan", "inf"])
def test_a_duration_that_is_not_finite_and_positive_is_refused_by_name(
    tmp_path, capsys, what, seconds
):
    """NaN or infinite --seconds used to reach every placement's `carrt drive --duration`."""
    model = tmp_path / "p.onnx"
    model.write_bytes(b"")
    argv = [what, "--out", str(tmp_path / "out"), "--model", str(model), "--seconds", seconds]
    with pytest.raises(SystemExit) as exit_:
        sim_data.main(argv)
    assert exit_.value.code == 2
    assert "argument --seconds: expected a finite number > 0" in capsys.readouterr().err
    assert not (tmp_path / "out").exists(), "nothing recorded"


def test_take_overs_carry_the_demonstrators_noise_to_every_placement(tmp_path):
    """`interventions --noise σ`: each placement's drive gets the expert's noise σ, as
    `carrt drive --expert-noise σ` would (the robustness setting's take-overs)."""
    from carrt.cli import build_parser

    model = tmp_path / "p.onnx"
    jobs = sim_data.drive_jobs(tmp_path, model, [1000, 1001], ["hard"], 8.0, intervene=True,
                               noise=0.5, noise_tau=0.25)  # fmt: skip
    for job in jobs:
        assert job.drive.expert_noise == 0.5 and job.drive.expert_intervene
        assert job.drive.expert_noise_tau == 0.25, "the same lasting error as the demonstrations"
    later = sim_data.drive_jobs(tmp_path, model, [1000], ["hard"], 8.0, intervene=True,
                                seed_offset=100_000)  # fmt: skip
    assert later[0].drive.seed == 101000, "another drive of the same placement"
    assert later[0].drive.track_seed == 1000
    alone = sim_data.drive_jobs(tmp_path, model, [1000], ["hard"], 8.0, intervene=False)
    assert alone[0].drive.expert_noise == 0.0, "no person, no noise of theirs"
    infinite = ["drive", "--sim", "--autopilot", "--model", str(model), "--expert-intervene",
                "--expert-noise", "inf"]  # fmt: skip
    with pytest.raises(SystemExit) as exit_:
        build_parser().parse_args(infinite)
    assert exit_.value.code == 2, "carrt drive refuses an infinite σ too"


def test_more_placements_than_a_worker_runs_all_finish(tmp_path, monkeypatch):
    """Regression: with max_tasks_per_child the pool hung once both workers had retired (CPython
    gh-115634; the take-over recording stopped forever after 100 placements)."""
    monkeypatch.setattr(sim_data, "TASKS_PER_WORKER", 2)
    brief = DriveConfig(rig="sim", expert=True, layout="empty", duration=0.05)
    jobs = [
        sim_data.Job(brief, tmp_path / f"{i}.log", tmp_path / f".done-{i}", tmp_path, i)
        for i in range(7)
    ]
    sim_data.run_jobs(jobs, 2, "test")
    assert all(job.marker.exists() for job in jobs)
    assert all(job.log.read_text().startswith("carrt") for job in jobs)


def test_exploration_drives_carry_the_noise_settings_to_every_placement(tmp_path):
    """The DIRL study's drives (bench/dirl_sim.explore_args): --explore plus `carrt drive --set`
    noise settings, so the world model sees steering far from the policy's for most of the
    time, which the paper's ±0.3 half the time did not give it."""
    import numpy as np
    from onnx_models import build_policy

    from carrt.interfaces import Mode

    model = build_policy(tmp_path / "gentle.onnx", steering=0.0, throttle=(0.3, 0.0))
    out = tmp_path / "drives"
    argv = ["drives", "--model", str(model), "--out", str(out), "--tracks", "1000-1001",
            "--layouts", "empty", "--seconds", "20", "--jobs", "2", "--explore",
            "--set", "noise.fraction=0.8", "--set", "noise.amplitude=0.8",
            "--set", "noise.period_s=2.0"]  # fmt: skip
    assert sim_data.main(argv) == 0
    steps = np.concatenate([read_episode(p).steps for p in list_episodes([str(out)])])
    auto = steps["mode"] == Mode.AUTO
    noisy = steps["noise"].astype(bool) & auto
    assert auto.sum() > 200 and 0.65 < noisy.sum() / auto.sum() < 0.95
    delta = np.abs(steps["executed_action"] - steps["policy_action"])[noisy]
    assert 0.5 < delta.max() <= 0.8 + 1e-6, "the amplitude reached the car, not the default 0.3"
    bad = [
        "drives",
        "--model",
        str(model),
        "--out",
        str(out),
        "--tracks",
        "1002",
        "--set",
        "noise.fraction=2",
    ]
    assert sim_data.main(bad) != 0


def test_demonstrations_are_bit_reproducible_from_their_placement_seeds(tmp_path):
    """The same placement recorded twice, by one process and by two, gives the same frames,
    actions, speeds and collisions (the wall-clock fields aside): a study's differences
    between runs on one install come from its settings, not from the recording."""

    def record(out, jobs):
        argv = ["demos", "--out", str(out), "--tracks", "1000-1001", "--episodes", "2",
                "--jobs", str(jobs)]  # fmt: skip
        assert sim_data.main(argv) == 0
        episodes = [read_episode(p) for p in list_episodes([str(out)])]
        by_start = sorted(episodes, key=lambda ep: (ep.meta["sim"]["track_seed"], ep.path.name))
        return [(ep.meta["sim"]["track_seed"], ep.steps, np.asarray(ep.frames)) for ep in by_start]

    first, second = record(tmp_path / "a", 1), record(tmp_path / "b", 2)
    assert len(first) == len(second) == 4
    for (seed_a, steps_a, frames_a), (seed_b, steps_b, frames_b) in zip(first, second, strict=True):
        assert seed_a == seed_b and len(steps_a) == len(steps_b) > 20
        for field in ("executed_action", "speed_mps", "collision", "lap"):
            assert np.array_equal(steps_a[field], steps_b[field]), field
        assert np.array_equal(frames_a, frames_b)


def test_publishing_merges_into_folders_another_placement_made(tmp_path):
    """Two placements finish at once: the second's sim-runs/ goes into the folder the first
    made, its episode takes the next free name of the same second, the marker comes last."""
    out = tmp_path / "out"
    (out / "sim-runs").mkdir(parents=True)
    (out / "sim-runs" / "a.json").write_text("{}")
    (out / "20261129-010101-000").mkdir()
    (out / "20261129-010101-000" / "meta.json").write_text("{}")
    job = sim_data.Job(DriveConfig(), out / "logs" / "x.log", out / ".done-7", out, 7)
    (job.staging / "sim-runs").mkdir(parents=True)
    (job.staging / "sim-runs" / "b.json").write_text("{}")
    (job.staging / "20261129-010101-000").mkdir()
    (job.staging / "20261129-010101-000" / "meta.json").write_text('{"mine": 1}')
    sim_data.publish(job)
    assert sorted(p.name for p in (out / "sim-runs").iterdir()) == ["a.json", "b.json"]
    assert (out / "20261129-010101-001" / "meta.json").read_text() == '{"mine": 1}'
    assert job.marker.exists() and not job.staging.exists() and not job.complete.exists()
