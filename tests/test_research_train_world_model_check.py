"""The world-model check (research/world_model_check.py) end to end at tiny sizes: recordings,
a weak policy, its drives, the held-out set, a world model of each form, each scored; run again,
every step is skipped; a bad setting is one line and exit 2."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

pytest.importorskip("torch")

from research import world_model_check as wmc

TINY = ["profile=tiny", "train_tracks=1000", "demo_episodes=2", "weak_frames=10",
        "weak_steps=3", "drive_seconds=4", "world_model_steps=4", "counterfactual_tracks=200",
        "counterfactual_starts=2", "json=", "seeds=0", "ground_steps=3"]  # fmt: skip


def sets(*items: str) -> list[str]:
    return [arg for item in items for arg in ("--set", item)]


def test_the_check_trains_and_scores_every_form_and_resumes(tmp_path, capsys):
    argv = sets(*TINY, f"out={tmp_path}")
    assert wmc.main(argv) == 0
    printed = capsys.readouterr().out
    results = json.loads((tmp_path / "results.json").read_text())
    assert [(r["form"], r["seed"]) for r in results["rows"]] == [
        ("first", 0),
        ("all", 0),
        ("ground", 0),
        ("ground-perfect-map", 0),
    ]
    assert results["targets"] == wmc.TARGETS
    assert results["config"]["world_model_steps"] == 4
    assert results["environment"]["date"] and results["data"]["set"]["starts"] == 2
    for name in ("demos", "drives"):
        assert results["data"][name]["frames"] > 0
    assert set(results["forms"]) == {"first", "all", "ground", "ground-perfect-map"}
    candidates = {f: v for f, v in results["forms"].items() if f != "ground-perfect-map"}
    assert results["passing_forms"] == [f for f, v in candidates.items() if v["passes"]]
    for row in results["rows"]:
        for key in ("steering_sign_agreement", "ordered_right", "collision_auroc",
                    "rank_correlation"):  # fmt: skip
            value = row[key]
            assert value is None or math.isnan(value) or -1.0 <= value <= 1.0
            assert row["meets"][key] is (value is not None and value >= wmc.TARGETS[key])
        assert row["passes"] is all(row["meets"].values())
        assert row["check"]["starts"] == 2 and row["check"]["sequences_per_start"] == 9
    # the forms are different models: the world models' checkpoints say which they are
    from research import ground_model
    from training import checkpoint as ck

    for form in ("first", "all"):
        model, _ = ck.load_world_model(tmp_path / "runs" / f"{form}-seed0" / "world_model.pt")
        assert model.action_inputs == form
    ground = ground_model.load(tmp_path / "runs" / "ground-seed0" / "ground_model.pt")
    assert isinstance(ground, ground_model.GroundWorldModel)
    assert set(results["constant_baselines"]) == {"steering_sign_agreement", "ordered_right"}
    baselines = results["constant_baselines"].values()
    assert all(v is None or 0.5 <= v <= 1.0 for v in baselines)
    table = (tmp_path / "table.md").read_text()
    assert ("The same answer at every start" in table) is (None not in baselines)
    assert "| first | 1 |" in table and "| all | 1 |" in table and "| ground | 1 |" in table
    assert "| ground-perfect-map | 1 |" in table and "ceiling, not a candidate" in table
    assert "| first | 1 |" in printed
    assert (wmc.STOP in table) is (not results["passing_forms"])
    # resumed: every step's marker found, nothing runs again, the same numbers
    assert wmc.main(argv) == 0
    again = json.loads((tmp_path / "results.json").read_text())
    assert [r["collision_auroc"] for r in again["rows"]] == [
        r["collision_auroc"] for r in results["rows"]
    ] or all(math.isnan(r["collision_auroc"]) for r in results["rows"])


def test_a_bad_setting_is_one_line_and_exit_2(tmp_path, capsys):
    assert wmc.main(sets(f"out={tmp_path}", "forms=first,every")) == 2
    err = capsys.readouterr().err.strip()
    assert (
        err
        == "world_model_check: error: forms: ('first', 'every') (each one of first, all, ground)"
    )
    with pytest.raises(SystemExit) as exc:
        wmc.main(sets("world_model_stepz=3"))
    assert exc.value.code == 2 and "did you mean world_model_steps" in capsys.readouterr().err


def test_constant_baselines_score_the_majority_answer():
    """Four starts: steering +0.3 crashes at three, steering −0.3 at one; every other
    alternative is as good as the plan (left out) except full throttle, better at all four."""
    from carrt.sim.counterfactual import SEQUENCE_NAMES

    n, k, h = 4, len(SEQUENCE_NAMES), 10
    col = {name: j for j, name in enumerate(SEQUENCE_NAMES)}
    speed, hit = np.ones((n, k, h), np.float32), np.zeros((n, k, h), np.float32)
    hit[:3, col["steer+0.3"], 2] = 1.0
    hit[3, col["steer-0.3"], 2] = 1.0
    speed[:, col["full"]] = 2.0
    data = {"true_speed": speed, "true_collision": hit, "mask": np.ones((n, k, h), np.float32),
            "meta": {"sequences": list(SEQUENCE_NAMES)}}  # fmt: skip
    base = wmc.constant_baselines(data)
    assert base["steering_sign_agreement"] == 0.75
    # steer-0.3 worse at 1 of 1 decided, steer+0.3 at 3 of 3, lift/brake tie, full better 4 of 4
    assert base["ordered_right"] == pytest.approx(1.0)
