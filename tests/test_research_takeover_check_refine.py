"""research/takeover_check.py's refinements of the last round (refine=true and the settings that
build on it): which world models it trains and on what, which policies each refines from, the
paper's form beside the safeguarded one, the drift checks, and the drift table. The check
itself drives and trains for half an hour; here its chain's commands and its table's pairs.
The rounds themselves are in test_research_takeover_check.py."""

from __future__ import annotations

import json

import pytest
from research_takeover_rig import record_chain as _chain
from research_takeover_rig import world_model_runs

from research import drift_steps, takeover_check


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
    world_model_runs(runs, "takeovers1-world-model", "takeovers1-drives-world-model")
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
