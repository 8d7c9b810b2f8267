"""research/outcome_check.py: the arms' commands and the paired table it reports.

The check itself trains and drives for an hour; here its pieces: the arms differ in nothing
but the advantage, refinement is told to use the drives' outcomes and no world model, and the
table pairs each arm with the re-imitated policy placement by placement, seed by seed.
"""

from __future__ import annotations

import sys

import pytest

from research import check_steps, dirl_steps, outcome_check


def _row(model, seed, completions, collisions=None):
    collisions = collisions or [0.0] * len(completions)
    pairs = enumerate(zip(completions, collisions, strict=True))
    runs = [{"track": 100 + i, "seed": 0, "completion_ratio": c, "collisions_per_min": k,
             "average_speed": 1.5} for i, (c, k) in pairs]  # fmt: skip
    return {"model": model, "seed": seed, "runs": runs}


def test_the_arms_differ_only_in_the_advantage():
    cfg = outcome_check.CheckConfig()
    flags = {a: outcome_check.arm_flags(cfg, adv) for a, adv in outcome_check.ARMS.items()}
    sets = {a: {f for f in flags[a] if f != "--set"} for a in flags}
    assert sets["outcomes"] ^ sets["uniform"] == {
        "outcome_advantage=true", "outcome_advantage=false"
    }  # fmt: skip
    assert {"refine_outcomes=true", "world_model_steps=0"} <= sets["outcomes"]


def test_differences_are_paired_by_placement_within_each_seed():
    rows = [
        _row("imitated", 0, [0.5, 1.0, 0.2]),
        _row("outcomes", 0, [0.7, 1.0, 0.2]),
        _row("imitated", 1, [0.9, 0.9, 0.9]),
        _row("outcomes", 1, [0.9, 0.6, 0.9]),
    ]
    got = check_steps.paired(rows, "outcomes", "imitated", "completion_ratio")
    assert [s for s, _, _ in got] == [0, 1]
    assert got[0][1] == pytest.approx(0.2 / 3) and got[1][1] == pytest.approx(-0.1)
    # seed 0's differences 0.2, 0, 0: sample std 0.2/√3, over √3 placements
    assert got[0][2] == pytest.approx(0.2 / 3)
    table = outcome_check.report(rows)
    assert "| outcomes | imitated |" in table and "-0.017 ± 0.083" in table, table


def test_a_bad_setting_is_refused_in_one_line(capsys):
    with pytest.raises(SystemExit) as stop:
        outcome_check.parse(["--set", "parallel=0"])
    assert stop.value.code == 2
    assert "parallel: 0" in capsys.readouterr().err.strip().splitlines()[-1]


def test_later_iterations_drive_the_previous_outcomes_policy_and_refine_it_again(
    monkeypatch, tmp_path
):
    cfg = outcome_check.parse(["--set", f"out={tmp_path}", "--set", "outcome_iterations=3",
                               "--set", "eval_tracks=200-259", "--set", "seeds=0"])  # fmt: skip
    steps, judged = [], []
    monkeypatch.setattr(
        outcome_check, "evaluate",
        lambda study, step, name, onnx, result: judged.append((name, result)) or {"runs": []},
    )  # fmt: skip
    # every episode directory holds 1,000 frames; the second pool is handed out 1,000 at a time
    monkeypatch.setattr(outcome_check, "frames_in", lambda paths: 1000 * len(paths))
    monkeypatch.setattr(
        dirl_steps, "top_up", lambda pool, frames: [pool / f"{i}" for i in range(frames // 1000)]
    )
    rows = []
    outcome_check.chain(cfg, lambda name, argv, marker: steps.append((name, argv)), 0.0, 0, rows)
    argv = dict(steps)
    runs = tmp_path / "runs" / "noise0-seed0"
    # iteration 2 drives with iteration 1's outcomes policy, iteration 3 with iteration 2's
    assert str(runs / "outcomes" / "policy.onnx") in argv["drive-noise0-seed0-iter2"]
    assert str(runs / "outcomes2" / "policy.onnx") in argv["drive-noise0-seed0-iter3"]
    third = argv["train-noise0-seed0-outcomes3"]
    assert third[third.index("--init") + 1] == str(runs / "outcomes2")
    # and learns from every drive so far, with the arm's own settings
    for k in (1, 2, 3):
        assert str(tmp_path / "data" / f"drives-noise0-seed0-iter{k}") in third
    assert "outcome_advantage=true" in third and "refine_outcomes=true" in third
    # IL at equal frames: the demonstrations topped up to outcomes3's 7 directories' frames
    frames = {r["model"]: r["frames"] for r in rows}
    assert frames["outcomes3"] == frames["IL-equal3"] == 7000 and frames["IL"] == 1000
    equal = argv["train-noise0-seed0-il-equal3"]
    assert str(tmp_path / "data" / "extra-noise0" / "5") in equal and "--init" not in equal
    # validation placements are judged apart from the test placements' results
    assert ("eval" not in [r.stem for _, r in judged]) and len(judged) == 7
    assert {r.name for _, r in judged} == {"eval-200-259.json"}
    assert cfg.study.eval_tracks == "200-259"


def test_each_outcomes_iteration_is_paired_with_imitation_at_its_frames():
    rows = [
        {**_row("outcomes2", 0, [0.9, 0.8]), "frames": 35000},
        {**_row("IL-equal2", 0, [0.7, 0.8]), "frames": 35100},
        _row("IL", 0, [0.6, 0.6]),
    ]
    table = outcome_check.report(rows)
    assert "| outcomes2 | IL-equal2 | +0.100 |" in table, table
    assert "| IL-equal2 | 1 | 35,100 |" in table and "| IL | 1 | – |" in table, table


def test_noisy_demonstrations_get_their_own_chain_without_the_control(monkeypatch, tmp_path):
    cfg = outcome_check.parse(["--set", f"out={tmp_path}", "--set", "demo_noise=0,1.0",
                               "--set", "outcome_iterations=1"])  # fmt: skip
    steps = []
    monkeypatch.setattr(outcome_check, "evaluate", lambda *a: {"runs": []})
    monkeypatch.setattr(outcome_check, "frames_in", lambda paths: 1000 * len(paths))
    monkeypatch.setattr(dirl_steps, "top_up", lambda pool, frames: [pool / "0", pool / "1"])
    rows = []
    outcome_check.chain(cfg, lambda name, argv, marker: steps.append((name, argv)), 1.0, 2, rows)
    argv = dict(steps)
    assert str(tmp_path / "data" / "expert-noise1") in argv["train-noise1-seed2-il"]
    # the expert's take-overs carry the demonstrations' noise
    takeovers = argv["takeovers-noise1-seed2-iter1"]
    assert takeovers[takeovers.index("--noise") + 1] == "1.0"
    assert not any("uniform" in name for name in argv)
    assert {r["model"] for r in rows} == {"IL", "imitated", "outcomes", "IL-equal1"}
    assert {r["demo_noise"] for r in rows} == {1.0}
    with pytest.raises(SystemExit):
        outcome_check.parse(["--set", "demo_noise=nan"])


def test_a_resumed_check_counts_the_steps_an_earlier_run_finished(monkeypatch, tmp_path):
    """So its ETA leaves them out (before, it priced them at a typical time: ~100 min said
    with ~20 left when most steps were reused)."""
    cfg = outcome_check.parse(["--set", f"out={tmp_path}", "--set", "seeds=0,1"])
    monkeypatch.setattr(dirl_steps, "demonstrations", lambda *a: None)
    (tmp_path / "m0").touch()  # seed 0's step finished in an earlier invocation
    seen = []

    def chain(cfg, step, sigma, seed, rows):
        step(f"train-noise0-seed{seed}-il", [sys.executable, "-c", "pass"], tmp_path / f"m{seed}")
        seen.append(step)
        rows.append(seed)

    rows = outcome_check.run_check(cfg, {"train il": 2}, chain)
    assert sorted(rows) == [0, 1] and (tmp_path / "m1").exists()
    step = seen[-1]
    assert step.finished_before == {"train il": 1} and not step.report_only
    assert step.eta_s() == 0.0
