"""research/robustness.py: the paper's robustness claim from two results files, seed by seed."""

from __future__ import annotations

import json

import pytest

from research import robustness


def _row(model: str, sigma: float, seed: int, completion: float, collisions: float) -> dict:
    aggregate = {"completion_ratio": {"mean": completion, "std": 0.1},
                 "collisions_per_min": {"mean": collisions, "std": 1.0}}  # fmt: skip
    return {"model": model, "demo_noise": sigma, "seed": seed, "aggregate": aggregate}


def _write(path, rows, tracks="100-199"):
    path.write_text(json.dumps({"config": {"eval_tracks": tracks}, "rows": rows}))
    return str(path)


def test_each_methods_loss_is_its_own_sigma_0_against_sigma_and_dirl_is_paired_with_il(
    tmp_path, capsys
):
    clean = _write(tmp_path / "clean.json", [
        _row("IL", 0.0, 0, 0.70, 5.0), _row("takeovers2", 0.0, 0, 0.80, 4.0),
        _row("IL", 0.0, 1, 0.74, 4.0), _row("takeovers2", 0.0, 1, 0.82, 3.5),
        _row("IL", 0.0, 4, 0.90, 1.0),  # a seed the noisy file lacks: left out
        _row("IL", 0.5, 0, 0.10, 9.0),  # another σ: ignored
    ])  # fmt: skip
    noisy = _write(tmp_path / "noisy.json", [
        _row("IL", 1.0, 0, 0.50, 8.0), _row("takeovers2", 1.0, 0, 0.75, 5.0),
        _row("IL", 1.0, 1, 0.60, 6.0), _row("takeovers2", 1.0, 1, 0.80, 4.5),
    ])  # fmt: skip
    out = tmp_path / "r.json"
    assert robustness.main(["--clean", clean, "--noisy", noisy, "--json", str(out)]) == 0
    result = json.loads(out.read_text())["result"]
    il = result["models"]["IL"]["completion_ratio"]
    assert il["seeds"] == [0, 1] and il["loss"] == pytest.approx([0.20, 0.14])
    dirl = result["models"]["takeovers2"]["collisions_per_min"]
    assert dirl["loss"] == pytest.approx([1.0, 1.0]), "collisions: a rise is a loss"
    against = result["against_il"]["takeovers2"]
    assert against["completion_ratio"]["difference"] == pytest.approx([0.05 - 0.20, 0.02 - 0.14])
    assert against["collisions_per_min"]["difference"] == pytest.approx([1.0 - 3.0, 1.0 - 2.0])
    text = capsys.readouterr().out
    assert "| takeovers2 | -0.135 ± 0.015 | -0.15, -0.12 |" in text


@pytest.mark.parametrize("case, says", [
    ("missing", "no such results file"), ("garbage", "not a results file"),
    ("other placements", "different placements"), ("no dirl", "no seed has takeovers2"),
    ("no aggregate", "lacks its completion_ratio"),
])  # fmt: skip
def test_bad_files_end_in_one_line_and_exit_2(tmp_path, capsys, case, says):
    good = [_row("IL", 0.0, 0, 0.7, 5.0), _row("takeovers2", 0.0, 0, 0.8, 4.0),
            _row("IL", 1.0, 0, 0.5, 8.0), _row("takeovers2", 1.0, 0, 0.7, 5.0)]  # fmt: skip
    clean = _write(tmp_path / "clean.json", good)
    noisy = {
        "missing": str(tmp_path / "none.json"),
        "garbage": str(tmp_path / "g.json"),
        "other placements": _write(tmp_path / "o.json", good, tracks="100-149"),
        "no dirl": _write(tmp_path / "d.json", good[:3]),
        "no aggregate": _write(
            tmp_path / "a.json", [*good, {"model": "IL", "demo_noise": 1.0, "seed": 3}]
        ),
    }[case]
    (tmp_path / "g.json").write_text("{not json")
    assert robustness.main(["--clean", clean, "--noisy", noisy]) == 2
    err = capsys.readouterr().err.strip()
    assert says in err and len(err.splitlines()) == 1, err


def test_a_sigma_that_is_not_finite_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        robustness.main(["--clean", "a", "--noisy", "b", "--sigma", "nan"])
    assert exit_.value.code == 2
