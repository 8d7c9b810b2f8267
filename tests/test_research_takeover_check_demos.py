"""research/takeover_check.py's world model of the demonstrations alone (refine_in_demos, and
refine_demos_noise: another person's demonstrations for it): what that world model learns, that
refinement still learns from the chain's own frames, how the frames are counted and which IL
each refined row is paired with. Split from test_research_takeover_check_refine.py (the other
world models)."""

from __future__ import annotations

import pytest
from research_takeover_rig import record_chain as _chain
from research_takeover_rig import world_model_runs

from research import dirl_steps, takeover_check


def test_refine_in_demos_adds_a_world_model_of_the_demonstrations_alone(monkeypatch, tmp_path):
    runs, data = tmp_path / "runs" / "noise1-seed0", tmp_path / "data"
    world_model_runs(runs, "takeovers2-world-model", "takeovers2-demos-world-model")
    sets = ["--set", "rounds=2", "--set", "refine=true", "--set", "refine_in_demos=true",
            "--set", "demo_noise=1"]  # fmt: skip
    argv, rows = _chain(monkeypatch, tmp_path, *sets, sigma=1.0)
    demos_world = argv["train-noise1-seed0-takeovers2-demos-world-model"]
    # the person's demonstrations alone, from the last round's policy, labelled as the others
    episodes = demos_world[demos_world.index("--episodes") + 1 : demos_world.index("--out")]
    assert episodes == [str(data / "expert-noise1")]
    assert demos_world[demos_world.index("--init") + 1] == str(runs / "takeovers2")
    assert "takeovers_as_collisions=true" in demos_world
    # the same refinements in it, still from every frame so far
    plain = argv["train-noise1-seed0-takeovers2-refined"]
    refined = argv["train-noise1-seed0-takeovers2-demos-refined"]
    assert refined[refined.index("--init") + 1] == str(runs / "takeovers2-demos-world-model")
    assert refined == [
        str(runs / "takeovers2-demos-world-model") if a == str(runs / "takeovers2-world-model")
        else a.replace("takeovers2-refined", "takeovers2-demos-refined") for a in plain
    ]  # fmt: skip
    assert "--no-uncertainty" in argv["train-noise1-seed0-takeovers2-demos-refined-unc"]
    by_model = {r["model"]: r for r in rows}
    assert by_model["takeovers2+demos+refined"]["frames"] == by_model["takeovers2"]["frames"]
    assert by_model["takeovers2+demos+refined"]["counterfactual"] == {
        "of": "takeovers2-demos-world-model"
    }
    pairs = takeover_check.pairs(takeover_check.parse(sets))
    for base in ("takeovers2", "IL-equal-takeovers2", "takeovers2+refined",
                 "takeovers2+demos+refined-unc"):  # fmt: skip
        assert ("takeovers2+demos+refined", base) in pairs
    plan = takeover_check.plan(takeover_check.parse(sets))
    assert plan["train takeovers2-demos-world-model"] == 3  # one per seed


def test_refine_in_demos_needs_refine(capsys):
    with pytest.raises(SystemExit) as stop:
        takeover_check.parse(["--set", "refine_in_demos=true"])
    assert stop.value.code == 2
    assert "refine_in_demos: True needs refine=true" in capsys.readouterr().err


def test_refine_demos_noise_gives_that_world_model_another_persons_demonstrations(
    monkeypatch, tmp_path
):
    runs, data = tmp_path / "runs" / "noise0-seed0", tmp_path / "data"
    world_model_runs(runs, "takeovers2-world-model", "takeovers2-demos-world-model")
    sets = ["--set", "rounds=2", "--set", "refine=true", "--set", "refine_in_demos=true",
            "--set", "refine_demos_noise=0.5"]  # fmt: skip
    argv, rows = _chain(monkeypatch, tmp_path, *sets)
    world = argv["train-noise0-seed0-takeovers2-demos-world-model"]
    assert world[world.index("--episodes") + 1 : world.index("--out")] == [
        str(data / "expert-noise0.5")
    ]
    # refinement still learns from the chain's own frames alone
    refined = argv["train-noise0-seed0-takeovers2-demos-refined"]
    assert str(data / "expert-noise0.5") not in refined and str(data / "expert-noise0") in refined
    # the sloppier person's frames count toward DIRL, and IL trains at as many
    by_model = {r["model"]: r for r in rows}
    assert by_model["takeovers2+demos+refined"]["frames"] == 4000  # 3 of the chain's + 1
    assert by_model["takeovers2+refined"]["frames"] == 3000
    il = argv["train-noise0-seed0-il-equal-takeovers2-demos"]
    assert il[il.index("--episodes") + 1 : il.index("--out")] == [
        str(data / "expert-noise0"),
        *(str(data / "extra-noise0" / f"{i}") for i in range(3)),
    ]
    assert by_model["IL-equal-takeovers2-demos"]["frames"] == 4000
    cfg = takeover_check.parse(sets)
    pairs = takeover_check.pairs(cfg, 0.0)
    assert ("takeovers2+demos+refined", "IL-equal-takeovers2-demos") in pairs
    assert ("takeovers2+demos+refined", "IL-equal-takeovers2") not in pairs  # fewer frames
    assert ("takeovers2+refined", "IL-equal-takeovers2") in pairs
    # recorded as the check records its own σs, on the training placements alone
    assert takeover_check.world_demos_only(cfg) == (0.5,)
    plan = takeover_check.plan(cfg)
    assert plan["demos"] == 3 and plan["train il-equal-takeovers2-demos"] == 3
    steps = []
    dirl_steps.every_noise_demonstrations(cfg.study, lambda n, a, m: steps.append(n), also=(0.5,))
    assert steps == ["expert-noise0", "extra-noise0", "expert-noise0.5"]


@pytest.mark.parametrize(
    ("sets", "says"),
    [
        (["--set", "refine=true", "--set", "refine_demos_noise=0.5"],
         "refine_demos_noise: 0.5 needs refine_in_demos=true"),
        (["--set", "refine=true", "--set", "refine_in_demos=true", "--set",
          "refine_demos_noise=3"], "refine_demos_noise: 3 (0 to 2, or -1: the chain's own)"),
    ],
)  # fmt: skip
def test_refine_demos_noise_is_checked(capsys, sets, says):
    with pytest.raises(SystemExit) as stop:
        takeover_check.parse(sets)
    assert stop.value.code == 2
    assert says in capsys.readouterr().err


def test_the_chains_own_demonstrations_count_no_extra_frames(monkeypatch, tmp_path):
    runs = tmp_path / "runs" / "noise0.5-seed0"
    world_model_runs(
        runs,
        "takeovers1-world-model",
        "takeovers1-demos-world-model",
        counterfactual=lambda name: {},
    )
    sets = ["--set", "rounds=1", "--set", "refine=true", "--set", "refine_in_demos=true",
            "--set", "refine_demos_noise=0.5", "--set", "demo_noise=0.5"]  # fmt: skip
    argv, rows = _chain(monkeypatch, tmp_path, *sets, sigma=0.5)
    assert not any("il-equal-takeovers1-demos" in name for name in argv)
    by_model = {r["model"]: r for r in rows}
    assert by_model["takeovers1+demos+refined"]["frames"] == by_model["takeovers1"]["frames"]
    cfg = takeover_check.parse(sets)
    assert takeover_check.world_demos_only(cfg) == ()
    assert ("takeovers1+demos+refined", "IL-equal-takeovers1") in takeover_check.pairs(cfg, 0.5)
