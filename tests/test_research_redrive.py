"""research/redrive.py: a finished study's rows driven again on other held-out placements.

Real `carrt eval` subprocesses drive tiny contract-valid ONNX policies (tests/onnx_models.py)
on one held-out placement for two simulated seconds.
"""

from __future__ import annotations

import json
import shutil

import pytest

from research import redrive
from tests.onnx_models import build_policy


def _row(model, seed, run, **extra):
    return {"model": model, "iteration": 1, "demo_noise": 0.0, "seed": seed, "frames": 100,
            "run": str(run), "aggregate": {}, "runs": [{"completion_ratio": 9.0}],
            "counterfactual": None, "chosen": None, **extra}  # fmt: skip


def test_each_row_finds_the_policy_the_study_drove(tmp_path):
    run = tmp_path / "dirl1"
    (run / "selected" / "candidates").mkdir(parents=True)
    assert redrive.policy_of(_row("IL", 0, run)) == run / "policy.onnx"
    (run / "selected" / "policy.onnx").write_bytes(b"x")
    assert redrive.policy_of(_row("DIRL iter 1", 0, run)) == run / "selected" / "policy.onnx"
    before = redrive.policy_of(_row("DIRL iter 1 before refinement", 0, run))
    assert before == run / "selected" / "candidates" / "imitated.onnx"
    named = _row("DIRL iter 1", 0, run, policy=str(tmp_path / "p.onnx"))
    assert redrive.policy_of(named) == tmp_path / "p.onnx"


@pytest.mark.parametrize(
    "argv, says",
    [
        (["--tracks", "1000-1010"], "not held out for evaluation"),
        (["--tracks", "199-200"], "[200]"),
        (["--models", "DIRL iter 7"], "no rows named"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, argv, says):
    run = tmp_path / "il"
    run.mkdir()
    build_policy(run / "policy.onnx")
    results = tmp_path / "results.json"
    results.write_text(json.dumps({"rows": [_row("IL", 0, run)]}))
    assert redrive.main([str(results), "--out", str(tmp_path / "o"), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert says in err and "\n" not in err and "Traceback" not in err


def test_a_file_that_is_not_a_study_is_one_line_and_exit_2(tmp_path, capsys):
    bad = tmp_path / "results.json"
    bad.write_text("[1, 2")
    assert redrive.main([str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert "not a study's results.json" in err and "\n" not in err


def test_rows_are_driven_once_per_distinct_policy_and_tabled_with_the_new_laps(tmp_path, capsys):
    """Two seeds' IL and DIRL rows with the same seed's IL bytes: two policies are driven, each
    copy's row gets its original's laps, the old laps are replaced, a second run drives none."""
    runs = {name: tmp_path / name for name in ("il0", "il1", "dirl0", "dirl1")}
    for path in runs.values():
        path.mkdir()
    build_policy(runs["il0"] / "policy.onnx", steering=0.0)
    build_policy(runs["il1"] / "policy.onnx", steering=2.0)
    shutil.copy(runs["il0"] / "policy.onnx", runs["dirl0"] / "policy.onnx")
    shutil.copy(runs["il1"] / "policy.onnx", runs["dirl1"] / "policy.onnx")
    rows = [_row("IL", s, runs[f"il{s}"]) for s in (0, 1)]
    rows += [_row("DIRL iter 1", s, runs[f"dirl{s}"]) for s in (0, 1)]
    results = tmp_path / "results.json"
    results.write_text(json.dumps({"config": {"eval_tracks": "100-124"}, "rows": rows}))
    out = tmp_path / "wide"
    argv = [str(results), "--out", str(out), "--tracks", "150", "--seconds", "2", "--jobs", "1"]
    assert redrive.main(argv) == 0
    assert "2 distinct policies (2 to drive)" in capsys.readouterr().out
    assert len(list((out / "evals").glob("*.json"))) == 2
    written = json.loads((out / "results.json").read_text())
    assert written["redriven"]["tracks"] == "150" and written["config"]["eval_tracks"] == "100-124"
    new = {(r["model"], r["seed"]): r for r in written["rows"]}
    for key, row in new.items():
        assert [run["track"] for run in row["runs"]] == [150], key
        # the 2 s less the pilot's arming (the trajectory starts at the first driving tick)
        assert 0.8 < row["runs"][0]["simulated_s"] <= 2.0
    assert new[("DIRL iter 1", 0)]["runs"] == new[("IL", 0)]["runs"]
    table = (out / "table.md").read_text()
    assert "| 0 | DIRL iter 1 | IL | 2 | +0.00, +0.00 |" in table  # identical bytes, identical laps
    assert redrive.main(argv) == 0
    assert "(0 to drive)" in capsys.readouterr().out
