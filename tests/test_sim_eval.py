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
