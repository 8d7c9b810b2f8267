"""bench/dirl_sim.py's bookkeeping: its settings, the paper-style table and the plot.

The study itself trains for an hour (`make study`); `python -m bench.dirl_sim --quick` runs
every step with the tiny profile in minutes and is how the pipeline was checked end to end.
"""

from __future__ import annotations

import pytest

from bench import dirl_sim


def _row(model, seed, completion, frames=1000, sigma=0.0, iteration=0, lap=None):
    return {
        "model": model, "iteration": iteration, "demo_noise": sigma, "seed": seed,
        "frames": frames, "average_speed": 1.5, "top_speed": 2.0,
        "completion_ratio": completion, "lap_time": lap, "collisions_per_min": 3.0,
    }  # fmt: skip


def test_settings_parse_tuples_and_refuse_unknown_fields():
    cfg = dirl_sim.parse(["--set", "seeds=0,1,2", "--set", "demo_noise=0,0.5", "--set", "jobs=1"])
    assert cfg.seeds == (0, 1, 2) and cfg.demo_noise == (0.0, 0.5) and cfg.jobs == 1
    assert dirl_sim.parse(["--quick"]).profile == "tiny"
    with pytest.raises(SystemExit):
        dirl_sim.parse(["--set", "colour=red"])
    with pytest.raises(SystemExit):
        dirl_sim.parse(["--set", "iterations=many"])


def test_table_averages_over_seeds_per_model_and_noise():
    rows = [
        _row("IL", 0, 0.2), _row("IL", 1, 0.4),
        _row("DIRL iter 1", 0, 0.5, iteration=1, lap=7.0),
        _row("IL", 0, 0.1, sigma=0.5),
    ]  # fmt: skip
    lines = dirl_sim.table(rows).splitlines()
    il = next(line for line in lines if line.startswith("| 0 | IL |"))
    assert "| 2 |" in il and "0.30 ± 0.10" in il
    dirl = next(line for line in lines if "DIRL iter 1" in line)
    assert "| 1 |" in dirl and "| 0.50 |" in dirl and "| 7.00 |" in dirl
    noisy = next(line for line in lines if line.startswith("| 0.5 | IL |"))
    assert "| 0.10 |" in noisy and "| — |" in noisy, "no clean lap: no lap time"


def test_plot_writes_completion_against_frames(tmp_path):
    rows = [_row("IL", 0, 0.2), _row("DIRL iter 1", 0, 0.3, frames=1500, iteration=1),
            _row("DIRL -unc iter 1", 0, 0.1, frames=1500, iteration=1)]  # fmt: skip
    dirl_sim.plot(rows, tmp_path / "c.png")
    assert (tmp_path / "c.png").stat().st_size > 5000


def test_sensitivity_table_lists_each_probed_world_model():
    probed = _row("DIRL iter 1", 0, 0.3, iteration=1)
    probed["sensitivity"] = {
        "speed": [1.86, 1.85, 1.81], "p_collision": [0.05, 0.05, 0.05],
        "uncertainty": [0.53, 0.53, 0.54],
    }  # fmt: skip
    lines = dirl_sim.sensitivity_table([_row("IL", 0, 0.2), probed]).splitlines()
    assert len(lines) == 3, "the IL row has no world model to probe"
    assert "1.860 / 1.850 / 1.810" in lines[2] and "| DIRL iter 1 | 0 |" in lines[2]
