"""research/paired_eval.py: two `carrt eval --json` files compared run by run (placement, seed)."""

from __future__ import annotations

import json

import pytest

from research import paired_eval


def _run(track: int, seed: int, completion: float, collisions: float, speed: float = 1.8) -> dict:
    return {"track": track, "seed": seed, "completion_ratio": completion,
            "collisions_per_min": collisions, "average_speed": speed}  # fmt: skip


def _write(path, runs, seconds=60.0):
    config = {"layout": "hard", "seconds": seconds, "tracks": sorted({r["track"] for r in runs})}
    path.write_text(json.dumps({"config": config, "runs": runs, "aggregate": {}}))
    return str(path)


def test_deltas_are_paired_by_placement_and_seed_not_by_order(tmp_path, capsys):
    a = _write(tmp_path / "a.json", [_run(200, 0, 0.9, 2.0), _run(201, 0, 0.5, 6.0),
                                     _run(200, 1, 0.8, 3.0), _run(201, 1, 0.6, 5.0)])  # fmt: skip
    # B in another order: pairing by position would compare 201 with 200
    b = _write(tmp_path / "b.json", [_run(201, 1, 0.6, 4.0), _run(200, 1, 0.9, 2.0),
                                     _run(201, 0, 0.5, 6.0), _run(200, 0, 1.0, 1.0)])  # fmt: skip
    out = tmp_path / "d.json"
    assert paired_eval.main([a, b, "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    c = result["completion_ratio"]
    assert c["delta"] == pytest.approx((0.1 + 0.0 + 0.1 + 0.0) / 4)
    assert c["per_seed"] == {"0": pytest.approx(0.05), "1": pytest.approx(0.05)}
    assert (c["better"], c["worse"]) == (2, 0)
    coll = result["collisions_per_min"]
    assert coll["delta"] == pytest.approx(-0.75) and (coll["better"], coll["worse"]) == (3, 0)
    assert c["se"] == pytest.approx(0.05 / 4**0.5 * (4 / 3) ** 0.5)  # sample std / sqrt(n)
    assert "completion_ratio: 0.700 -> 0.750, delta +0.050" in capsys.readouterr().out


@pytest.mark.parametrize("case, says", [
    ("missing", "no such carrt eval file"), ("garbage", "not a carrt eval file"),
    ("other runs", "different runs"), ("other seconds", "differ in seconds"),
    ("nan", "without finite"),
])  # fmt: skip
def test_bad_files_end_in_one_line_and_exit_2(tmp_path, capsys, case, says):
    good = [_run(200, 0, 0.9, 2.0), _run(201, 0, 0.5, 6.0)]
    a = _write(tmp_path / "a.json", good)
    b = {
        "missing": str(tmp_path / "none.json"),
        "garbage": str(tmp_path / "g.json"),
        "other runs": _write(tmp_path / "b1.json", [_run(200, 0, 0.9, 2.0)]),
        "other seconds": _write(tmp_path / "b2.json", good, seconds=30.0),
        "nan": _write(tmp_path / "b3.json", [_run(200, 0, float("nan"), 2.0), good[1]]),
    }[case]
    (tmp_path / "g.json").write_text("{not json")
    assert paired_eval.main([a, b]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0]


def test_racing_numbers_are_paired_where_both_files_have_them(tmp_path, capsys):
    def racing(run, laps, progress):
        return {**run, "laps_per_min": laps, "progress_per_metre": progress}

    a_runs = [racing(_run(200, 0, 0.9, 2.0), 5.0, 0.9), racing(_run(201, 0, 0.5, 6.0), 3.0, 0.7)]
    b_runs = [racing(_run(200, 0, 0.9, 2.0), 5.5, 0.95), racing(_run(201, 0, 0.5, 6.0), 2.0, 0.6)]
    out = tmp_path / "d.json"
    a, b = _write(tmp_path / "a.json", a_runs), _write(tmp_path / "b.json", b_runs)
    assert paired_eval.main([a, b, "--json", str(out)]) == 0
    laps = json.loads(out.read_text())["laps_per_min"]
    assert laps["delta"] == pytest.approx(-0.25) and (laps["better"], laps["worse"]) == (1, 1)
    assert "laps_per_min: 4.000 -> 3.750, delta -0.250" in capsys.readouterr().out
    # A written before carrt eval recorded them: the three old metrics as before, racing "—"
    old = _write(tmp_path / "old.json", [_run(200, 0, 0.9, 2.0), _run(201, 0, 0.5, 6.0)])
    assert paired_eval.main([old, b, "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "laps_per_min: — (not in both files)" in text
    assert "progress_per_metre: — (not in both files)" in text
    assert "completion_ratio: 0.700 -> 0.700" in text
    assert "laps_per_min" not in json.loads(out.read_text())
