"""research/paired_table.py: a check's paired table again from its results file's rows."""

from __future__ import annotations

import json

import pytest

from research import paired_table


def run(track: int, completion: float, collisions: float) -> dict:
    return {"track": track, "completion_ratio": completion, "collisions_per_min": collisions,
            "average_speed": 1.8}  # fmt: skip


def results(tmp_path, rows) -> str:
    path = tmp_path / "results.json"
    path.write_text(json.dumps({"config": {}, "rows": rows}))
    return str(path)


def row(model: str, seed: int, comps: list[float], sigma: float = 0.0) -> dict:
    return {"model": model, "seed": seed, "demo_noise": sigma, "frames": 100,
            "runs": [run(100 + i, c, 1.0) for i, c in enumerate(comps)]}  # fmt: skip


def test_pairs_by_seed_and_placement(tmp_path, capsys):
    rows = [row("IL", 0, [0.5, 0.6]), row("B", 0, [0.7, 0.7]),
            row("IL", 1, [0.5, 0.5]), row("B", 1, [0.6, 0.6])]  # fmt: skip
    assert paired_table.main([results(tmp_path, rows), "--pair", "B:IL"]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    # seed 0: +0.15, seed 1: +0.10 → +0.125 ± 0.025 over seeds
    assert last.startswith("| B | IL | +0.125 ± 0.025 |")


def test_sigma_picks_the_rows(tmp_path, capsys):
    rows = [row("IL", 0, [0.5], 0.0), row("B", 0, [0.9], 0.0),
            row("IL", 0, [0.5], 1.0), row("B", 0, [0.4], 1.0)]  # fmt: skip
    assert paired_table.main([results(tmp_path, rows), "--sigma", "1", "--pair", "B:IL"]) == 0
    assert "| B | IL | -0.100 |" in capsys.readouterr().out  # one seed: no spread


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--pair", "B:X"], "no model 'X' at σ 0"),
        (["--sigma", "0.5", "--pair", "B:IL"], "no rows at σ 0.5"),
        (["--pair", "B"], "'B' is not MODEL:AGAINST"),
    ],
)
def test_bad_input_is_one_line_exit_2(tmp_path, capsys, argv, message):
    path = results(tmp_path, [row("IL", 0, [0.5]), row("B", 0, [0.6])])
    try:
        code = paired_table.main([path, *argv])
    except SystemExit as exc:  # argparse's errors, made one line
        code = exc.code
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0]


def test_not_a_results_file(tmp_path, capsys):
    missing = str(tmp_path / "none.json")
    assert paired_table.main([missing, "--pair", "A:B"]) == 2
    assert "no such results file" in capsys.readouterr().err
    other = tmp_path / "eval.json"
    other.write_text(json.dumps({"aggregate": {}}))
    assert paired_table.main([str(other), "--pair", "A:B"]) == 2
    assert "not a check's results file" in capsys.readouterr().err


def test_racing_columns_where_the_runs_have_them_and_a_dash_where_they_predate_them(
    tmp_path, capsys
):
    def racing(r: dict, laps: list[float]) -> dict:
        for run, value in zip(r["runs"], laps, strict=True):
            run.update(laps_per_min=value, progress_per_metre=0.9)
        return r

    rows = [
        racing(row("IL", 0, [0.5, 0.6]), [4.0, 5.0]),
        racing(row("B", 0, [0.7, 0.7]), [5.0, 5.0]),
        racing(row("IL", 1, [0.5, 0.5]), [4.0, 4.0]),
        racing(row("B", 1, [0.6, 0.6]), [4.0, 5.0]),
    ]
    assert paired_table.main([results(tmp_path, rows), "--pair", "B:IL"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].endswith("| avg m/s | laps / min | progress / m |")
    assert any(x.startswith("| IL | 2 | 100 |") and x.endswith("| 4.25 ± 0.43 | 0.90 ± 0.00 |")
               for x in lines)  # fmt: skip
    # Δ laps / min: seed 0 +0.5, seed 1 +0.5
    assert lines[-1].endswith("| +0.50 ± 0.00 |")
    old = [row("IL", 0, [0.5, 0.6]), row("B", 0, [0.7, 0.7])]
    assert paired_table.main([results(tmp_path, old), "--pair", "B:IL"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[2].endswith("| 1.80 ± 0.00 | — | — |") and lines[-1].endswith("| — |")
