"""research/takeover_check.py: rounds whose every frame is a take-over drive, against IL at equal
frames. The check itself drives and trains for half an hour; here its rounds' commands (what
each round drives, what it learns from, from which policy), its settings, its plan and its
table's pairs. The refinements it can add are in test_research_takeover_check_refine.py."""

from __future__ import annotations

import json

import pytest
from research_takeover_rig import record_chain as _chain

from research import (
    check_steps,
    dirl_steps,
    outcome_check,
    takeover_check,
    takeover_refine,
)


def test_each_round_is_take_overs_by_the_previous_policy_and_imitation_again(monkeypatch, tmp_path):
    argv, rows = _chain(monkeypatch, tmp_path, "--set", "rounds=2", "--set", "round_seconds=50",
                        "--set", "demo_noise=1.0", sigma=1.0, seed=2)  # fmt: skip
    runs, data = tmp_path / "runs" / "noise1-seed2", tmp_path / "data"
    first, second = argv["takeovers-noise1-seed2-rounds1"], argv["takeovers-noise1-seed2-rounds2"]
    # take-overs only (the expert steps in before a crash), the round's seconds, the demos' σ
    assert "interventions" in first and "drives" not in first
    assert first[first.index("--seconds") + 1] == "50.0"
    assert first[first.index("--noise") + 1] == "1.0"
    # round 1 drives IL's policy, round 2 the policy round 1 made, on placements of its own
    assert str(runs / "il" / "policy.onnx") in first
    assert str(runs / "takeovers1" / "policy.onnx") in second
    assert first[first.index("--tracks") + 1] != second[second.index("--tracks") + 1]
    assert not any(name.startswith("drive-") for name in argv)  # no exploration drives
    # round 2 imitates again from round 1's policy on the demonstrations and both rounds
    train = argv["train-noise1-seed2-takeovers2"]
    assert train[train.index("--init") + 1] == str(runs / "takeovers1")
    for episodes in ("expert-noise1", "rounds-noise1-seed2-iter1", "rounds-noise1-seed2-iter2"):
        assert str(data / episodes) in train
    assert "reimitate=true" in train and "world_model_steps=0" in train
    assert "refine_steps=0" in train
    # IL: the outcome check's own command (so its run is reused); IL at each round's frames
    study = takeover_check.parse(["--set", f"out={tmp_path}"]).study
    assert argv["train-noise1-seed2-il"][-len(check_steps.imitation_flags(study, 2)) :] == (
        check_steps.imitation_flags(study, 2)
    )
    frames = {r["model"]: r["frames"] for r in rows}
    assert frames == {"IL": 1000, "takeovers1": 2000, "IL-equal-takeovers1": 2000,
                      "takeovers2": 3000, "IL-equal-takeovers2": 3000}  # fmt: skip
    equal = argv["train-noise1-seed2-il-equal-takeovers2"]
    assert str(data / "extra-noise1" / "1") in equal and "--init" not in equal
    assert str(data / "extra-noise1" / "1") not in argv["train-noise1-seed2-il-equal-takeovers1"]


def test_each_round_is_paired_with_imitation_at_its_frames():
    cfg = takeover_check.parse([])
    assert takeover_check.pairs(cfg) == [
        ("takeovers1", "IL-equal-takeovers1"), ("takeovers1", "IL"),
        ("takeovers2", "IL-equal-takeovers2"), ("takeovers2", "IL"),
        ("takeovers2", "takeovers1"),
    ]  # fmt: skip
    runs = [{"track": t, "completion_ratio": c, "collisions_per_min": 1.0, "average_speed": 1.0}
            for t, c in ((100, 0.9), (101, 0.7))]  # fmt: skip
    rows = [{"model": "takeovers2", "seed": 0, "frames": 35000, "runs": runs},
            {"model": "IL-equal-takeovers2", "seed": 0, "frames": 35100,
             "runs": [{**r, "completion_ratio": 0.6} for r in runs]}]  # fmt: skip
    table = outcome_check.report(rows, takeover_check.pairs(cfg))
    assert "| takeovers2 | IL-equal-takeovers2 | +0.200 |" in table, table


@pytest.mark.parametrize(
    "setting, says",
    [("rounds=0", "rounds: 0"), ("rounds=4", "rounds: 4"), ("round_seconds=nan", "round_seconds"),
     ("parallel=0", "parallel: 0"), ("demo_noise=-1", "demo_noise"),
     ("refine_with_drives=true", "needs refine=true"),
     ("refine_paper_form=true", "needs refine=true"),
     ("refine_crashes_only=true", "needs refine_with_drives=true"),
     ("refine_drift=true", "needs refine=true"),
     ("drift_members=2", "needs refine_drift=true"),
     ("drift_members=-1", "drift_members"), ("il_equal_at=3", "il_equal_at: (3,)"),
     ("study.out=x", "the check's own"), ("study.profil=paper", "did you mean profile"),
     ("study.imitation_steps=many", "imitation_steps=many"),
     ("robustness_rounds=-1", "robustness_rounds: -1"),
     ("robustness_rounds=4", "robustness_rounds: 4"),
     ("study.demo_noise_tau=-0.5", "study.demo_noise_tau: -0.5"),
     ("study.demo_noise_tau=nan", "not a valid float")],
)  # fmt: skip
def test_a_bad_setting_is_refused_in_one_line(capsys, setting, says):
    with pytest.raises(SystemExit) as stop:
        takeover_check.parse(["--set", setting])
    assert stop.value.code == 2
    assert says in capsys.readouterr().err.strip().splitlines()[-1]


def test_the_run_writes_its_results_table_and_completion_against_frames(monkeypatch, tmp_path):
    def fake_chain(cfg, step, sigma, seed, rows):
        for model, frames, c in (("IL", 1000, 0.5), ("takeovers1", 2000, 0.7),
                                 ("IL-equal-takeovers1", 2000, 0.6)):  # fmt: skip
            runs = [{"track": 100, "completion_ratio": c, "collisions_per_min": 1.0,
                     "average_speed": 1.0}]  # fmt: skip
            rows.append({"model": model, "demo_noise": sigma, "seed": seed, "frames": frames,
                         "aggregate": {"completion_ratio": {"mean": c}}, "runs": runs})  # fmt: skip

    monkeypatch.setattr(takeover_check, "chain", fake_chain)
    monkeypatch.setattr(dirl_steps, "demonstrations", lambda *a: None)
    assert takeover_check.main(["--set", f"out={tmp_path}", "--set", "rounds=1",
                                "--set", "demo_noise=0,1.0"]) == 0  # fmt: skip
    name = "takeovers-noise0_1"
    assert (tmp_path / f"completion_vs_frames-{name}.png").read_bytes()[:4] == b"\x89PNG"
    results = json.loads((tmp_path / f"results-{name}.json").read_text())
    assert {r["demo_noise"] for r in results["rows"]} == {0.0, 1.0}
    table = (tmp_path / f"table-{name}.md").read_text()
    assert "Demonstration noise σ 1:" in table
    assert "| takeovers1 | IL-equal-takeovers1 | +0.100 ± 0.000 |" in table, table


def test_il_equal_at_trains_imitation_at_equal_frames_only_at_those_rounds(monkeypatch, tmp_path):
    argv, rows = _chain(monkeypatch, tmp_path, "--set", "rounds=2", "--set", "il_equal_at=2")
    assert "train-noise0-seed0-il-equal-takeovers2" in argv
    assert "train-noise0-seed0-il-equal-takeovers1" not in argv
    assert [r["model"] for r in rows] == ["IL", "takeovers1", "takeovers2", "IL-equal-takeovers2"]
    pairs = takeover_check.pairs(takeover_check.parse(["--set", "il_equal_at=2"]))
    assert ("takeovers2", "IL-equal-takeovers2") in pairs and ("takeovers1", "IL") in pairs
    assert not any(base == "IL-equal-takeovers1" for _, base in pairs)


def test_the_last_trained_policies_are_driven_first_and_the_rows_keep_training_order(
    monkeypatch, tmp_path
):
    driven = []

    def evaluate(study, step, name, onnx, result):
        driven.append(name)
        return {"runs": [], "aggregate": {}}

    cfg = takeover_check.parse(["--set", f"out={tmp_path}", "--set", "rounds=2"])
    monkeypatch.setattr(takeover_check, "evaluate", evaluate)
    for module in (takeover_check, takeover_refine):
        monkeypatch.setattr(module, "frames_in", lambda paths: 1000 * len(paths))
    monkeypatch.setattr(dirl_steps, "top_up", lambda pool, frames: [pool / "0"])
    rows = [{"model": "an earlier chain's"}]
    takeover_check.chain(cfg, lambda *step: None, 0.0, 0, rows)
    # a check stopped part way (a lent GPU's minutes) has the last round and its IL first
    assert driven == [f"noise0-seed0-{m}" for m in ("IL-equal-takeovers2", "takeovers2",
                      "IL-equal-takeovers1", "takeovers1", "IL")]  # fmt: skip
    assert [r["model"] for r in rows] == ["an earlier chain's", "IL", "takeovers1",
                                          "IL-equal-takeovers1", "takeovers2",
                                          "IL-equal-takeovers2"]  # fmt: skip


def test_study_settings_are_set_through_the_check_and_reach_its_commands(monkeypatch, tmp_path):
    cfg = takeover_check.parse(["--set", "study.profile=paper", "--set", "study.imitation_steps=50",
                                "--set", "parallel=3"])  # fmt: skip
    assert cfg.study.profile == "paper" and cfg.study.imitation_steps == 50
    assert cfg.study.parallel == 3  # the check's own still reaches the study
    argv, _ = _chain(monkeypatch, tmp_path, "--set", "study.profile=paper",
                     "--set", "study.imitation_steps=50")  # fmt: skip
    il = argv["train-noise0-seed0-il"]
    assert il[il.index("--profile") + 1] == "paper" and "imitation_steps=50" in il


def _recording_into(commands: list[list[str]]):
    """A step function that records each command instead of running it."""
    return lambda name, argv, marker: commands.append(argv)


def test_a_lasting_demonstrator_error_reaches_the_demonstrations_and_every_take_over(
    monkeypatch, tmp_path
):
    """study.demo_noise_tau: the imperfect person's error lasts that long in the demonstrations
    (both pools) and in each round's take-overs, the same person throughout; 0 by default."""
    for tau, sets in (("0.0", ()), ("0.5", ("--set", "study.demo_noise_tau=0.5"))):
        argv, _ = _chain(monkeypatch, tmp_path, "--set", "demo_noise=1.0", *sets, sigma=1.0)
        cfg = takeover_check.parse(["--set", f"out={tmp_path}", "--set", "demo_noise=1.0", *sets])
        demos: list[list[str]] = []
        check_steps.every_noise_demonstrations(cfg.study, _recording_into(demos), extra=True)
        commands = [*demos, argv["takeovers-noise1-seed0-rounds1"],
                    argv["takeovers-noise1-seed0-rounds2"]]  # fmt: skip
        assert len(commands) == 4
        for a in commands:
            assert a[a.index("--noise") + 1] == "1.0" and a[a.index("--noise-tau") + 1] == tau


def test_robustness_rounds_give_the_noisy_chains_their_own_rounds_and_il_at_the_last(
    monkeypatch, tmp_path
):
    sets = ("--set", "rounds=3", "--set", "il_equal_at=3", "--set", "robustness_rounds=2",
            "--set", "refine=true", "--set", "demo_noise=0,1.0")  # fmt: skip
    argv, rows = _chain(monkeypatch, tmp_path, *sets, sigma=1.0, seed=0)
    assert [r["model"] for r in rows] == ["IL", "takeovers1", "takeovers2", "IL-equal-takeovers2"]
    assert not any("rounds3" in name or "world-model" in name for name in argv)
    world = tmp_path / "runs" / "noise0-seed0" / "takeovers3-world-model"
    world.mkdir(parents=True)
    (world / "metrics.json").write_text(json.dumps({"counterfactual": None}))
    argv, rows = _chain(monkeypatch, tmp_path, *sets, sigma=0.0, seed=0)  # σ 0: as set
    assert (
        "takeovers-noise0-seed0-rounds3" in argv and "train-noise0-seed0-takeovers3-refined" in argv
    )
    assert [r["model"] for r in rows if "IL-equal" in r["model"]] == ["IL-equal-takeovers3"]
    cfg = takeover_check.parse(list(sets))
    noisy = takeover_check.pairs(takeover_check.for_noise(cfg, 1.0))
    assert ("takeovers2", "IL-equal-takeovers2") in noisy and not any("+" in m for m, _ in noisy)
    plan = takeover_check.plan(cfg)  # 3 seeds: σ 0 three rounds and refinement, σ 1 two rounds
    assert plan["takeovers"] == 3 * 3 + 2 * 3 and plan["train il-equal-takeovers"] == 3 + 3
    assert plan["train takeovers3-world-model"] == 3 and plan["demos"] == 4
    assert plan["eval"] == 3 * (1 + 3 + 1 + 2) + 3 * (1 + 2 + 1)
    assert takeover_check.for_noise(takeover_check.parse(["--set", "rounds=2"]), 1.0).rounds == 2


def test_every_step_of_the_checks_plan_has_a_typical_time_for_the_eta():
    """The ETA's guess for a kind not run yet (research/study_steps.typical_s): every kind the
    check plans, with every world model and refinement it can add, has one; only the drift
    reading (a network's forward passes) is guessed from its family's steps."""
    from research.study_steps import typical_s

    cfg = takeover_check.parse(
        ["--set", "rounds=3", "--set", "refine=true", "--set", "refine_paper_form=true",
         "--set", "refine_with_drives=true", "--set", "refine_crashes_only=true",
         "--set", "refine_drift=true", "--set", "drift_members=2",
         "--set", "more_drive_tracks=1100-1104", "--set", "paper_corrected_in=drives-only",
         "--set", "demo_noise=0,1.0", "--set", "robustness_rounds=2"]
    )  # fmt: skip
    kinds = set(takeover_check.plan(cfg))
    assert {k for k in kinds if typical_s(k) is None} == {"drift"}, kinds
