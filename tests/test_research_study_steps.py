"""How the study runs its steps (research/study_steps.py): at most `parallel` commands at once
across chains, each chain's steps in order, rows in chain order, finished steps skipped, a failure
stopping every chain. Real subprocesses that record when they ran."""

from __future__ import annotations

import functools
import json
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from research import dirl_sim, dirl_steps, study_steps
from research.study_steps import TYPICAL_S, StudyStep, finished_steps, run_chains

RECORD = (
    "import json, sys, time; start = time.monotonic(); time.sleep(float(sys.argv[2])); "
    "open(sys.argv[1], 'w').write(json.dumps([start, time.monotonic()]))"
)


def chain(step: StudyStep, out: Path, name: str, steps: int, rows: list, fail_at: int = -1):
    for k in range(steps):
        code = RECORD if k != fail_at else "raise SystemExit(3)"
        step(f"{name}-{k}", [sys.executable, "-c", code, str(out / f"{name}-{k}.json"), "0.8"],
             out / "markers" / f"{name}-{k}")  # fmt: skip
        rows.append(f"{name}-{k}")


def intervals(out: Path) -> list[tuple[float, float]]:
    return [tuple(json.loads(p.read_text())) for p in sorted(out.glob("*.json"))]


def most_at_once(spans: list[tuple[float, float]]) -> int:
    events = sorted([(s, 1) for s, _ in spans] + [(e, -1) for _, e in spans])
    running = peak = 0
    for _, change in events:
        running += change
        peak = max(peak, running)
    return peak


def test_chains_share_the_slots_and_their_rows_keep_chain_order(tmp_path, capsys):
    step = StudyStep(tmp_path, 8, parallel=2)
    names = ["a", "b", "c", "d"]
    rows, missing = run_chains([functools.partial(chain, step, tmp_path, n, 2) for n in names])
    assert rows == [f"{n}-{k}" for n in names for k in range(2)] and missing == []
    spans = intervals(tmp_path)
    assert len(spans) == 8 and most_at_once(spans) == 2, "two at once, never three"
    assert "[8/8]" in capsys.readouterr().out and (tmp_path / "logs" / "a-0.log").is_file()
    # Run again: every step has its marker, nothing runs (the study resumes where it stopped).
    for p in tmp_path.glob("*.json"):
        p.unlink()
    again = StudyStep(tmp_path, 8, parallel=2)
    assert run_chains([functools.partial(chain, again, tmp_path, n, 2) for n in names])[0] == rows
    assert intervals(tmp_path) == []


def test_one_at_a_time_when_parallel_is_one(tmp_path):
    step = StudyStep(tmp_path, 4, parallel=1)
    run_chains([functools.partial(chain, step, tmp_path, n, 2) for n in "ab"])
    assert most_at_once(intervals(tmp_path)) == 1


def test_a_failed_step_stops_every_chain_and_is_reported_after_they_end(tmp_path):
    step = StudyStep(tmp_path, 6, parallel=2)
    chains = [functools.partial(chain, step, tmp_path, "bad", 3, fail_at=0),
              functools.partial(chain, step, tmp_path, "good", 3)]  # fmt: skip
    with pytest.raises(SystemExit, match="bad-0 failed"):
        run_chains(chains)
    assert not (tmp_path / "markers" / "bad-0").exists()
    assert not (tmp_path / "markers" / "good-2").exists(), "the other chain stopped early"


def test_report_only_runs_nothing_and_names_each_chain_s_first_missing_step(tmp_path):
    (tmp_path / "markers").mkdir()
    (tmp_path / "markers" / "a-0").touch()
    step = StudyStep(tmp_path, 4, report_only=True)
    rows, missing = run_chains([functools.partial(chain, step, tmp_path, n, 2) for n in "ab"])
    assert rows == ["a-0"] and missing == ["a-1", "b-0"]
    assert intervals(tmp_path) == []


def test_the_eta_weighs_the_steps_left_by_their_kind(tmp_path):
    """Three trainings and three evaluations planned, one at a time. Before anything ran, each
    kind at its typical time (research/study_steps.TYPICAL_S); a kind that ran, at its own mean;
    a step reused from identical weights counts as done and took nothing."""
    il, ev = TYPICAL_S["train il"], TYPICAL_S["eval"]
    step = StudyStep(tmp_path, {"train il": 3, "eval": 3}, parallel=1)
    assert step.eta_s() == pytest.approx(3 * il + 3 * ev)
    step.done_by_kind["train il"] += 1
    step.seconds["train il"].append(2 * il)
    assert step.eta_s() == pytest.approx(2 * 2 * il + 3 * ev), "a training says nothing of drives"
    step.done_by_kind["eval"] += 1
    step.seconds["eval"].append(50.0)
    assert step.eta_s() == pytest.approx(2 * 2 * il + 2 * 50)
    step.reuse("eval-noise0-seed0-dirl1-imitated", "same weights")  # counted, took nothing
    assert step.eta_s() == pytest.approx(2 * 2 * il + 1 * 50)
    assert step.seconds["eval"] == [50.0]
    two = StudyStep(tmp_path, {"train il": 3, "eval": 3}, parallel=2)
    assert two.eta_s() == pytest.approx((3 * il + 3 * ev) / 2), "typical times, two at once"


def test_a_kind_not_run_yet_is_scaled_by_its_own_family_only(tmp_path):
    """The one-command study of 2026-11-26 made its demonstrations 5 times faster than their
    (then stale) typical time, and one scale took every training down as much: "ETA ~48 min"
    for 93. Demonstrations at 1/5 of typical now scale the evaluations (the simulator's
    family), not the trainings; a training at twice its typical time scales the other
    trainings, a world model among them, found by what it does."""
    plan = {"demos": 2, "eval": 2, "train il": 1, "train takeovers": 2,
            "train takeovers3-drives-world-model": 1}  # fmt: skip
    step = StudyStep(tmp_path, plan, parallel=1)
    step.done_by_kind["demos"] += 1
    step.seconds["demos"].append(TYPICAL_S["demos"] / 5)
    trainings = TYPICAL_S["train il"] + 2 * TYPICAL_S["train takeovers"]
    trainings += TYPICAL_S["train world-model"]
    assert step.eta_s() == pytest.approx(
        TYPICAL_S["demos"] / 5 + 2 * TYPICAL_S["eval"] / 5 + trainings
    )
    step.done_by_kind["train il"] += 1
    step.seconds["train il"].append(2 * TYPICAL_S["train il"])
    trainings = 2 * (2 * TYPICAL_S["train takeovers"] + TYPICAL_S["train world-model"])
    assert step.eta_s() == pytest.approx(
        TYPICAL_S["demos"] / 5 + 2 * TYPICAL_S["eval"] / 5 + trainings
    )


def test_typical_times_name_a_checks_world_models_and_refinements_by_what_they_do():
    assert study_steps.typical_s("train takeovers3-world-model") == TYPICAL_S["train world-model"]
    assert (
        study_steps.typical_s("train takeovers3-drives-crashes-only-member")
        == TYPICAL_S["train world-model"]
    )
    for kind in ("train takeovers3-refined-unc", "train takeovers3-drives-paper-corrected"):
        assert study_steps.typical_s(kind) == TYPICAL_S["train refine"], kind
    assert study_steps.typical_s("train takeovers") == TYPICAL_S["train takeovers"]
    assert study_steps.typical_s("drift") is None and study_steps.typical_s("train other") is None


def test_a_kind_with_no_typical_time_is_guessed_from_its_family(tmp_path):
    step = StudyStep(tmp_path, {"drift": 2, "demos": 2}, parallel=1)
    assert step.eta_s() == pytest.approx(2 * TYPICAL_S["demos"]), "nothing ran: no guess"
    step.done_by_kind["demos"] += 1
    step.seconds["demos"].append(10.0)
    assert step.eta_s() == pytest.approx(10.0 + 2 * 10.0), "every step's mean, none of its own"
    step.seconds["train il"].append(300.0)
    assert step.eta_s() == pytest.approx(10.0 + 2 * 300.0), "its family's mean"


def test_a_plain_count_plans_one_kind_of_step(tmp_path, capsys):
    step = StudyStep(tmp_path, 4, parallel=2)
    run_chains([functools.partial(chain, step, tmp_path, n, 2) for n in "ab"])
    assert step.done_by_kind == {"step": 4} and len(step.seconds["step"]) == 4
    assert step.eta_s() == 0.0 and "[4/4]" in capsys.readouterr().out


def test_a_resumed_study_leaves_its_finished_steps_out_of_the_eta(tmp_path):
    """An earlier invocation finished both evaluations: the walk finds them without running
    anything, and the ETA counts only the drives, also once the chains reach the evaluations."""
    (tmp_path / "markers").mkdir()
    for name in ("eval-0", "eval-1"):
        (tmp_path / "markers" / name).touch()
    plan = {"eval": 2, "drive": 2}

    def walk(step: StudyStep) -> None:
        run_chains([functools.partial(chain, step, tmp_path, n, 2) for n in ("eval", "drive")])

    finished = finished_steps(tmp_path, plan, walk)
    assert finished == {"eval": 2} and intervals(tmp_path) == [], "found, nothing run"
    fresh = StudyStep(tmp_path, plan, parallel=1)
    assert fresh.eta_s() == pytest.approx(2 * TYPICAL_S["eval"] + 2 * TYPICAL_S["drive"])
    resumed = StudyStep(tmp_path, plan, parallel=1, finished_before=finished)
    assert resumed.eta_s() == pytest.approx(2 * TYPICAL_S["drive"])
    walk(resumed)  # the drives run; the evaluations are reached, not counted twice
    assert len(intervals(tmp_path)) == 2 and resumed.eta_s() == 0.0


def test_finished_steps_behind_an_unfinished_one_are_counted_once(tmp_path):
    """The walk goes on past a step that has not run, so an evaluation finished earlier but
    behind it is counted before the chain reaches it, and not again when it does (the take-over
    check of 2026-11-26 said "ETA ~140 min" with 41 steps left: its walk stopped at the first
    step that had not run and priced the finished evaluations behind it as left)."""
    (tmp_path / "markers").mkdir()
    (tmp_path / "markers" / "eval-1").touch()  # behind drive-0 in its chain
    plan = {"drive": 1, "eval": 1}

    def walk(step: StudyStep) -> None:
        def one_chain(rows):
            step("drive-0", [sys.executable, "-c", ""], tmp_path / "markers" / "drive-0")
            step("eval-1", [sys.executable, "-c", ""], tmp_path / "markers" / "eval-1")

        run_chains([one_chain])

    finished = finished_steps(tmp_path, plan, walk)
    assert finished == {"eval": 1}, "found behind drive-0, which has not run"
    resumed = StudyStep(tmp_path, plan, parallel=1, finished_before=finished)
    assert resumed.eta_s() == pytest.approx(TYPICAL_S["drive"])
    walk(resumed)
    assert resumed.done_by_kind == {"drive": 1, "eval": 1} and resumed.eta_s() == 0.0


def test_the_counting_walk_passes_an_evaluation_that_has_not_run_and_stops_where_files_are_needed(
    tmp_path,
):
    """An evaluation that has not run gives the walk an empty result (its rows are thrown
    away) and the finished training behind it is counted; a chain that needs episodes a step
    that has not run would write stops there, and the other chains' counts stand."""
    markers = tmp_path / "markers"
    markers.mkdir()
    (markers / "train-b").touch()
    cfg = dirl_sim.StudyConfig(out=str(tmp_path))

    def ran(name: str) -> list[str]:
        return [sys.executable, "-c", RECORD, str(tmp_path / f"{name}.json"), "0"]

    def walk(step: StudyStep) -> None:
        def evaluated_then_trained(rows):
            out = dirl_steps.evaluate(cfg, step, "a", tmp_path / "a.onnx", tmp_path / "a.json")
            rows.append(out)
            step("train-b", ran("train-b"), markers / "train-b")

        def needs_episodes(rows):
            step("drive-c", ran("drive-c"), markers / "drive-c")
            dirl_steps.frames_in([tmp_path / "no-episodes-yet"])
            step("train-d", ran("train-d"), markers / "train-d")

        run_chains([evaluated_then_trained, needs_episodes])

    plan = {"eval": 1, "train b": 1, "drive": 1, "train d": 1}
    assert finished_steps(tmp_path, plan, walk) == {"train b": 1}
    assert intervals(tmp_path) == [], "nothing ran"
    with pytest.raises(FileNotFoundError):  # a real run reads the evaluation it ran
        study_steps.output_of(StudyStep(tmp_path, plan), tmp_path / "a.json")


def test_a_step_counts_as_done_when_it_finishes_and_a_running_one_by_what_is_left(tmp_path):
    """Five world models planned, two slots: until 2026-11-27 a step waiting for a slot counted
    as done, and the ETA said ~14 min for ~24. Now two running steps count by what is left of
    their expected time, the three waiting ones in full."""
    each = TYPICAL_S["train world-model"]
    step = StudyStep(tmp_path, {"train takeovers3-world-model": 5}, parallel=2)
    now = study_steps.time.monotonic()
    step.running = {"a": ("train takeovers3-world-model", now - 100.0),
                    "b": ("train takeovers3-world-model", now - 10 * each)}  # fmt: skip
    assert step.eta_s() == pytest.approx((3 * each + (each - 100.0) + 0.0) / 2, abs=1.0)


def test_the_progress_count_and_the_eta_see_a_step_only_once_it_finished(tmp_path):
    """Two chains, one slot: while the first step runs, the second waits and neither is done."""
    seen = []
    step = StudyStep(tmp_path, {"step": 2}, parallel=1)

    def chain(name, rows):
        argv = [sys.executable, "-c", "import time; time.sleep(0.5)"]
        step(name, argv, tmp_path / f".done-{name}")

    with ThreadPoolExecutor(max_workers=3) as pool:
        running = pool.submit(run_chains, [functools.partial(chain, n) for n in ("a", "b")])
        deadline = study_steps.time.monotonic() + 10
        while not step.running and study_steps.time.monotonic() < deadline:
            study_steps.time.sleep(0.01)
        with step.lock:
            seen.append((step.done, dict(step.done_by_kind), len(step.running)))
        running.result()
    assert seen == [(0, {}, 1)]
    assert step.done == 2 and step.done_by_kind == {"step": 2} and step.running == {}
