"""bench/takeover_check.py: rounds whose every frame is a take-over drive, against IL at equal
frames. The check itself drives and trains for half an hour; here its chain's commands (what
each round drives, what it learns from, from which policy) and its table's pairs."""

from __future__ import annotations

import json

import pytest

from bench import (
    check_steps,
    dirl_steps,
    drift_steps,
    outcome_check,
    takeover_check,
    takeover_refine,
)


def _chain(monkeypatch, tmp_path, *sets, sigma=0.0, seed=0):
    cfg = takeover_check.parse(["--set", f"out={tmp_path}", *sets])
    steps = []
    monkeypatch.setattr(takeover_check, "evaluate", lambda *a: {"runs": [], "aggregate": {}})
    # every episode directory holds 1,000 frames; the second pool is handed out 1,000 at a time
    for module in (takeover_check, takeover_refine):
        monkeypatch.setattr(module, "frames_in", lambda paths: 1000 * len(paths))
    monkeypatch.setattr(
        dirl_steps, "top_up", lambda pool, frames: [pool / f"{i}" for i in range(frames // 1000)]
    )
    rows = []
    takeover_check.chain(
        cfg, lambda name, argv, marker: steps.append((name, argv)), sigma, seed, rows
    )
    return dict(steps), rows


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


def test_refine_trains_one_world_model_and_refines_the_last_round_with_and_without_unc(
    monkeypatch, tmp_path
):
    world = tmp_path / "runs" / "noise0-seed1" / "takeovers2-world-model"
    world.mkdir(parents=True)
    check = {"collision_auroc": 0.9, "rank_correlation": 0.4}
    (world / "metrics.json").write_text(json.dumps({"counterfactual": check}))
    argv, rows = _chain(monkeypatch, tmp_path, "--set", "rounds=2", "--set", "refine=true",
                        seed=1)  # fmt: skip
    runs, data = tmp_path / "runs" / "noise0-seed1", tmp_path / "data"
    train = argv["train-noise0-seed1-takeovers2-world-model"]
    # the world model: from the last round's policy, on every frame so far, its check on
    for episodes in ("expert-noise0", "rounds-noise0-seed1-iter1", "rounds-noise0-seed1-iter2"):
        assert str(data / episodes) in train
    assert train[train.index("--init") + 1] == str(runs / "takeovers2")
    study = takeover_check.parse([]).study
    assert f"world_model_steps={study.world_model_steps}" in train and "refine_steps=0" in train
    assert f"counterfactual_starts={study.counterfactual_starts}" in train
    assert "reimitate=true" not in train  # the round's policy, as it was
    assert "takeovers_as_collisions=true" in train  # as the table of 2026-11-26 ran
    # both refinements start from that world model and its policy, the same frames; -unc only
    # drops the uncertainty term
    refined = argv["train-noise0-seed1-takeovers2-refined"]
    unc = argv["train-noise0-seed1-takeovers2-refined-unc"]
    assert refined[refined.index("--init") + 1] == str(world)
    assert "world_model_steps=0" in refined and f"refine_steps={study.refine_steps}" in refined
    assert "refine_w_anchor=10.0" in refined and "refine_search=false" in refined
    assert "--no-uncertainty" in unc and "--no-uncertainty" not in refined
    assert [a for a in unc if a != "--no-uncertainty"] == [
        a.replace("takeovers2-refined", "takeovers2-refined-unc") for a in refined
    ]
    by_model = {r["model"]: r for r in rows}
    assert by_model["takeovers2+refined"]["frames"] == by_model["takeovers2"]["frames"] == 3000
    assert by_model["takeovers2+refined-unc"]["counterfactual"] == check
    assert "counterfactual" not in by_model["takeovers2"]
    assert ("takeovers2+refined", "takeovers2+refined-unc") in takeover_check.pairs(
        takeover_check.parse(["--set", "rounds=2", "--set", "refine=true"])
    )


def test_the_papers_form_refines_in_the_same_world_model_with_every_safeguard_off(
    monkeypatch, tmp_path
):
    world = tmp_path / "runs" / "noise0-seed0" / "takeovers1-world-model"
    world.mkdir(parents=True)
    (world / "metrics.json").write_text(json.dumps({"counterfactual": None}))
    sets = ["--set", "rounds=1", "--set", "refine=true", "--set", "refine_paper_form=true"]
    argv, rows = _chain(monkeypatch, tmp_path, *sets)
    paper, unc = (
        argv["train-noise0-seed0-takeovers1-paper"],
        argv["train-noise0-seed0-takeovers1-paper-unc"],
    )
    safeguarded = argv["train-noise0-seed0-takeovers1-refined"]
    for args in (paper, unc):
        assert args[args.index("--init") + 1] == str(world)
        # the paper's form wins over the study's safeguards: iterate.py applies --set in order
        for setting in ("refine_w_anchor", "refine_w_imitation", "refine_center_gradient",
                        "collision_prior_correction"):  # fmt: skip
            given = [a for a in args if a.startswith(f"{setting}=")]
            assert given[-1] in (f"{setting}=0", f"{setting}=false"), given
        assert given[0] in safeguarded
    assert "--no-uncertainty" in unc and "--no-uncertainty" not in paper
    assert {"takeovers1+paper", "takeovers1+paper-unc"} <= {r["model"] for r in rows}
    assert ("takeovers1+paper", "takeovers1+paper-unc") in takeover_check.pairs(
        takeover_check.parse(sets)
    )


def test_refine_with_drives_adds_a_world_model_that_also_learns_exploration_drives(
    monkeypatch, tmp_path
):
    runs, data = tmp_path / "runs" / "noise0-seed0", tmp_path / "data"
    for name in ("takeovers1-world-model", "takeovers1-drives-world-model"):
        (runs / name).mkdir(parents=True)
        (runs / name / "metrics.json").write_text(json.dumps({"counterfactual": {"of": name}}))
    sets = ["--set", "rounds=1", "--set", "refine=true", "--set", "refine_with_drives=true"]
    argv, rows = _chain(monkeypatch, tmp_path, *sets)
    drive = argv["drive-noise0-seed0-round-drives1"]
    # the last round's policy alone, with exploration noise, on its own round's placements
    assert "drives" in drive and "--explore" in drive
    assert str(runs / "takeovers1" / "policy.onnx") in drive
    assert drive[drive.index("--out") + 1] == str(data / "round-drives-noise0-seed0-iter1")
    plain = argv["train-noise0-seed0-takeovers1-world-model"]  # the rounds' frames alone
    more = argv["train-noise0-seed0-takeovers1-drives-world-model"]
    assert str(data / "round-drives-noise0-seed0-iter1") in more
    assert str(data / "round-drives-noise0-seed0-iter1") not in plain
    unc = argv["train-noise0-seed0-takeovers1-drives-refined-unc"]
    assert unc[unc.index("--init") + 1] == str(runs / "takeovers1-drives-world-model")
    assert "--no-uncertainty" in unc
    by_model = {r["model"]: r for r in rows}
    assert by_model["takeovers1+drives+refined"]["frames"] == 3000  # 1,000 more: the drives
    assert by_model["takeovers1+drives+refined"]["counterfactual"] == {
        "of": "takeovers1-drives-world-model"
    }
    assert by_model["takeovers1+refined"]["counterfactual"] == {"of": "takeovers1-world-model"}
    pairs = takeover_check.pairs(takeover_check.parse(sets))
    assert ("takeovers1+drives+refined", "takeovers1+drives+refined-unc") in pairs
    assert ("takeovers1+drives+refined", "IL-equal-takeovers1") not in pairs  # more frames


def test_refine_crashes_only_adds_a_world_model_without_the_take_over_labels(monkeypatch, tmp_path):
    runs = tmp_path / "runs" / "noise0-seed0"
    for source in ("", "drives-", "drives-crashes-only-"):
        (runs / f"takeovers1-{source}world-model").mkdir(parents=True)
        (runs / f"takeovers1-{source}world-model" / "metrics.json").write_text(
            json.dumps({"counterfactual": {"of": source}})
        )
    sets = ["--set", "rounds=1", "--set", "refine=true", "--set", "refine_with_drives=true",
            "--set", "refine_crashes_only=true"]  # fmt: skip
    argv, rows = _chain(monkeypatch, tmp_path, *sets)
    labelled = argv["train-noise0-seed0-takeovers1-drives-world-model"]
    crashes = argv["train-noise0-seed0-takeovers1-drives-crashes-only-world-model"]
    assert "takeovers_as_collisions=false" in crashes and "takeovers_as_collisions=true" in labelled
    # the same episodes, steps and seed: only the labels differ
    assert [a for a in crashes if "takeovers_as_collisions" not in a] == [
        a.replace("drives-world-model", "drives-crashes-only-world-model")
        for a in labelled
        if "takeovers_as_collisions" not in a
    ]
    refined = argv["train-noise0-seed0-takeovers1-drives-crashes-only-refined-unc"]
    assert refined[refined.index("--init") + 1] == str(
        runs / "takeovers1-drives-crashes-only-world-model"
    )
    by_model = {r["model"]: r for r in rows}
    assert by_model["takeovers1+drives-crashes-only+refined"]["counterfactual"] == {
        "of": "drives-crashes-only-"
    }
    assert (
        "takeovers1+drives-crashes-only+refined",
        "takeovers1+drives-crashes-only+refined-unc",
    ) in takeover_check.pairs(takeover_check.parse(sets))


def test_refine_drift_checks_every_refined_policy_and_members_join_the_crash_only_ones(
    monkeypatch, tmp_path
):
    runs = tmp_path / "runs" / "noise0-seed1"
    for source in ("", "drives-", "drives-crashes-only-"):
        (runs / f"takeovers1-{source}world-model").mkdir(parents=True)
        (runs / f"takeovers1-{source}world-model" / "metrics.json").write_text("{}")
    (runs / "takeovers1-drives-crashes-only-paper").mkdir()
    (runs / "takeovers1-drives-crashes-only-paper" / "drift.json").write_text('{"moved": 1}')
    sets = ["--set", "rounds=1", "--set", "refine=true", "--set", "refine_with_drives=true",
            "--set", "refine_crashes_only=true", "--set", "refine_paper_form=true",
            "--set", "refine_drift=true", "--set", "drift_members=2"]  # fmt: skip
    argv, rows = _chain(monkeypatch, tmp_path, *sets, seed=1)
    world = argv["train-noise0-seed1-takeovers1-drives-crashes-only-world-model"]
    for m, seed in ((1, "101"), (2, "201")):
        member = argv[f"train-noise0-seed1-takeovers1-drives-crashes-only-member{m}"]
        # the crash-only world model's command, its own seed and initialisation
        assert member[member.index("--out") + 1] == str(
            runs / f"takeovers1-drives-crashes-only-member{m}"
        )
        assert member[-4:] == ["--seed", seed, "--set", "world_model_fresh=true"]
        assert member[member.index("--init") + 1] == world[world.index("--init") + 1]
        same = [a for a in member[:-4] if "member" not in a]
        assert same == [a for a in world if "world-model" not in a]
    assert not any("member" in name for name in argv if "crashes-only" not in name)
    drifts = {n: a for n, a in argv.items() if n.startswith("drift-")}
    assert len(drifts) == 12  # 3 world models × 4 refinements
    crash = drifts["drift-noise0-seed1-takeovers1-drives-crashes-only-paper-unc"]
    assert crash[crash.index("--start") + 1] == str(
        runs / "takeovers1-drives-crashes-only-world-model"
    )
    assert crash[crash.index("--members") + 1 :][:2] == [
        str(runs / f"takeovers1-drives-crashes-only-member{m}") for m in (1, 2)
    ]
    assert "--members" not in drifts["drift-noise0-seed1-takeovers1-drives-paper-unc"]
    by_model = {r["model"]: r for r in rows}
    assert by_model["takeovers1+refined"]["drift"] is None  # not run here: no file
    assert by_model["takeovers1+drives-crashes-only+paper"]["drift"] == {"moved": 1}


def test_more_drive_tracks_adds_world_models_on_more_exploration_drives_and_on_drives_alone(
    monkeypatch, tmp_path
):
    runs = tmp_path / "runs" / "noise0-seed0"
    for source in (
        "",
        "drives-",
        "drives-crashes-only-",
        "more-drives-crashes-only-",
        "drives-only-",
    ):
        (runs / f"takeovers1-{source}world-model").mkdir(parents=True)
        (runs / f"takeovers1-{source}world-model" / "metrics.json").write_text("{}")
    sets = ["--set", "rounds=1", "--set", "refine=true", "--set", "refine_with_drives=true",
            "--set", "refine_crashes_only=true",
            "--set", "more_drive_tracks=1100-1144"]  # fmt: skip
    argv, rows = _chain(monkeypatch, tmp_path, *sets)
    drive = argv["drive-noise0-seed0-more-drives1"]
    assert drive[drive.index("--tracks") + 1] == "1100-1144"
    assert drive[drive.index("--model") + 1] == str(runs / "takeovers1" / "policy.onnx")
    assert "--explore" in drive
    world = argv["train-noise0-seed0-takeovers1-more-drives-crashes-only-world-model"]
    crashes = argv["train-noise0-seed0-takeovers1-drives-crashes-only-world-model"]
    episodes = world[world.index("--episodes") + 1 : world.index("--out")]
    assert episodes == [
        *crashes[crashes.index("--episodes") + 1 : crashes.index("--out")],
        str(tmp_path / "data" / "more-drives-noise0-seed0-iter1"),
    ]
    assert "takeovers_as_collisions=false" in world
    # the fifth world model learns the exploration drives alone; its refinements every frame
    alone = argv["train-noise0-seed0-takeovers1-drives-only-world-model"]
    assert alone[alone.index("--episodes") + 1 : alone.index("--out")] == [
        str(tmp_path / "data" / "round-drives-noise0-seed0-iter1"),
        str(tmp_path / "data" / "more-drives-noise0-seed0-iter1"),
    ]
    assert "takeovers_as_collisions=false" in alone
    refined = argv["train-noise0-seed0-takeovers1-drives-only-refined"]
    assert refined[refined.index("--episodes") + 1 : refined.index("--out")] == episodes
    assert refined[refined.index("--init") + 1] == str(runs / "takeovers1-drives-only-world-model")
    by_model = {r["model"]: r for r in rows}
    assert (
        by_model["takeovers1+drives-only+refined"]["frames"]
        == (by_model["takeovers1+more-drives-crashes-only+refined"]["frames"])
    )
    assert by_model["takeovers1+more-drives-crashes-only+refined"]["frames"] == (
        by_model["takeovers1+drives-crashes-only+refined"]["frames"] + 1000
    )
    with pytest.raises(SystemExit):
        takeover_check.parse(["--set", "refine=true", "--set", "more_drive_tracks=1100-1144"])


def test_paper_corrected_in_adds_the_papers_form_with_p_hat_corrected_in_the_named_world_model(
    monkeypatch, tmp_path
):
    runs = tmp_path / "runs" / "noise0-seed0"
    for source in ("", "drives-", "drives-crashes-only-", "more-drives-crashes-only-",
                   "drives-only-"):  # fmt: skip
        (runs / f"takeovers1-{source}world-model").mkdir(parents=True)
        (runs / f"takeovers1-{source}world-model" / "metrics.json").write_text("{}")
    sets = ["--set", "rounds=1", "--set", "refine=true", "--set", "refine_paper_form=true",
            "--set", "refine_with_drives=true", "--set", "refine_crashes_only=true",
            "--set", "more_drive_tracks=1100-1144",
            "--set", "paper_corrected_in=drives-only,rounds"]  # fmt: skip
    argv, rows = _chain(monkeypatch, tmp_path, *sets)
    corrected = argv["train-noise0-seed0-takeovers1-drives-only-paper-corrected"]
    paper = argv["train-noise0-seed0-takeovers1-drives-only-paper"]
    unc = argv["train-noise0-seed0-takeovers1-drives-only-paper-corrected-unc"]
    assert corrected[corrected.index("--init") + 1] == str(
        runs / "takeovers1-drives-only-world-model"
    )
    for setting in ("refine_w_anchor", "refine_w_imitation", "refine_center_gradient"):
        given = [a for a in corrected if a.startswith(f"{setting}=")]
        assert given[-1] in (f"{setting}=0", f"{setting}=false"), given
    # the last word on the correction: on for the corrected form, off for the paper's own
    last = lambda args: [a for a in args if a.startswith("collision_prior_correction=")][-1]  # noqa: E731
    assert last(corrected) == last(unc) == "collision_prior_correction=true"
    assert last(paper) == "collision_prior_correction=false"
    assert "--no-uncertainty" in unc and "--no-uncertainty" not in corrected
    models = {r["model"] for r in rows}
    assert {"takeovers1+drives-only+paper-corrected", "takeovers1+paper-corrected-unc"} <= models
    assert not any("paper-corrected" in m for m in models if "+drives+" in m or "more-drives" in m)
    cfg = takeover_check.parse(sets)
    assert ("takeovers1+drives-only+paper-corrected",
            "takeovers1+drives-only+paper-corrected-unc") in takeover_check.pairs(cfg)  # fmt: skip
    assert ("takeovers1+paper-corrected", "IL-equal-takeovers1") in takeover_check.pairs(cfg)


def test_paper_corrected_in_names_only_the_checks_world_models(capsys):
    with pytest.raises(SystemExit) as stop:
        takeover_check.parse(["--set", "refine=true", "--set", "paper_corrected_in=drives-only"])
    assert stop.value.code == 2
    assert (
        "'drives-only' is not one of this check's world models (rounds)"
        in (capsys.readouterr().err.strip().splitlines()[-1])
    )


def test_the_drift_table_reports_the_move_and_the_spread_over_seeds():
    def one(steer: float, spread: float) -> dict:
        terms = {"u_total": 10.0, "speed_spread": 0.4, "p_collision_spread": 1.0}
        return {"moved": {"steering_abs": steer, "throttle_abs": 0.05},
                "change": {"speed": 1.0, "p_collision": -0.1, "u_total": 0.0},
                "start": terms, "refined": {**terms, "speed_spread": spread}}  # fmt: skip

    rows = [{"model": "takeovers3+paper", "drift": one(0.3, 0.5)},
            {"model": "takeovers3+paper", "drift": one(0.5, 0.7)},
            {"model": "takeovers3", "drift": None}]  # fmt: skip
    table = drift_steps.drift_table(rows).splitlines()
    assert len(table) == 3 and table[2].startswith("| takeovers3+paper | 2 | 0.400 ± 0.100 |")
    assert "| 0.40 → 0.60 | 1.00 → 1.00 |" in table[2]
    assert drift_steps.drift_table(rows[2:]) == ""


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
    """The ETA's guess for a kind not run yet (bench/study_steps.typical_s): every kind the
    check plans, with every world model and refinement it can add, has one; only the drift
    reading (a network's forward passes) is guessed from its family's steps."""
    from bench.study_steps import typical_s

    cfg = takeover_check.parse(
        ["--set", "rounds=3", "--set", "refine=true", "--set", "refine_paper_form=true",
         "--set", "refine_with_drives=true", "--set", "refine_crashes_only=true",
         "--set", "refine_drift=true", "--set", "drift_members=2",
         "--set", "more_drive_tracks=1100-1104", "--set", "paper_corrected_in=drives-only",
         "--set", "demo_noise=0,1.0", "--set", "robustness_rounds=2"]
    )  # fmt: skip
    kinds = set(takeover_check.plan(cfg))
    assert {k for k in kinds if typical_s(k) is None} == {"drift"}, kinds
