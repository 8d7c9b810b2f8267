"""`carrt eval`: a policy judged by driving, the paper's table with mean ± std."""

from __future__ import annotations

import json

import pytest
from onnx_models import build_policy

from carrt.arg_types import parse_int_list
from carrt.cli import main
from carrt.errors import UserError
from carrt.sim.evaluate import evaluate


def test_the_expert_completes_without_collisions_and_the_table_has_mean_and_std(tmp_path, capsys):
    out = tmp_path / "expert.json"
    code = main(["eval", "--expert", "--layout", "hard", "--tracks", "100-101", "--seconds", "10",
                 "--json", str(out)])  # fmt: skip
    assert code == 0
    text = capsys.readouterr().out
    assert "| scripted expert | 2 |" in text and "±" in text
    result = json.loads(out.read_text())
    assert [r["track"] for r in result["runs"]] == [100, 101]
    for run in result["runs"]:
        assert run["completion_ratio"] > 0.5 and run["collisions"] == 0
        assert run["average_speed"] > 1.0
    agg = result["aggregate"]
    assert agg["collisions_per_min"] == {"mean": 0.0, "std": 0.0}
    assert set(agg) >= {"completion_ratio", "collisions_per_min", "average_speed", "laps"}


def test_a_policy_that_drives_into_the_fence_collides_and_parallel_runs_agree(tmp_path):
    model = build_policy(tmp_path / "crash.onnx", steering=0.0, throttle=(0.8, 0.0))
    serial = evaluate(model, "easy", [0, 1], 10.0, [0], jobs=1)
    assert all(r["collisions"] > 0 for r in serial["runs"])
    assert serial["aggregate"]["collisions_per_min"]["mean"] > 6
    assert serial["aggregate"]["completion_ratio"]["mean"] < 0.5
    parallel = evaluate(model, "easy", [0, 1], 10.0, [0], jobs=2)
    assert parallel["runs"] == serial["runs"], "the simulated clock is deterministic"


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--model", "missing.onnx"], "no such file"),
        (["--expert", "--tracks", "104-100"], "--tracks"),
        (["--expert", "--tracks", "a,b"], "--tracks"),
        (["--expert", "--seconds", "nan"], "--seconds"),
        (["--expert", "--seconds", "0"], "--seconds"),
        (["--expert", "--jobs", "0"], "--jobs"),
        (["--expert", "--expert-intervene"], "needs --model"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(argv, message, capsys):
    assert main(["eval", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err


def test_track_lists_and_ranges():
    assert parse_int_list("100-102,7", "tracks") == [100, 101, 102, 7]
    assert parse_int_list("3", "seeds") == [3]
    with pytest.raises(UserError):
        parse_int_list("-1", "seeds")


def test_runs_in_this_process_leave_the_signal_handlers_as_they_found_them():
    """A session installs its own SIGINT/SIGTERM handlers while it runs; several sessions in one
    process (carrt eval with one job) must not leave Ctrl-C bound to a finished loop."""
    import signal

    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    evaluate(None, layout="easy", tracks=(3,), seconds=3.0)
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


def test_json_and_table_carry_the_racing_numbers_per_run_and_as_mean_and_std(tmp_path, capsys):
    out = tmp_path / "demo.json"
    code = main(["eval", "--model", "demo", "--tracks", "100", "--seconds", "20",
                 "--json", str(out)])  # fmt: skip
    assert code == 0
    header, _, row = capsys.readouterr().out.splitlines()[1:4]
    assert header.endswith("| laps | laps / min | lap time s | progress / m |")
    result = json.loads(out.read_text())
    (run,) = result["runs"]
    assert run["laps"] >= 1, "20 s is more than a lap of the shipped policy"
    assert run["laps_per_min"] == pytest.approx(run["laps"] / (run["driving_time"] / 60))
    assert run["best_lap"] <= run["lap_time_mean"] < 20.0
    assert 0.8 < run["progress_per_metre"] < 1.1, "the shipped policy keeps to the line"
    agg = result["aggregate"]
    assert agg["laps_per_min"] == {"mean": run["laps_per_min"], "std": 0.0}
    assert agg["progress_per_metre"]["mean"] == run["progress_per_metre"]
    assert agg["lap_time_mean"] == {"mean": run["lap_time_mean"], "std": 0.0, "runs": 1}
    assert row.endswith(f"| {run['lap_time_mean']:.2f} ± 0.00 | {run['progress_per_metre']:.2f}"
                        " ± 0.00 |")  # fmt: skip


def test_lap_times_average_only_over_runs_that_have_a_clean_lap():
    from carrt.sim.evaluate import aggregate, format_table

    base = {"completion_ratio": 0.5, "collisions_per_min": 2.0, "average_speed": 1.5, "laps": 1,
            "laps_per_min": 3.0, "progress_per_metre": 0.9, "collisions": 1, "top_speed": 2.0,
            "distance": 30.0, "seed": 0}  # fmt: skip
    runs = [{**base, "track": 1, "lap_time_mean": 9.0, "best_lap": 9.0},
            {**base, "track": 2, "lap_time_mean": 11.0, "best_lap": 10.0},
            {**base, "track": 3, "lap_time_mean": None, "best_lap": None}]  # fmt: skip
    agg = aggregate(runs)
    assert agg["lap_time_mean"] == {"mean": 10.0, "std": 1.0, "runs": 2}
    assert agg["laps_per_min"] == {"mean": 3.0, "std": 0.0}
    none = aggregate(runs[2:])
    assert none["lap_time_mean"] == {"mean": None, "std": None, "runs": 0}
    table = format_table({"runs": runs[2:], "aggregate": none}, "p")
    assert "| 3.00 ± 0.00 | — | 0.90 ± 0.00 |" in table
    assert table.splitlines()[-1].split()[-2:] == ["—", "0.90"]
