"""`carrt episodes replay`: policies over recorded simulator drives, against the person.

A policy that imitates the scripted expert (the shipped one) must score closer to the person's
actions than a constant one; the actions must be exactly what onnxruntime gives on the same
frames (the car's contract: the plan's first step, clipped to the action bounds); only the
steps the person drove and did not exclude are scored.
"""

from __future__ import annotations

import json

import numpy as np
import onnxruntime as ort
import pytest
from episode_factory import run_cli
from onnx_models import build_policy

from carrt import model_contract as mc
from carrt.episodes import marks, replay
from carrt.episodes.reader import iter_episodes
from carrt.interfaces import Mode
from carrt.policy import OnnxPolicy
from carrt.shipped import resolve_model


@pytest.fixture(scope="module")
def constant(tmp_path_factory):
    return build_policy(tmp_path_factory.mktemp("const") / "const.onnx", steering=0.0,
                        throttle=(0.3, 0.0))  # fmt: skip


def test_a_policy_that_imitates_the_expert_scores_closer_than_a_constant_one(
    sim_episodes, constant
):
    policies = {"demo": OnnxPolicy("demo"), "const": OnnxPolicy(constant)}
    replays = [replay.replay(ep, policies) for ep in iter_episodes(sim_episodes) if ep.n]
    total = replay.overall(replays)
    assert total["demo"]["steps"] == total["const"]["steps"] > 100
    # measured: steering MAE 0.16 against 0.31, on the fixture's noisy expert laps
    assert total["demo"]["steering_mae"] < 0.75 * total["const"]["steering_mae"]
    assert total["demo"]["throttle_mae"] < total["const"]["throttle_mae"]
    assert total["demo"]["steering_within"] > total["const"]["steering_within"]
    scored = np.concatenate([r.scored for r in replays])
    modes = np.concatenate([r.episode.steps["mode"] for r in replays])
    assert (modes[scored] == Mode.MANUAL).all() and (modes == Mode.AUTO).any(), (
        "the crash drives' AUTO steps are replayed but not scored against resting sticks"
    )


def test_the_actions_are_onnxruntimes_on_the_same_frames(sim_episodes):
    ep = next(e for e in iter_episodes(sim_episodes) if e.n > 20)
    got = replay.model_actions(OnnxPolicy("demo"), ep)
    session = ort.InferenceSession(str(resolve_model("demo")), providers=["CPUExecutionProvider"])
    meta = session.get_modelmeta().custom_metadata_map
    low, high = mc.action_bounds(meta)
    for i in range(ep.n):
        mu, _ = session.run(
            [mc.OUTPUT_MU, mc.OUTPUT_SIGMA],
            {mc.INPUT_IMAGE: np.asarray(ep.frames[i])[None],
             mc.INPUT_SPEED: np.array([[ep.steps["speed_mps"][i]]], np.float32)},
        )  # fmt: skip
        np.testing.assert_allclose(got[i], np.clip(mu[0, 0], low, high), atol=1e-6)


def test_excluded_steps_are_not_scored(sim_episodes, constant, tmp_path):
    import shutil

    ep_path = next(e.path for e in iter_episodes(sim_episodes) if (e.steps["mode"] == 1).sum() > 30)
    copy = tmp_path / ep_path.name
    shutil.copytree(ep_path, copy)
    before = replay.replay(next(iter_episodes(copy)), {"c": OnnxPolicy(constant)}).scored.sum()
    marks.change(copy, lambda m: m.exclude.append((0.0, 1.0)))
    after = replay.replay(next(iter_episodes(copy)), {"c": OnnxPolicy(constant)}).scored.sum()
    assert 5 <= before - after <= 11, "the first second (10 steps at 10 Hz) left out"


def test_the_cli_prints_the_table_and_writes_the_numbers_and_the_plot(
    sim_episodes, constant, tmp_path, capsys
):
    out, png = tmp_path / "replay.json", tmp_path / "replay.png"
    argv = ["episodes", "replay", str(sim_episodes), "--model", "demo", "--model", str(constant),
            "--json", str(out), "--plot", str(png)]  # fmt: skip
    assert run_cli(argv) == 0
    printed = capsys.readouterr().out
    assert "demo_policy.onnx" in printed and "const.onnx" in printed and "frames in" in printed
    assert "before the collision" in printed, "the crash drives' collisions are looked at"
    numbers = json.loads(out.read_text())
    assert set(numbers["all"]) == {"demo_policy.onnx", "const.onnx"}
    crash = [e for e in numbers["episodes"] if e["models"]["const.onnx"]["before_collisions"]]
    assert crash, "each collision gets what the policy would have done before it"
    assert png.stat().st_size > 10_000
