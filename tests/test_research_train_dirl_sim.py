"""research/dirl_sim.py's bookkeeping: its settings, step plan, the frames top-up for IL at equal
frames, the paper-style table and the plot.

The study itself trains for hours (`make study`); `python -m research.dirl_sim --quick` runs every
step with the tiny profile in minutes and is how the pipeline was checked end to end.
"""

from __future__ import annotations

import dataclasses
import json

import pytest

from research import dirl_sim, dirl_steps, dirl_table, study_config
from research.study_steps import TYPICAL_S, step_kind


def _row(model, seed, completions, frames=1000, sigma=0.0, iteration=0, check=None):
    runs = [
        {"completion_ratio": c, "collisions_per_min": 3.0, "average_speed": 1.5}
        for c in completions
    ]
    mean = sum(completions) / len(completions)
    return {
        "model": model, "iteration": iteration, "demo_noise": sigma, "seed": seed,
        "frames": frames, "runs": runs, "counterfactual": check,
        "aggregate": {"completion_ratio": {"mean": mean, "std": 0.0}},
    }  # fmt: skip


def test_settings_parse_tuples_and_refuse_unknown_fields():
    cfg = dirl_sim.parse(["--set", "seeds=0,1,2", "--set", "demo_noise=0,0.5", "--set", "jobs=1"])
    assert cfg.seeds == (0, 1, 2) and cfg.demo_noise == (0.0, 0.5) and cfg.jobs == 1
    assert dirl_sim.parse(["--quick"]).profile == "tiny"
    with pytest.raises(SystemExit):
        dirl_sim.parse(["--set", "colour=red"])
    with pytest.raises(SystemExit):
        dirl_sim.parse(["--set", "iterations=many"])
    assert dirl_sim.parse(["--set", "drive_explore=false"]).drive_explore is False
    assert dirl_sim.parse(["--set", "drive_explore=true"]).drive_explore is True
    with pytest.raises(SystemExit):
        dirl_sim.parse(["--set", "drive_explore=maybe"])


def test_threads_and_jobs_default_to_every_usable_core_split_among_parallel_steps(monkeypatch):
    monkeypatch.setattr(study_config.os, "sched_getaffinity", lambda pid: set(range(16)))
    cfg = dirl_sim.parse(["--set", "parallel=3"])
    assert (cfg.threads, cfg.jobs) == (0, 0)  # "every core", resolved when steps are built
    assert (cfg.all_threads(), cfg.all_jobs(), cfg.step_threads(), cfg.step_jobs()) == (
        16,
        16,
        5,
        5,
    )
    assert "threads=5" in cfg.iterate_overrides()
    calls = []  # the demonstrations' command: every simulator process
    dirl_steps.demonstrations(cfg, lambda name, argv, marker: calls.append(argv), 0.0, "1000", "x")
    assert calls[0][calls[0].index("--jobs") + 1] == "16"
    given = dirl_sim.parse(["--set", "threads=4", "--set", "jobs=6", "--set", "parallel=2"])
    assert (given.step_threads(), given.step_jobs()) == (2, 3)


@pytest.mark.parametrize("field", ["threads=-1", "jobs=-2", "parallel=0"])
def test_negative_threads_or_jobs_are_refused_in_one_line(field, capsys):
    with pytest.raises(SystemExit) as exc:
        dirl_sim.parse(["--set", field])
    assert exc.value.code == 2
    assert (
        capsys.readouterr().err.strip().splitlines()[-1].startswith("python -m research.dirl_sim")
    )


def test_the_drives_explore_with_the_configured_noise():
    cfg = dirl_sim.parse(["--set", "explore_amplitude=0.6", "--set", "explore_hold_s=0.4,1.2"])
    args = dirl_steps.explore_args(cfg)
    assert args[0] == "--explore"
    sets = dict(a.split("=") for a in args[2::2])
    assert sets == {"noise.fraction": "0.8", "noise.amplitude": "0.6",
                    "noise.hold_min_s": "0.4", "noise.hold_max_s": "1.2"}  # fmt: skip
    assert dirl_steps.explore_args(dirl_sim.parse(["--set", "drive_explore=false"])) == []


def _total(cfg) -> int:
    return sum(dirl_steps.plan(cfg).values())


# The design before 2026-11-25's defaults: one σ > 0 seed, -unc at iteration 1 only, gradient
# refinement (so a "DIRL search iter 1" row); the plan tests below count from it.
GRADIENT_DESIGN = ["--set", "robustness_seeds=0", "--set", "unc_every_iteration=false",
                   "--set", "refine_search=false", "--set", "search_from=1"]  # fmt: skip


def test_the_default_plan_is_the_runs_of_2026_11_25():
    """σ 0: 3 seeds × (IL 2 + 3 iterations × 8 + -unc at each iteration 3 × 3 + the search row
    3) = 3 × 38; σ 0.5 and 1.0: 3 seeds each × (IL 2 + one iteration 8); demos 2 per noise. The
    σ 1.0 run of that day had its 32 steps (2 + 3 × 10)."""
    cfg = dirl_sim.parse([])
    assert cfg.refine_search and cfg.search_from == 2 and cfg.unc_every_iteration
    assert _total(cfg) == 6 + 3 * 38 + 2 * 3 * 10
    assert _total(dataclasses.replace(cfg, demo_noise=(1.0,))) == 32


def test_the_plan_counts_every_step_the_study_runs():
    cfg = dirl_sim.parse([*GRADIENT_DESIGN, "--set", "seeds=0,1", "--set", "demo_noise=0,1",
                          "--set", "iterations=2", "--set", "robustness_iterations=1"])  # fmt: skip
    # demos 2×2; σ 0 per seed: IL 2 + 2 iterations × (drive, take-overs, train, select, eval,
    # eval before refinement + IL at its frames train, eval) + -unc 3 (train, select, eval)
    # + search 3 = 24; σ 1: IL 2 + 1 iteration × 8 = 10
    assert _total(cfg) == 4 + 2 * 24 + 10
    # without the search row (or with search as the method itself): -unc alone
    for no_row in ("compare_search=false", "refine_search=true"):
        alone = dirl_sim.parse([*GRADIENT_DESIGN, "--set", "seeds=0,1", "--set", "demo_noise=0,1",
                                "--set", "iterations=2", "--set", no_row])  # fmt: skip
        assert _total(alone) == 4 + 2 * 21 + 10
    # search from iteration 2: iteration 1 by the gradient, so its search row is run
    later = dirl_sim.parse([*GRADIENT_DESIGN, "--set", "seeds=0,1", "--set", "demo_noise=0,1",
                            "--set", "iterations=2", "--set", "refine_search=true", "--set",
                            "search_from=2"])  # fmt: skip
    assert _total(later) == _total(cfg)
    # without the selection by driving, no selection and no before-refinement row
    off = dataclasses.replace(cfg, select_by_driving=False)
    assert _total(off) == 4 + 2 * 18 + 8
    # the paper's iterations (no take-overs, imitation once): drive, train, select, eval, IL ×2
    paper = dataclasses.replace(cfg, takeover_seconds=0.0, reimitate_steps=0)
    assert _total(paper) == 4 + 2 * 20 + 8


def test_the_plan_counts_steps_by_the_kind_their_names_say():
    """The ETA weighs each kind by its time: the plan's kinds are the ones step_kind reads from
    the names the study gives its steps, and each has a typical time."""
    cfg = dirl_sim.parse([*GRADIENT_DESIGN, "--set", "seeds=0,1", "--set", "demo_noise=0,1",
                          "--set", "iterations=2", "--set", "robustness_iterations=1"])  # fmt: skip
    kinds = dirl_steps.plan(cfg)
    # 2 σ0 chains × 2 iterations + 1 σ1 chain × 1; iteration 1 trains its world model anew
    assert kinds["train dirl1"] == 3 and kinds["train dirl"] == 2
    assert kinds["train il"] == 3 and kinds["train il-equal"] == 5
    assert kinds["train unc"] == kinds["train search"] == 2 and kinds["demos"] == 4
    assert kinds["drive"] == kinds["takeovers"] == 5 and kinds["select"] == 5 + 4
    # per chain: IL; per iteration: DIRL, before refinement, IL at its frames; -unc, search
    assert kinds["eval"] == 3 + 5 * 3 + 2 * 2
    assert set(kinds) <= set(TYPICAL_S)
    names = {
        "expert-noise0.5": "demos", "extra-noise1": "demos", "train-noise0-seed1-il": "train il",
        "train-noise0.5-seed2-dirl1": "train dirl1", "train-noise0-seed0-dirl3": "train dirl",
        "train-noise0-seed0-il-equal2": "train il-equal", "train-noise0-seed0-unc1": "train unc",
        "train-noise0-seed0-search1": "train search", "select-noise0-seed0-dirl2": "select",
        "eval-noise0-seed0-dirl2-imitated": "eval", "drive-noise0-seed0-iter2": "drive",
        "takeovers-noise1-seed0-iter1": "takeovers",
    }  # fmt: skip
    assert {name: step_kind(name) for name in names} == names
    # -unc at every σ 0 iteration: one more training, selection and evaluation per iteration
    every = dataclasses.replace(cfg, unc_every_iteration=True)
    assert dirl_steps.plan(every) - kinds == {"train unc": 2, "select": 2, "eval": 2}


class _Steps:
    """Records what the study would run instead of running it."""

    def __init__(self):
        self.commands: dict[str, list[str]] = {}

    def __call__(self, name, command, marker):
        self.commands[name] = command


def _flag(command: list[str], flag: str) -> str:
    return command[command.index(flag) + 1]


def test_an_iteration_drives_alone_then_with_the_noisy_person_taking_over(tmp_path):
    cfg = dirl_sim.parse(["--set", f"out={tmp_path}", "--set", "takeover_seconds=8"])
    cfg = dataclasses.replace(cfg, iteration_tracks=())  # every iteration on the training ones
    steps = _Steps()
    data = dirl_steps.iteration_drives(cfg, steps, "noise1-seed0", 1.0, 2, tmp_path / "dirl1")
    assert [d.name for d in data] == ["drives-noise1-seed0-iter2", "takeovers-noise1-seed0-iter2"]
    alone, helped = steps.commands.values()
    assert "drives" in alone and "--explore" in alone, "crashes from varied actions"
    assert "interventions" in helped and "--explore" not in helped, "the policy's own states"
    assert _flag(helped, "--noise") == "1.0", "the demonstrations' σ"
    assert _flag(helped, "--seconds") == "8.0" and _flag(helped, "--model").endswith(
        "dirl1/policy.onnx"
    )
    assert _flag(alone, "--seed-offset") == _flag(helped, "--seed-offset") == "100000"
    first = _Steps()
    dirl_steps.iteration_drives(cfg, first, "noise1-seed0", 1.0, 1, tmp_path / "il")
    assert {_flag(c, "--seed-offset") for c in first.commands.values()} == {"0"}, (
        "iteration 1 keeps the placement's seed; later ones new seeds, new episodes"
    )
    assert {_flag(c, "--tracks") for c in steps.commands.values()} == {cfg.train_tracks}
    off = dataclasses.replace(cfg, takeover_seconds=0.0)
    assert len(dirl_steps.iteration_drives(off, _Steps(), "t", 0.0, 1, tmp_path)) == 1


def test_each_iteration_can_drive_on_placements_of_its_own(tmp_path, capsys):
    """iteration_tracks: iteration k's drives and take-overs on its k-th entry (buckets moved);
    fewer entries than iterations is refused before anything runs."""
    tracks = "iteration_tracks=1040-1053,1054-1067"
    cfg = dirl_sim.parse(["--set", f"out={tmp_path}", "--set", tracks, "--set", "iterations=2"])
    for k, expected in ((1, "1040-1053"), (2, "1054-1067")):
        steps = _Steps()
        dirl_steps.iteration_drives(cfg, steps, "noise0-seed0", 0.0, k, tmp_path / "run")
        assert len(steps.commands) == 2
        assert {_flag(c, "--tracks") for c in steps.commands.values()} == {expected}
    with pytest.raises(SystemExit) as exit_:
        dirl_sim.parse(["--set", tracks, "--set", "iterations=3"])
    assert exit_.value.code == 2
    assert "iteration_tracks: 2 entries for 3 iterations" in capsys.readouterr().err


def test_each_iteration_selects_on_validation_placements_of_its_own(tmp_path, capsys):
    """select_tracks: iteration k's selection drives its k-th entry (the start's numbers on the
    placements that chose it are biased by that choice), keeping the imitated policy unless a
    candidate wins by select_margin_z standard errors; one entry serves every iteration."""
    cfg = dirl_sim.parse(["--set", f"out={tmp_path}", "--set", "iterations=3"])
    run, start = tmp_path / "dirl2", tmp_path / "dirl1"
    steps = _Steps()
    imitated = run / "checkpoints" / "imitation.pt"
    dirl_steps.select(cfg, steps, "noise0-seed0-dirl2", 2, run, start, [tmp_path], imitated)
    (command,) = steps.commands.values()
    assert _flag(command, "--tracks") == "220-239" != cfg.select_tracks[0]
    assert _flag(command, "--incumbent") == "imitated" and f"imitated={imitated}" in command
    assert _flag(command, "--margin-z") == "2.0"
    one = dirl_sim.parse(["--set", f"out={tmp_path}", "--set", "select_tracks=200-219"])
    steps = _Steps()
    dirl_steps.select(one, steps, "noise0-seed0-dirl3", 3, run, start, [tmp_path])
    (command,) = steps.commands.values()
    assert _flag(command, "--tracks") == "200-219" and "--incumbent" not in command
    with pytest.raises(SystemExit) as exit_:
        dirl_sim.parse(["--set", "select_tracks=200-219,220-239", "--set", "iterations=3"])
    assert exit_.value.code == 2
    assert "select_tracks: 2 entries for 3 iterations" in capsys.readouterr().err


def test_top_up_takes_whole_episodes_until_the_frames_are_reached(sim_episodes):
    from carrt.episodes.reader import list_episodes, read_episode

    sizes = [read_episode(p).n for p in list_episodes([str(sim_episodes)])]
    picked = dirl_steps.top_up(sim_episodes, sizes[0] + 1)
    assert len(picked) == 2
    assert dirl_steps.frames_in(picked) == sizes[0] + sizes[1]
    with pytest.raises(SystemExit, match="frames"):
        dirl_steps.top_up(sim_episodes, sum(sizes) + 1)


def test_table_pools_runs_over_seeds_per_model_and_noise():
    check = {"collision_auroc": 0.9, "rank_correlation": 0.4, "speed_mae": 0.1,
             "speed_mae_constant": 0.3}  # fmt: skip
    rows = [
        _row("IL", 0, [0.2, 0.4]), _row("IL", 1, [0.2, 0.4]),
        {**_row("DIRL iter 1", 0, [0.5], iteration=1, check=check), "chosen": "refine200"},
        _row("IL", 0, [0.1], sigma=0.5),
    ]  # fmt: skip
    lines = dirl_table.table(rows).splitlines()
    il = next(line for line in lines if line.startswith("| 0 | IL |"))
    assert "| 2 |" in il and "0.30 ± 0.10" in il and il.endswith("| — | — | — | — |")
    dirl = next(line for line in lines if "DIRL iter 1" in line)
    assert "| 0.50 |" in dirl and "| 0.90 | 0.40 | 0.10 (0.30) | refine200 |" in dirl
    assert any(line.startswith("| 0.5 | IL | 1 |") for line in lines)


def test_comparison_pairs_each_dirl_row_with_its_baselines_seed_by_seed():
    rows = [
        _row("IL", 0, [0.2, 0.4]), _row("IL", 1, [0.6, 0.8]),
        _row("DIRL iter 1", 0, [0.5, 0.5], iteration=1),
        _row("DIRL iter 1", 1, [0.5, 0.5], iteration=1),
        _row("DIRL -unc iter 1", 0, [0.4, 0.4], iteration=1),
        _row("IL, frames of iter 1", 0, [0.9, 0.9], iteration=1),
    ]  # fmt: skip
    lines = dirl_table.comparison(rows).splitlines()
    against_il = next(line for line in lines if "| DIRL iter 1 | IL |" in line)
    # seed 0: 0.5 − 0.3 = +0.20, seed 1: 0.5 − 0.7 = −0.20; mean 0 ± 0.20 over the two seeds
    assert "| 2 | +0.20, -0.20 | +0.00 ± 0.20 |" in against_il
    more_data = next(line for line in lines if "| IL, frames of iter 1 |" in line)
    assert "| 1 | -0.40 | -0.40 |" in more_data, "only seeds both rows have are paired"
    unc = next(line for line in lines if line.startswith("| 0 | DIRL -unc iter 1 |"))
    assert "| DIRL iter 1 | 1 | -0.10 |" in unc
    assert not any("| IL | IL" in line for line in lines), "IL rows have no baseline"


def test_refinement_is_compared_with_the_same_iteration_before_it():
    """With take-overs, DIRL's gain could be the take-overs alone: each DIRL row is paired with
    its own policy before refinement, and that one with IL and IL at equal frames."""
    name = dirl_table.before_refinement(2)
    assert name == "DIRL iter 2 before refinement"
    assert dirl_table.baselines("DIRL iter 2") == ["IL", "IL, frames of iter 2", name]
    assert dirl_table.baselines(name) == ["IL", "IL, frames of iter 2"]
    rows = [_row("DIRL iter 1", 0, [0.6], iteration=1),
            _row(dirl_table.before_refinement(1), 0, [0.5], iteration=1)]  # fmt: skip
    lines = dirl_table.comparison(rows).splitlines()
    assert any("| DIRL iter 1 | DIRL iter 1 before refinement | 1 | +0.10 |" in x for x in lines)


def test_the_search_row_is_compared_with_gradient_refinement_and_its_start():
    assert dirl_table.baselines(dirl_table.SEARCH_ROW) == [
        "DIRL iter 1", "DIRL iter 1 before refinement", "IL", "IL, frames of iter 1"]  # fmt: skip
    rows = [_row("DIRL iter 1", 0, [0.6], iteration=1),
            _row(dirl_table.SEARCH_ROW, 0, [0.7], iteration=1)]  # fmt: skip
    lines = dirl_table.comparison(rows).splitlines()
    assert any("| DIRL search iter 1 | DIRL iter 1 | 1 | +0.10 |" in x for x in lines)


def test_plot_writes_completion_against_frames(tmp_path):
    rows = [_row("IL", 0, [0.2]), _row("DIRL iter 1", 0, [0.3], frames=1500, iteration=1),
            _row("DIRL -unc iter 1", 0, [0.1], frames=1500, iteration=1)]  # fmt: skip
    dirl_table.plot(rows, tmp_path / "c.png")
    assert (tmp_path / "c.png").stat().st_size > 5000


def test_report_runs_nothing_and_says_what_has_not_finished(tmp_path, capsys):
    """--report on a study that has not started: no command runs, the table says so."""
    assert dirl_sim.main(["--quick", "--report", "--set", f"out={tmp_path}"]) == 0
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["complete"] is False and results["rows"] == []
    assert "expert-noise0" in results["not_finished"]
    assert "Not finished yet" in (tmp_path / "table.md").read_text()
    assert not (tmp_path / "config.json").exists(), "a report does not relabel the run"
    assert not (tmp_path / "data").exists(), "nothing ran"


def test_every_run_gets_the_refinement_method_and_its_safeguards():
    """The study's refinement settings reach iterate.py, and iterate.py accepts them."""
    from carrt.settings import apply_sets
    from research.variants.config import ResearchConfig

    cfg = dirl_sim.parse(["--set", "refine_search=true", "--set", "refine_search_margin=0.5",
                          "--set", "refine_center_gradient=false",
                          "--set", "search_from=1"])  # fmt: skip
    args = dirl_sim.run_settings(cfg, 2, 100)
    assert args[:2] == ["--seed", "2"]
    sets = [args[i + 1] for i, a in enumerate(args) if a == "--set"]
    assert {"refine_search=true", "refine_search_margin=0.5", "refine_center_gradient=false",
            "refine_candidates_every=100"} <= set(sets)  # fmt: skip
    run = apply_sets(ResearchConfig(), sets, "research/variants/config.py")
    assert run.refine_search is True and run.refine_search_margin == 0.5
    assert run.refine_center_gradient is False and run.refine_candidates_every == 100
    assert "refine_search=false" in dirl_sim.run_settings(dirl_sim.parse([]), 0, 0)


def test_search_from_refines_later_iterations_by_search_and_earlier_by_the_gradient():
    cfg = dirl_sim.parse(["--set", "refine_search=true", "--set", "search_from=2"])
    method = {k: dirl_sim.run_settings(cfg, 0, 100, iteration=k) for k in (1, 2, 3)}
    assert "refine_search=false" in method[1]
    assert "refine_search=true" in method[2] and "refine_search=true" in method[3]
    assert [dirl_steps.searches(cfg, k) for k in (1, 2, 3)] == [False, True, True]
    off = dirl_sim.parse(["--set", "refine_search=false", "--set", "search_from=2"])  # never
    assert not any(dirl_steps.searches(off, k) for k in (1, 2, 3))


def test_the_ablation_without_uncertainty_can_follow_every_iteration():
    """-unc at iteration 1 only (the studies before 2026-11-25), or at every iteration with that
    iteration's refinement method; the search row at iteration 1 only, and only where iteration
    1 refines by the gradient."""
    cfg = dirl_sim.parse(["--set", "refine_search=true", "--set", "search_from=2", "--set",
                          "unc_every_iteration=false"])  # fmt: skip
    assert [v[0] for v in dirl_sim.ablations(cfg, 1)] == ["search1", "unc1"]
    assert dirl_sim.ablations(cfg, 2) == []
    every = dataclasses.replace(cfg, unc_every_iteration=True)
    assert dirl_sim.ablations(every, 2) == [
        ("unc2", "DIRL -unc iter 2", ["--no-uncertainty"], "search")
    ]
    assert dirl_sim.ablations(every, 1)[-1][3] == "gradient"
    gradient = dirl_sim.parse(
        ["--set", "unc_every_iteration=true", "--set", "compare_search=false"]
    )
    assert [v[0] for v in dirl_sim.ablations(gradient, 3)] == ["unc3"]
    assert [v[0] for v in dirl_sim.ablations(gradient, 1)] == ["unc1"]


def test_the_tables_show_laps_per_minute_and_progress_per_metre_where_runs_have_them():
    def racing(row, laps, progress):
        for run in row["runs"]:
            run.update(laps_per_min=laps, progress_per_metre=progress)
        return row

    rows = [racing(_row("IL", 0, [0.4, 0.6]), 4.0, 0.9), racing(_row("IL", 1, [0.5]), 5.0, 0.8),
            racing(_row("DIRL iter 1", 0, [0.5], iteration=1), 4.5, 0.95),
            racing(_row("DIRL iter 1", 1, [0.5], iteration=1), 6.0, 0.85)]  # fmt: skip
    lines = dirl_table.table(rows).splitlines()
    assert "| avg m/s | laps / min | progress / m |" in lines[0]
    il = next(line for line in lines if line.startswith("| 0 | IL |"))
    # pooled over the three runs: laps 4, 4, 5; progress 0.9, 0.9, 0.8
    assert "| 1.50 ± 0.00 | 4.33 ± 0.47 | 0.87 ± 0.05 | — |" in il
    against_il = next(x for x in dirl_table.comparison(rows).splitlines() if "| IL |" in x)
    assert against_il.endswith("| +0.75 ± 0.25 |"), "Δ laps / min per seed: +0.5, +1.0"
    # a results file from before the racing numbers: its cells and Δ say "—", nothing fails
    old = [_row("IL", 0, [0.4]), _row("DIRL iter 1", 0, [0.5], iteration=1)]
    assert "| 1.50 | — | — | — |" in dirl_table.table(old).splitlines()[2]
    assert dirl_table.comparison(old).splitlines()[2].endswith("| +0.10 | +0.0 | — |")
