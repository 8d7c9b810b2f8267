"""research/refine_loop.py: the refined policy drives, its crashes teach the next world model, and
it is refined again. One chain is run recording its steps instead of running them (every episode
directory holds 1,000 frames, the policies are never driven), and what each step learns from and
starts from is checked: that is what makes the loop closed."""

from __future__ import annotations

import json
from collections import Counter

import pytest

from research import dirl_steps, refine_loop
from research.study_steps import step_kind, typical_s


def record_chain(monkeypatch, tmp_path, *sets, seed=5):
    """({step name: argv}, rows) of one σ 0 chain run with `--set`s, nothing trained or driven."""
    cfg = refine_loop.parse(["--set", f"out={tmp_path}", *sets])
    steps = []
    monkeypatch.setattr(refine_loop, "evaluate", lambda *a: {"runs": [], "aggregate": {}})
    monkeypatch.setattr(refine_loop, "frames_in", lambda paths: 1000 * len(paths))
    monkeypatch.setattr(
        dirl_steps, "top_up", lambda pool, frames: [pool / f"{i}" for i in range(frames // 1000)]
    )

    def record(name, argv, marker):
        steps.append((name, argv))

    record.counting = True  # as a counting walk: a world model not trained yet has no metrics
    rows = []
    refine_loop.chain(cfg, record, 0.0, seed, rows)
    return dict(steps), rows


def episodes_of(argv):
    return argv[argv.index("--episodes") + 1 : argv.index("--out")]


def value_of(argv, flag):
    return argv[argv.index(flag) + 1]


def sets_of(argv):
    return [argv[i + 1] for i, a in enumerate(argv) if a == "--set"]


def test_each_refined_policy_drives_and_its_crashes_teach_the_next_world_model(
    monkeypatch, tmp_path
):
    argv, rows = record_chain(monkeypatch, tmp_path, "--set", "loops=3")
    runs, data = tmp_path / "runs" / "noise0-seed5", tmp_path / "data"
    tag = "train-noise0-seed5"
    drives = [data / f"loop-drives-noise0-seed5-iter{k}" for k in (1, 2, 3)]
    starts = [runs / "il", runs / "loop1-refined", runs / "loop2-refined"]
    for k in (1, 2, 3):
        drive = argv[f"drive-noise0-seed5-loop-drives{k}"]
        assert value_of(drive, "--model") == str(starts[k - 1] / "policy.onnx")
        assert "--explore" in drive and value_of(drive, "--out") == str(drives[k - 1])
        world = argv[f"{tag}-loop{k}-world-model"]
        assert value_of(world, "--init") == str(starts[k - 1])  # continues the last world model
        assert episodes_of(world) == [str(d) for d in drives[:k]]  # the drives so far, alone
        assert "takeovers_as_collisions=false" in sets_of(world)
        refined = argv[f"{tag}-loop{k}-refined"]
        assert value_of(refined, "--init") == str(runs / f"loop{k}-world-model")
        assert episodes_of(refined) == [str(data / "expert-noise0"), *map(str, drives[:k])]
        assert "--no-uncertainty" not in refined
    # the study's steps: the first world model from scratch's count, later ones continue
    world_steps = [s for k in (1, 2, 3) for s in sets_of(argv[f"{tag}-loop{k}-world-model"])
                   if s.startswith("world_model_steps=")]  # fmt: skip
    assert world_steps[-1] == "world_model_steps=1500" and "world_model_steps=3000" in world_steps
    assert "--no-uncertainty" in argv[f"{tag}-loop3-refined-unc"]
    assert f"{tag}-loop1-refined-unc" not in argv  # -unc at the last loop only
    assert value_of(argv[f"{tag}-loop3-refined-unc"], "--init") == str(runs / "loop3-world-model")
    # IL at the last loop's recorded frames: the demonstrations and 3 drive sets = 4,000
    equal = argv[f"{tag}-il-equal-loop3"]
    assert len(episodes_of(equal)) == 4 and "--init" not in equal
    by_model = {r["model"]: r for r in rows}
    assert list(by_model) == ["IL", "loop1", "loop2", "loop3", "loop3-unc", "IL-equal-loop3"]
    assert [by_model[m]["frames"] for m in by_model] == [1000, 2000, 3000, 4000, 4000, 4000]


def test_a_loop_row_carries_its_world_models_data_and_check(monkeypatch, tmp_path):
    runs = tmp_path / "runs" / "noise0-seed5"
    for k in (1, 2):
        (runs / f"loop{k}-world-model").mkdir(parents=True)
        data = {"episodes": 40 * k, "frames": 9000 * k, "collision_frames": 800 * k}
        check = {"collision_auroc": (0.81, 0.82)[k - 1], "rank_correlation": 0.4}
        metrics = {"data": data, "counterfactual": check}
        (runs / f"loop{k}-world-model" / "metrics.json").write_text(json.dumps(metrics))
    _, rows = record_chain(monkeypatch, tmp_path, "--set", "loops=2")
    by_model = {r["model"]: r for r in rows}
    assert by_model["loop2"]["world_data"] == {
        "episodes": 80, "frames": 18000, "collision_frames": 1600
    }  # fmt: skip
    assert by_model["loop2-unc"]["counterfactual"]["collision_auroc"] == 0.82
    assert by_model["loop1"]["counterfactual"]["collision_auroc"] == 0.81
    assert "world_model" not in by_model["IL"] and "world_model" not in by_model["IL-equal-loop2"]
    table = refine_loop.world_table(rows)
    assert "| loop1 | 5 | 9000 | 800 | 0.81 | +0.40 |" in table
    assert "| loop2 | 5 | 18000 | 1600 | 0.82 | +0.40 |" in table


def test_world_learns_all_adds_the_demonstrations_to_every_world_model(monkeypatch, tmp_path):
    argv, _ = record_chain(monkeypatch, tmp_path, "--set", "loops=2", "--set", "world_learns=all")
    world = argv["train-noise0-seed5-loop2-world-model"]
    assert episodes_of(world)[0] == str(tmp_path / "data" / "expert-noise0")
    assert len(episodes_of(world)) == 3


def test_the_plan_counts_every_step_a_chain_takes_each_with_a_typical_time(monkeypatch, tmp_path):
    argv, _ = record_chain(monkeypatch, tmp_path, "--set", "loops=3")
    cfg = refine_loop.parse(["--set", "loops=3", "--set", "seeds=5"])
    plan = refine_loop.plan(cfg)
    taken = Counter(step_kind(name) for name in argv)
    taken["demos"] += 2  # the demonstrations and the second pool, recorded before the chains
    taken["eval"] += 6  # IL, three loops, -unc, IL at equal frames (evaluate is not recorded)
    assert plan == taken
    assert all(typical_s(kind) is not None for kind in plan), plan


def test_pairs_judge_the_last_loop_against_il_at_its_frames_and_its_unc():
    cfg = refine_loop.parse(["--set", "loops=2"])
    assert refine_loop.pairs(cfg) == [
        ("loop2", "IL-equal-loop2"), ("loop2", "loop2-unc"), ("loop1", "IL"), ("loop2", "IL"),
        ("loop2", "loop1"),
    ]  # fmt: skip


@pytest.mark.parametrize(
    ("setting", "says"),
    [
        ("loops=0", "loops: 0 (1 to 10)"),
        ("world_learns=demos", "world_learns: 'demos'"),
        ("study.no_such_field=1", "no_such_field"),
        ("refine_form=pure", "refine_form: 'pure'"),
    ],
)
def test_a_bad_setting_ends_in_one_line_and_exit_code_2(capsys, setting, says):
    with pytest.raises(SystemExit) as exc:
        refine_loop.parse(["--set", setting])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert says in err and "Traceback" not in err


def test_the_paper_corrected_form_refines_with_every_constraint_off_in_its_own_loop(
    monkeypatch, tmp_path
):
    sets = ("--set", "loops=2", "--set", "refine_form=paper-corrected")
    argv, rows = record_chain(monkeypatch, tmp_path, *sets)
    runs, tag = tmp_path / "runs" / "noise0-seed5", "train-noise0-seed5"
    refined = sets_of(argv[f"{tag}-paper-corrected-loop2-refined"])
    assert {"refine_w_anchor=0", "refine_w_imitation=0", "refine_center_gradient=false"} <= set(
        refined
    )
    corrections = [s for s in refined if s.startswith("collision_prior_correction=")]
    assert corrections[-1] == "collision_prior_correction=true"  # the later --set wins
    # its own drives, world models and rows: it shares the OUT and IL with the safeguards' loop
    drive = argv["drive-noise0-seed5-paper-corrected-loop-drives2"]
    assert value_of(drive, "--model") == str(runs / "paper-corrected-loop1-refined" / "policy.onnx")
    assert [r["model"] for r in rows] == [
        "IL", "paper-corrected-loop1", "paper-corrected-loop2", "paper-corrected-loop2-unc",
        "IL-equal-paper-corrected-loop2",
    ]  # fmt: skip
    cfg = refine_loop.parse(["--set", "seeds=5", *sets])
    taken = Counter(step_kind(name) for name in argv)
    taken["demos"] += 2
    taken["eval"] += 5
    assert refine_loop.plan(cfg) == taken
    assert refine_loop.pairs(cfg)[0] == ("paper-corrected-loop2", "IL-equal-paper-corrected-loop2")
