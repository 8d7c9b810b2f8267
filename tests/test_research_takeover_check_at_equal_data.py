"""research/takeover_check.py with `rounds=0`: no take-overs; IL refined in a world model of its own
demonstrations, on the same frames. That is the DIRL iteration at exactly IL's data (the
issue's "DIRL against IL at equal frames" with nothing else different), so its rows pair with
IL itself and the second demonstration pool is not recorded — unless a world model also learns
another σ's demonstrations (`refine_demos_noise`), whose refined rows pair with IL at as many
frames."""

from __future__ import annotations

import pytest
from research_takeover_rig import record_chain, world_model_runs

from research import takeover_check
from research.study_steps import typical_s

AT_EQUAL_DATA = ["--set", "rounds=0", "--set", "refine=true"]


def test_il_is_refined_in_a_world_model_of_its_own_demonstrations_on_the_same_frames(
    monkeypatch, tmp_path
):
    runs, data = tmp_path / "runs" / "noise1-seed5", tmp_path / "data"
    world_model_runs(runs, "il-world-model")
    argv, rows = record_chain(monkeypatch, tmp_path, *AT_EQUAL_DATA, sigma=1.0, seed=5)
    names = ["il", "il-world-model", "il-refined", "il-refined-unc"]
    assert list(argv) == [f"train-noise1-seed5-{name}" for name in names]
    world = argv["train-noise1-seed5-il-world-model"]
    assert world[world.index("--init") + 1] == str(runs / "il")
    for args in argv.values():  # every step learns the σ 1.0 demonstrations and nothing else
        episodes = args[args.index("--episodes") + 1 : args.index("--out")]
        assert episodes == [str(data / "expert-noise1")], args
    refined = argv["train-noise1-seed5-il-refined"]
    assert refined[refined.index("--init") + 1] == str(runs / "il-world-model")
    assert "--no-uncertainty" in argv["train-noise1-seed5-il-refined-unc"]
    assert "--no-uncertainty" not in refined
    by_model = {r["model"]: r for r in rows}
    assert list(by_model) == ["IL", "IL+refined", "IL+refined-unc"]
    assert by_model["IL+refined"]["frames"] == by_model["IL"]["frames"] == 1000
    assert by_model["IL+refined"]["counterfactual"] == {"of": "il-world-model"}


def test_the_refined_rows_pair_with_il_itself_and_each_other_once():
    cfg = takeover_check.parse([*AT_EQUAL_DATA, "--set", "demo_noise=0,1.0"])
    assert takeover_check.pairs(cfg, 1.0) == [
        ("IL+refined", "IL"), ("IL+refined-unc", "IL"), ("IL+refined", "IL+refined-unc")
    ]  # fmt: skip


def test_no_second_pool_is_recorded_and_every_planned_step_has_a_typical_time():
    cfg = takeover_check.parse([*AT_EQUAL_DATA, "--set", "demo_noise=0,1.0"])
    assert not takeover_check.needs_second_pool(cfg)  # what main tells run_check
    plan = takeover_check.plan(cfg)
    assert plan["demos"] == 2  # each σ's demonstrations, no pool for IL at equal frames
    assert plan["train il-world-model"] == plan["train il-refined-unc"] == 2 * 3
    assert plan["eval"] == 2 * 3 * 3 and "takeovers" not in plan
    assert all(typical_s(kind) is not None for kind in plan), plan


def test_a_sloppier_persons_world_model_refines_il_paired_with_il_at_as_many_frames(
    monkeypatch, tmp_path
):
    runs, data = tmp_path / "runs" / "noise0-seed5", tmp_path / "data"
    world_model_runs(runs, "il-world-model", "il-demos-world-model")
    sets = [*AT_EQUAL_DATA, "--set", "refine_in_demos=true", "--set", "refine_demos_noise=0.5"]
    argv, rows = record_chain(monkeypatch, tmp_path, *sets, seed=5)
    world = argv["train-noise0-seed5-il-demos-world-model"]
    assert world[world.index("--init") + 1] == str(runs / "il")
    assert world[world.index("--episodes") + 1 : world.index("--out")] == [
        str(data / "expert-noise0.5")
    ]
    refined = argv["train-noise0-seed5-il-demos-refined"]  # on the clean demonstrations alone
    assert refined[refined.index("--episodes") + 1 : refined.index("--out")] == [
        str(data / "expert-noise0")
    ]
    assert refined[refined.index("--init") + 1] == str(runs / "il-demos-world-model")
    il = argv["train-noise0-seed5-il-equal-demos"]  # the clean pool tops IL up to as many
    assert il[il.index("--episodes") + 1 : il.index("--out")] == [
        str(data / "expert-noise0"), str(data / "extra-noise0" / "0")
    ]  # fmt: skip
    by_model = {r["model"]: r for r in rows}
    assert by_model["IL+demos+refined"]["frames"] == by_model["IL-equal-demos"]["frames"] == 2000
    assert by_model["IL+refined"]["frames"] == 1000
    assert by_model["IL+demos+refined"]["counterfactual"] == {"of": "il-demos-world-model"}
    cfg = takeover_check.parse(sets)
    pairs = takeover_check.pairs(cfg, 0.0)
    assert ("IL+demos+refined", "IL-equal-demos") in pairs
    assert ("IL+demos+refined", "IL+refined") in pairs and ("IL+refined", "IL") in pairs
    assert takeover_check.needs_second_pool(cfg)
    plan = takeover_check.plan(cfg)
    assert plan["demos"] == 3 and plan["train il-equal-demos"] == 3  # σ 0, its pool, σ 0.5
    assert all(typical_s(kind) is not None for kind in plan), plan


@pytest.mark.parametrize(
    ("sets", "says"),
    [(["--set", "rounds=0"], "rounds: 0"), (["--set", "rounds=-1"], "rounds: -1"),
     ([*AT_EQUAL_DATA, "--set", "refine_in_demos=true"], "give refine_demos_noise"),
     ([*AT_EQUAL_DATA, "--set", "refine_with_drives=true"], "refine_with_drives: needs rounds")],
)  # fmt: skip
def test_rounds_0_needs_refine_and_takes_no_option_built_on_rounds(capsys, sets, says):
    with pytest.raises(SystemExit) as stop:
        takeover_check.parse(sets)
    assert stop.value.code == 2
    assert says in capsys.readouterr().err.strip().splitlines()[-1]
