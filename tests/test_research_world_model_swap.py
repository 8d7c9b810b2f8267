"""research/world_model_swap.py: one check's last-round policy refined in another check's world
model. The swap itself trains and drives for half an hour; here what it refines in which world
model, that its command is the take-over check's own refinement with only the world model
changed, and its one-line refusals."""

from __future__ import annotations

import dataclasses
import json

import pytest

from research import dirl_steps, takeover_check, takeover_refine, world_model_swap


def _check_tree(root, sigma: float, rounds: int, seeds=(0,), tag_bytes=b""):
    """The files a finished take-over check leaves that the swap reads."""
    data = root / "data"
    for name in [f"expert-noise{sigma:g}"] + [
        f"rounds-noise{sigma:g}-seed{s}-iter{i}" for s in seeds for i in range(1, rounds + 1)
    ]:
        (data / name).mkdir(parents=True, exist_ok=True)
    for s in seeds:
        runs = root / "runs" / f"noise{sigma:g}-seed{s}"
        world = runs / f"takeovers{rounds}-world-model"
        world.mkdir(parents=True)
        (world / "policy.pt").write_bytes(b"policy of " + tag_bytes)
        (world / "world_model.pt").write_bytes(b"world model of " + tag_bytes)
        facts = {"metrics": {"response_steering_risk": 0.1}, "counterfactual": {"rank_correlation":
                 0.2}, "data": {"train_frames": 100, "collision_frames": 6}}  # fmt: skip
        (world / "metrics.json").write_text(json.dumps(facts))
        for run in (f"takeovers{rounds}", f"il-equal-takeovers{rounds}",
                    f"takeovers{rounds}-refined"):  # fmt: skip
            (runs / run).mkdir()
            laps = {"runs": [{"track": 100, "completion_ratio": 0.5, "collisions_per_min": 2.0,
                              "average_speed": 1.5}], "aggregate": {}}  # fmt: skip
            (runs / run / "eval.json").write_text(json.dumps(laps))
        (runs / f"takeovers{rounds}" / "policy.pt").write_bytes(b"last round of " + tag_bytes)


def _swap_cfg(tmp_path, *sets):
    _check_tree(tmp_path / "half", 0.5, 2, tag_bytes=b"half")
    _check_tree(tmp_path / "one", 1.0, 2, tag_bytes=b"one")
    return world_model_swap.parse(
        ["--set", f"out={tmp_path / 'swap'}", "--set", f"policy_out={tmp_path / 'half'}",
         "--set", "policy_noise=0.5", "--set", f"world_out={tmp_path / 'one'}",
         "--set", "world_noise=1", "--set", "seeds=0", *sets]
    )  # fmt: skip


def test_the_start_policy_is_refined_in_the_other_world_model_as_the_check_refines(
    monkeypatch, tmp_path
):
    cfg = _swap_cfg(tmp_path)
    steps, rows = {}, []
    driven = {"runs": [{"track": 100, "completion_ratio": 0.7}], "aggregate": {"n": 1}}
    monkeypatch.setattr(world_model_swap, "evaluate", lambda *a: driven)
    world_model_swap.chain(cfg, lambda name, argv, marker: steps.update({name: argv}), 0, rows)
    swap = steps["train-noise0.5-seed0-takeovers2-refined-in-noise1"]
    init = swap[swap.index("--init") + 1]
    # the composed start: σ 0.5's policy, σ 1.0's world model
    assert (tmp_path / init / "policy.pt").read_bytes() == b"policy of half"
    assert (tmp_path / init / "world_model.pt").read_bytes() == b"world model of one"

    # the take-over check's own refinement of the same round: the same command but for where
    # it starts (its own world model's run) and where it writes
    check = takeover_check.parse(["--set", f"out={tmp_path / 'half'}", "--set", "refine=true",
                                  "--set", "demo_noise=0.5"])  # fmt: skip
    recorded = {}
    monkeypatch.setattr(takeover_check, "evaluate", lambda *a: {"runs": [], "aggregate": {}})
    for module in (takeover_check, takeover_refine):
        monkeypatch.setattr(module, "frames_in", lambda paths: 1000 * len(paths))
    monkeypatch.setattr(dirl_steps, "top_up", lambda pool, frames: [pool])
    takeover_check.chain(check, lambda n, argv, m: recorded.update({n: argv}), 0.5, 0, [])
    own = recorded["train-noise0.5-seed0-takeovers2-refined"]
    out = str(tmp_path / "swap" / "runs" / "noise0.5-seed0" / "takeovers2-refined-in-noise1")
    own_world = str(tmp_path / "half" / "runs" / "noise0.5-seed0" / "takeovers2-world-model")
    assert swap == [out if a.endswith("takeovers2-refined") else init if a == own_world else a
                    for a in own]  # fmt: skip
    # the rows: the start, IL at its frames and its own refinement as the check drove them,
    # then the swap's laps
    models = ["takeovers2", "IL-equal-takeovers2", "takeovers2+refined",
              "takeovers2+refined-in-noise1"]  # fmt: skip
    assert [r["model"] for r in rows] == models
    assert rows[0]["runs"][0]["completion_ratio"] == 0.5
    assert rows[3]["runs"] == driven["runs"] and rows[3]["aggregate"] == {"n": 1}
    # the swapped row says which world model it ran in and what that one is
    facts = rows[3]["world_model"]
    assert facts["run"] == str(
        tmp_path / "one" / "runs" / "noise1-seed0" / "takeovers2-world-model"
    )
    assert (facts["train_frames"], facts["collision_frames"]) == (100, 6)
    assert facts["response_steering_risk"] == 0.1
    assert facts["counterfactual"] == {"rank_correlation": 0.2}
    assert not any("world_model" in row for row in rows[:3])


def test_the_swapped_rows_are_paired_with_the_start_and_its_own_refinement(tmp_path):
    rows = [{"model": m, "seed": 0, "runs": [{"track": 100, "completion_ratio": c,
             "collisions_per_min": 1.0, "average_speed": 1.0}],
             "moved": None if m == "takeovers2" else {"steering": 0.02, "throttle": 0.01,
                                                       "throttle_signed": s}}
            for m, c, s in (("takeovers2", 0.5, 0), ("takeovers2+refined", 0.6, 0.01),
                            ("takeovers2+refined-in-noise1", 0.4, -0.01))]  # fmt: skip
    table = world_model_swap.moves_table(rows)
    assert "| takeovers2+refined | 1 | 0.0200 | 0.0100 | +0.0100 |" in table
    assert "| takeovers2+refined-in-noise1 | 1 | 0.0200 | 0.0100 | -0.0100 |" in table
    assert "takeovers2 |" not in table.replace("takeovers2+", "")


@pytest.mark.parametrize(
    ("sets", "says"),
    [
        (["--set", "world_noise=0.7"], "noise0.7-seed0/takeovers2-world-model/world_model.pt"),
        (["--set", "policy_rounds=3"], "takeovers3-world-model/policy.pt"),
        (["--set", "policy_rounds=0"], "policy_rounds: 0 (1 or more)"),
        (["--set", "seeds=0,1"], "(seed 1)"),
        (["--set", "world_data=drives"], "world_data: 'drives' (one of all, demos, rounds)"),
    ],
)
def test_a_check_that_did_not_make_what_the_swap_needs_is_refused_in_one_line(
    tmp_path, capsys, sets, says
):
    with pytest.raises(SystemExit) as stop:
        _swap_cfg(tmp_path, *sets)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert says in err and "Traceback" not in err


def test_unc_adds_the_papers_ablation_in_the_same_other_world_model(monkeypatch, tmp_path):
    cfg = _swap_cfg(tmp_path, "--set", "unc=true")
    steps, rows = {}, []
    monkeypatch.setattr(world_model_swap, "evaluate", lambda *a: {"runs": [], "aggregate": {}})
    world_model_swap.chain(cfg, lambda name, argv, marker: steps.update({name: argv}), 0, rows)
    refined = steps["train-noise0.5-seed0-takeovers2-refined-in-noise1"]
    unc = steps["train-noise0.5-seed0-takeovers2-refined-unc-in-noise1"]
    # the same start, world model and settings; only the uncertainty term dropped
    out = refined[refined.index("--out") + 1]
    assert [a for a in unc if a != "--no-uncertainty"] == [
        a.replace("refined-in-noise1", "refined-unc-in-noise1") if a == out else a for a in refined
    ]
    assert "--no-uncertainty" in unc and "--no-uncertainty" not in refined
    assert [r["model"] for r in rows][-2:] == [
        "takeovers2+refined-in-noise1", "takeovers2+refined-unc-in-noise1"]  # fmt: skip


@pytest.mark.parametrize("part", ["demos", "rounds"])
def test_world_data_learns_the_other_world_model_anew_on_part_of_its_frames(
    monkeypatch, tmp_path, part
):
    cfg = _swap_cfg(tmp_path, "--set", f"world_data={part}")
    steps = {}

    def step(name, argv, marker):
        steps[name] = argv
        if "world-model" in name:  # the world model it learns
            marker.parent.mkdir(parents=True, exist_ok=True)
            (marker.parent / "world_model.pt").write_bytes(b"learnt on " + part.encode())

    monkeypatch.setattr(world_model_swap, "evaluate", lambda *a: {"runs": [], "aggregate": {}})
    world_model_swap.chain(cfg, step, 0, [])
    learn = steps[f"train-noise1-seed0-takeovers2-{part}-world-model"]
    data = tmp_path / "one" / "data"
    wanted = [data / "expert-noise1"] if part == "demos" else [
        data / "rounds-noise1-seed0-iter1", data / "rounds-noise1-seed0-iter2"]  # fmt: skip
    episodes = learn[learn.index("--episodes") + 1 : learn.index("--out")]
    assert episodes == [str(p) for p in wanted]
    # the check's own world-model command: from the world check's last round, its labels
    assert learn[learn.index("--init") + 1] == str(tmp_path / "one" / "runs" / "noise1-seed0"
                                                   / "takeovers2")  # fmt: skip
    assert learn == takeover_refine.world_model_cmd(
        cfg.study, wanted, tmp_path / "swap" / "runs" / "noise1-seed0" /
        f"takeovers2-{part}-world-model", tmp_path / "one" / "runs" / "noise1-seed0" /
        "takeovers2", 0, "takeovers_as_collisions=true")  # fmt: skip
    refine = steps[f"train-noise0.5-seed0-takeovers2-refined-in-noise1-{part}"]
    init = refine[refine.index("--init") + 1]
    assert (tmp_path / init / "world_model.pt").read_bytes() == b"learnt on " + part.encode()
    assert (tmp_path / init / "policy.pt").read_bytes() == b"policy of half"


def test_placements_the_check_did_not_drive_drive_its_own_rows_here_too(
    monkeypatch, tmp_path, capsys
):
    half = tmp_path / "half" / "runs" / "noise0.5-seed0"
    # validation placements the check never drove: without its policies the swap refuses
    with pytest.raises(SystemExit) as stop:
        _swap_cfg(tmp_path, "--set", "eval_tracks=200-201")
    assert stop.value.code == 2
    assert "takeovers2/policy.onnx does not exist" in capsys.readouterr().err
    for run in ("takeovers2", "il-equal-takeovers2", "takeovers2-refined"):
        (half / run / "policy.onnx").write_bytes(b"onnx of " + run.encode())
    # the check drove its refinement there once already: those laps are read, not driven again
    mine = {"runs": [{"track": 200, "completion_ratio": 0.9}], "aggregate": {}}
    (half / "takeovers2-refined" / "eval-200-201.json").write_text(json.dumps(mine))
    cfg = world_model_swap.parse(
        ["--set", f"out={tmp_path / 'swap'}", "--set", f"policy_out={tmp_path / 'half'}",
         "--set", "policy_noise=0.5", "--set", f"world_out={tmp_path / 'one'}",
         "--set", "world_noise=1", "--set", "seeds=0", "--set", "eval_tracks=200-201"]
    )  # fmt: skip
    driven, rows = [], []

    def evaluate(study, step, name, onnx, result):
        driven.append((name, onnx.read_bytes() if onnx.is_file() else None, result))
        return {"runs": [{"track": 200, "completion_ratio": 0.1 * len(driven)}], "aggregate": {}}

    monkeypatch.setattr(world_model_swap, "evaluate", evaluate)
    world_model_swap.chain(cfg, lambda name, argv, marker: None, 0, rows)
    swap_runs = tmp_path / "swap" / "runs" / "noise0.5-seed0"
    assert [(n, o) for n, o, _ in driven[:2]] == [
        ("noise0.5-seed0-takeovers2-200-201", b"onnx of takeovers2"),
        ("noise0.5-seed0-IL-equal-takeovers2-200-201", b"onnx of il-equal-takeovers2"),
    ]
    # written into the swap's own OUT, never into the check's
    assert driven[0][2] == swap_runs / "takeovers2" / "eval-200-201.json"
    assert len(driven) == 3 and driven[2][0].endswith("refined-in-noise1-200-201")
    by_model = {r["model"]: r for r in rows}
    assert by_model["takeovers2+refined"]["runs"] == mine["runs"]
    assert by_model["takeovers2"]["runs"][0]["completion_ratio"] == 0.1
    assert by_model["takeovers2"]["run"] == str(half / "takeovers2")
    assert "world_model" in by_model["takeovers2+refined-in-noise1"]
    assert not any("world_model" in by_model[m] for m in ("takeovers2", "IL-equal-takeovers2"))


def test_each_swap_and_set_of_placements_gets_its_own_results_file(tmp_path):
    demos = _swap_cfg(tmp_path / "demos", "--set", "world_data=demos")
    cfgs = [_swap_cfg(tmp_path / "all"), _swap_cfg(tmp_path / "unc", "--set", "unc=true"), demos,
            dataclasses.replace(demos, eval_tracks="200-259")]  # fmt: skip
    assert [world_model_swap.results_name(c) for c in cfgs] == [
        "swap-noise0.5-refined-in-noise1", "swap-noise0.5-refined-in-noise1",
        "swap-noise0.5-refined-in-noise1-demos", "swap-noise0.5-refined-in-noise1-demos-200-259"
    ]  # fmt: skip
