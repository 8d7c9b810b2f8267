"""training/pace.py: the expected duration up front and the one warning when a run is slow."""

from __future__ import annotations

import json

from training.pace import MEASURE, WARMUP, WINDOW_S, Pace


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def pace(tmp_path, clock):
    lines: list[str] = []
    return Pace("cpu/threads2", path=tmp_path / "rates.json", clock=clock, say=lines.append), lines


def run_steps(p: Pace, clock: Clock, n: int, seconds_each: float) -> None:
    for _ in range(n):
        clock.t += seconds_each
        p.step()


def test_a_first_run_states_each_stage_expectation_after_its_first_steps(tmp_path):
    clock = Clock()
    p, lines = pace(tmp_path, clock)
    p.announce("cpu", [("imitation", 1200, 64), ("world_model", 0, 32)])
    assert "has not run them yet" in lines[0] and "imitation 1200" in lines[0]
    assert "world_model" not in lines[0]  # nothing left to do there
    p.begin("cpu", "imitation", 64, 0, 1200)
    run_steps(p, clock, WARMUP + MEASURE, 0.5)  # 2 steps/s
    assert lines[1] == (
        "carrt-train: imitation: expected ~10 min on this machine (1200 steps at 2 steps/s)"
    )
    run_steps(p, clock, 40, 0.5)
    p.end()
    assert json.loads((tmp_path / "rates.json").read_text()) == {
        "cpu/imitation/batch64/cpu/threads2": 2.0
    }
    assert len(lines) == 2  # no warning at the expected pace


def test_the_next_run_says_its_duration_up_front_and_warns_once_when_slow(tmp_path):
    (tmp_path / "rates.json").write_text(json.dumps({"cpu/imitation/batch64/cpu/threads2": 2.0}))
    clock = Clock()
    p, lines = pace(tmp_path, clock)
    p.announce("cpu", [("imitation", 1200, 64)])
    assert lines == [
        "carrt-train: imitation 1200 steps: expected ~10 min on this machine "
        "(its step rates measured before)"
    ]
    p.begin("cpu", "imitation", 64, 0, 1200)
    run_steps(p, clock, WARMUP + round(WINDOW_S / 0.5), 0.5)  # one window at the expected pace
    assert len(lines) == 1
    run_steps(p, clock, 3 * round(WINDOW_S / 1.5), 1.5)  # three windows at a third of it
    warnings = [line for line in lines if "slower" in line]
    assert warnings == [
        "carrt-train: imitation runs 3.0x slower than expected (0.667 against 2 steps/s): "
        "another job is using the cores?"
    ]


def test_a_run_of_another_batch_size_or_an_unreadable_cache_expects_nothing(tmp_path):
    (tmp_path / "rates.json").write_text("not json")
    p, lines = pace(tmp_path, Clock())
    p.announce("cpu", [("imitation", 100, 128)])
    assert "has not run them yet" in lines[0]


def test_carrt_train_measures_a_stage_and_the_next_run_says_its_duration_up_front(
    sim_episodes, tmp_path, monkeypatch, capsys
):
    import torch

    from training.one_run import main

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    steps = WARMUP + MEASURE + 2
    argv = ["--episodes", str(sim_episodes), "--profile", "tiny", "--set", "threads=1",
            "--set", "imitation_batch_size=8", "--set", f"imitation_steps={steps}",
            "--set", "world_model_steps=0", "--set", "refine_steps=0", "--set", "export=false",
            "--set", "figures=false", "--set", "eval_windows=32"]  # fmt: skip
    before = torch.get_num_threads()
    try:
        assert main([*argv, "--out", str(tmp_path / "first")]) == 0
        first = capsys.readouterr().err
        assert "has not run them yet" in first
        assert "carrt-train: imitation: expected ~" in first and f"({steps} steps at" in first
        assert main([*argv, "--out", str(tmp_path / "second")]) == 0
        second = capsys.readouterr().err
        assert f"carrt-train: imitation {steps} steps: expected ~" in second
        assert "on this machine (its step rates measured before)" in second
    finally:
        torch.set_num_threads(before)
