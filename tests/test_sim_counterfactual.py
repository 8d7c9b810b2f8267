"""carrt.sim.counterfactual: several action sequences replayed from one simulated start state,
the ground truth the world model's imagination is scored against (evaluation only)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from carrt.sim import counterfactual as cf
from carrt.sim.world import SimWorld

DEMO_POLICY = Path(__file__).resolve().parents[1] / "carrt" / "assets" / "demo_policy.onnx"


def test_sequences_are_the_plan_and_its_perturbations_in_the_named_order():
    plan = np.tile(np.array([[0.1, 0.5]], np.float32), (10, 1))
    seqs = cf.sequences(plan, np.random.default_rng(0))
    assert seqs.shape == (len(cf.SEQUENCE_NAMES), 10, 2)
    named = dict(zip(cf.SEQUENCE_NAMES, seqs, strict=True))
    np.testing.assert_array_equal(named["plan"], plan)
    np.testing.assert_allclose(named["steer-0.6"][:, 0], -0.5)
    np.testing.assert_allclose(named["steer+0.6"][:, 0], 0.7)
    assert (named["lift"][:, 1] == 0).all() and (named["full"][:, 1] == 1).all()
    assert (named["brake"][: cf.BRAKE_STEPS, 1] < 0).all() and (named["brake"][3:, 1] == 0).all()
    assert np.ptp(named["random"][:, 0]) == 0 and (named["random"][:, 1] == 0.5).all()


def test_a_replay_is_what_the_simulator_does_and_leaves_the_start_untouched():
    rng = np.random.default_rng(3)
    world = SimWorld(layout="hard", seed=200)
    state = None
    while state is None:
        state = cf.start_state(world, rng)
    world, throttle = state
    before = (world.car, world.time, world.progress)
    straight = np.tile(np.array([[0.0, 1.0]], np.float32), (10, 1))
    one = cf.execute(cf.clone(world), straight, throttle)
    two = cf.execute(cf.clone(world), straight, throttle)
    assert (world.car, world.time, world.progress) == before
    for key in ("speed", "collision", "mask"):
        np.testing.assert_array_equal(one[key], two[key])
    lift = cf.execute(cf.clone(world), np.tile(np.array([[0.0, 0.0]], np.float32), (10, 1)), 0.0)
    steps = int(min(one["mask"].sum(), lift["mask"].sum()))
    assert (one["speed"][:steps] >= lift["speed"][:steps] - 1e-6).all()


def test_steps_after_a_collision_are_masked():
    rng = np.random.default_rng(0)
    world = SimWorld(layout="hard", seed=201)
    crashes = []
    for _ in range(30):  # until a few crashes (each start costs an approach: seconds)
        if len(crashes) >= 4:
            break
        state = cf.start_state(world, rng)
        if state is None:
            continue
        world, throttle = state
        for steering in (-1.0, 1.0):
            seq = np.tile(np.array([[steering, 1.0]], np.float32), (10, 1))
            out = cf.execute(cf.clone(world), seq, throttle)
            if out["collision"].any():
                crashes.append(out)
    assert crashes, "full lock at full throttle towards obstacles never crashed"
    for out in crashes:
        k = int(np.argmax(out["collision"]))
        assert out["collision"].sum() == 1
        assert (out["mask"][: k + 1] == 1).all() and (out["mask"][k + 1 :] == 0).all()


def test_the_command_writes_a_set_from_a_real_onnx_policy(tmp_path, capsys):
    out = tmp_path / "cf.npz"
    argv = ["--model", str(DEMO_POLICY), "--tracks", "200", "--starts", "3", "--out", str(out)]
    assert cf.main(argv) == 0
    with np.load(out) as data:
        meta = json.loads(str(data["meta"]))
        assert data["image"].shape == (3, 96, 96, 3) and data["image"].dtype == np.uint8
        k = len(cf.SEQUENCE_NAMES)
        assert data["actions"].shape[:2] == (3, k) and data["true_speed"].shape[:2] == (3, k)
        assert np.isfinite(data["true_speed"]).all()
    assert meta["tracks"] == [200] and meta["sequences"] == list(cf.SEQUENCE_NAMES)
    assert "3 starts" in capsys.readouterr().out


def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    out = ["--starts", "1", "--out", str(tmp_path / "x.npz")]
    assert cf.main(["--model", str(tmp_path / "none.onnx"), "--tracks", "200", *out]) == 2
    assert cf.main(["--model", str(DEMO_POLICY), "--tracks", "a-b", *out]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith("counterfactual: error:") for line in err)
