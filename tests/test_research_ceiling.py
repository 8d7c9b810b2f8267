"""research/ceiling.py: model-predictive control with the simulator as a perfect world model.

The search must never touch the world it drives (only clones), the 13 plans are the documented
ones, each objective form ranks hand-built outcomes as its docstring says, and a short run of
the command writes a complete row. The shipped demo policy drives (no torch needed).
"""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest

from carrt.sim.track import pose_at
from carrt.sim.types import CarState
from carrt.sim.world import SimWorld
from research import ceiling
from research.ceiling import CANDIDATES, Outcome, Weights
from research.json_file import read_json

W = Weights()
H = 10


def _world_under_way() -> tuple[SimWorld, float]:
    world = SimWorld(layout="hard", seed=200)
    throttle_now = 0.0
    for _ in range(8):
        throttle_now, *_ = ceiling.drive_period(world, 0.0, 0.6, throttle_now, [])
    return world, throttle_now


def _state(world: SimWorld) -> dict:
    state = {k: v for k, v in vars(world).items() if k != "_locator"}
    state["car"] = copy.copy(vars(world.car))
    state["hint"] = world._locator._hint
    return state


def test_the_search_leaves_the_driven_world_untouched():
    world, throttle_now = _world_under_way()
    before = _state(world)
    mu = np.tile([[0.0, 0.8]], (H, 1)).astype(np.float32)
    plans = ceiling.candidates(mu, H, [-1, -1], [1, 1])
    _, scores = ceiling.choose(world, plans, throttle_now, "survival", W)
    assert _state(world) == before
    assert len(set(np.round(scores, 6))) > 1  # the rollouts really ran, and differ
    # and a rollout really moves its clone: the same world driven gives the same outcome
    twice = [ceiling.rollout(world, plans[0], throttle_now) for _ in range(2)]
    assert twice[0].progress[-1] > 0.5
    np.testing.assert_array_equal(twice[0].progress, twice[1].progress)


def test_thirteen_plans_around_mu_mu_first():
    mu = np.array([[0.1, 0.5], [0.2, 0.6], [0.95, -0.5]], np.float32)
    plans = ceiling.candidates(mu, 5, [-1.0, -1.0], [1.0, 0.9])
    names = [n for n, _, _ in CANDIDATES]
    assert len(CANDIDATES) == 13 == len(set(names)) and plans.shape == (13, 5, 2)
    np.testing.assert_allclose(plans[0, :3], mu)
    np.testing.assert_allclose(plans[0, 3:], mu[[-1, -1]])  # a longer horizon holds the last
    offsets = sorted(d for _, d, k in CANDIDATES if k == 1.0)
    assert offsets == [-0.6, -0.3, -0.15, 0.0, 0.15, 0.3, 0.6]
    combinations = {(d, k) for _, d, k in CANDIDATES if d and k != 1.0}
    assert combinations == {(-0.3, 0.5), (0.3, 0.5), (-0.3, 1.2), (0.3, 1.2)}
    assert sorted(k for _, d, k in CANDIDATES if not d) == [0.5, 1.0, 1.2]
    j = names.index("steer-0.3,throttle*1.2")
    np.testing.assert_allclose(plans[j, 0], [0.1 - 0.3, 0.5 * 1.2])
    np.testing.assert_allclose(plans[names.index("throttle*1.2"), 1], [0.2, 0.6 * 1.2])
    assert plans[names.index("steer+0.6"), 2, 0] == 1.0  # clipped to the bounds
    assert plans[names.index("throttle*1.2"), :, 1].max() <= 0.9


def _outcome(speeds, gains, crash_at=None) -> Outcome:
    speed = np.asarray(speeds, float)
    progress = np.cumsum(gains).astype(float)
    collided = np.zeros(len(speed), bool)
    if crash_at is not None:
        collided[crash_at:] = True
        speed[crash_at:] = 0.0
        progress[crash_at:] = progress[crash_at]
    return Outcome(speed, progress, collided)


@pytest.mark.parametrize("form", ["speed", "progress", "survival"])
def test_a_plan_that_crashes_scores_below_one_that_does_not(form):
    fast_crash = _outcome([2.4] * H, [0.24] * H, crash_at=8)
    slow_safe = _outcome([1.0] * H, [0.1] * H)
    assert ceiling.score(form, fast_crash, W) < ceiling.score(form, slow_safe, W)
    early = _outcome([2.4] * H, [0.24] * H, crash_at=2)
    assert ceiling.score(form, early, W) <= ceiling.score(form, fast_crash, W)


def test_speed_pays_a_fast_loop_across_the_infield_progress_does_not():
    loop = _outcome([2.4] * H, [0.0] * H)  # full speed, no metres along the track
    racing = _outcome([1.8] * H, [0.18] * H)
    assert ceiling.score("speed", loop, W) > ceiling.score("speed", racing, W)
    for form in ("progress", "survival"):
        assert ceiling.score(form, loop, W) < ceiling.score(form, racing, W)


def test_survival_weights_the_first_steps_and_what_lies_beyond():
    early_gain = _outcome([1.5] * H, [0.3] * 5 + [0.0] * 5)
    late_gain = _outcome([1.5] * H, [0.0] * 5 + [0.3] * 5)
    assert ceiling.score("progress", early_gain, W) == ceiling.score("progress", late_gain, W)
    assert ceiling.score("survival", early_gain, W) > ceiling.score("survival", late_gain, W)
    arriving_fast = _outcome([1.0] * 9 + [2.0], [0.1] * H)
    assert ceiling.score("survival", arriving_fast, W) > ceiling.score(
        "survival", _outcome([1.0] * H, [0.1] * H), W
    )


def test_a_tie_keeps_mu():
    world, throttle_now = _world_under_way()
    plans = np.repeat(np.array([[[0.0, 0.5]] * H], np.float32), 13, axis=0)
    best, scores = ceiling.choose(world, plans, throttle_now, "progress", W)
    assert best == 0 and np.all(scores == scores[0])


def test_a_jump_of_the_tracks_projection_earns_nothing():
    """A car that reaches another leg of the track is located there at once: the simulator's
    progress jumps metres, the counted progress does not."""
    world = SimWorld(layout="hard", seed=200)
    world.reset(2.0)
    world.car = CarState(*pose_at(world.track, 7.0), v=1.0)  # as if it had cut across
    before = world.progress
    _, earned = ceiling.hold_counted(world, 0.0, 0.3, 0.3)
    assert world.progress - before > 4.0
    assert 0.0 <= earned < 0.25


def test_a_short_run_writes_a_row_with_every_field(tmp_path, capsys):
    argv = ["--models", "demo", "--forms", "plain,survival", "--tracks", "200", "--seeds", "0",
            "--seconds", "3", "--horizon", "4", "--out", str(tmp_path / "out"),
            "--results", str(tmp_path / "ceiling.json.gz")]  # fmt: skip
    assert ceiling.main(argv) == 0
    row_file = tmp_path / "out" / "demo" / "survival" / "h4-hard200-seed0.json"
    row = json.loads(row_file.read_text())
    fields = {"model", "policy", "policy_sha256", "track", "seed", "form", "horizon", "seconds",
              "completion_ratio", "collisions", "collisions_per_min", "laps", "laps_per_min",
              "lap_time_mean", "progress_per_metre", "average_speed", "distance", "driving_time",
              "off_track_share", "cut_m", "apex_jump_m", "uncut_laps_per_min", "decisions",
              "kept_mu", "mean_abs_dsteering", "throttle_choices", "chosen", "wall_s"}  # fmt: skip
    assert fields <= set(row)
    assert row["decisions"] == 30 and sum(row["chosen"].values()) == 30
    assert math.isclose(sum(row["throttle_choices"].values()), 1.0)
    assert row["distance"] > 1.0 and 0.0 < row["completion_ratio"] < 1.0
    results = read_json(str(tmp_path / "ceiling.json.gz"), "results file")
    assert {(c["model"], c["form"]) for c in results["aggregate"]} == {
        ("demo", "plain"),
        ("demo", "survival"),
    }
    assert results["date"] and results["environment"] and len(results["rows"]) == 2
    plain = next(r for r in results["rows"] if r["form"] == "plain")
    assert plain["decisions"] == 0 and plain["kept_mu"] == 1.0
    # a second call drives nothing: every run is kept
    capsys.readouterr()
    row_file.write_text(json.dumps({**row, "laps": 99}))
    assert ceiling.main(argv) == 0
    out = capsys.readouterr().out
    assert "(0 to drive)" in out and "99 laps" in out


def test_uncut_laps_leave_the_cuts_out():
    row = {"progress_per_metre": 1.0, "distance": 26.0, "cut_m": 0.0, "driving_time": 30.0}
    assert ceiling.uncut_laps_per_min(row, 13.0) == pytest.approx(4.0)
    assert ceiling.uncut_laps_per_min({**row, "cut_m": 13.0}, 13.0) == pytest.approx(2.0)


@pytest.mark.parametrize(
    "extra, says",
    [
        (["--models", "nowhere.onnx"], "nowhere.onnx: no such file"),
        (["--tracks", "150"], "test placements 100-199"),
        (["--tracks", "1x"], "tracks"),
        (["--forms", "speed,fastest"], "--forms"),
        (["--horizon", "0"], "--horizon"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(extra, says, tmp_path, capsys):
    argv = ["--seconds", "1", "--tracks", "200", "--out", str(tmp_path), *extra]
    assert ceiling.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and says in err and err.startswith("ceiling: error:")
    assert not any(tmp_path.iterdir())


def test_bad_model_file_is_one_line(tmp_path, capsys):
    bad = tmp_path / "broken.onnx"
    bad.write_bytes(b"not a model")
    assert ceiling.main(["--models", f"x={bad}", "--tracks", "200", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not a valid ONNX model" in err


def test_true_progress_counts_metres_along_the_track_inside_its_markings():
    """The diagnostic's progress of imagined paths: 1 m straight on from a place on the track
    (which bends: a straight metre earns a little less) earns most of a metre, never more; the
    same metre driven sideways out of the markings earns (almost) nothing."""
    world = SimWorld(layout="hard", seed=200)
    world.reset(2.0)
    ahead = np.stack([np.linspace(0.1, 1.0, 10), np.zeros(10)], axis=1)
    sideways = np.stack([np.zeros(10), np.linspace(0.1, 1.0, 10)], axis=1)
    progress = ceiling.true_progress(world, np.stack([ahead, sideways]))
    assert progress.shape == (2, 10)
    assert 0.7 < progress[0, -1] <= 1.0 and abs(progress[1, -1]) < 0.3
