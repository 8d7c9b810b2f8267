"""The gymnasium environment: API conformance, determinism, rewards, termination, truncation."""

from __future__ import annotations

import math
import warnings

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from carrt.sim.env import ENV_ID, CarrtSimEnv
from carrt.sim.track import pose_at


def steer_to_centerline(env: CarrtSimEnv, info: dict, throttle: float) -> np.ndarray:
    """A crude pure pursuit on the centerline, enough to drive laps of the empty layout."""
    car = env.car
    tx, ty, _ = pose_at(env.track, info["s"] + 0.5)
    err = math.atan2(ty - car.y, tx - car.x) - car.yaw
    err = (err + math.pi) % (2 * math.pi) - math.pi
    return np.array([np.clip(-2.0 * err, -1, 1), throttle], np.float32)  # −1 is left


def test_check_env_passes():
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*infinity.*")  # speed is unbounded on purpose
        warnings.filterwarnings("ignore", message=".*alternative render modes.*")  # no spec
        check_env(CarrtSimEnv())
        check_env(gymnasium.make(ENV_ID, render_mode="rgb_array").unwrapped)


def test_observations_stay_in_their_spaces():
    env = CarrtSimEnv(layout="hard", seed=3)
    obs, info = env.reset(seed=0)
    env.action_space.seed(0)
    assert obs in env.observation_space
    assert obs["image"].shape == (96, 96, 3) and obs["image"].dtype == np.uint8
    assert obs["speed"].dtype == np.float32
    assert set(info) >= {"speed", "s", "laps", "collision", "off_track"}
    for _ in range(40):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert obs in env.observation_space and isinstance(reward, float)
        if terminated or truncated:
            obs, info = env.reset()
            assert obs in env.observation_space


def test_reset_is_deterministic_for_a_seed():
    def rollout(env, seed):
        obs, _ = env.reset(seed=seed)
        frames = [obs["image"]]
        for k in range(15):
            obs, *_ = env.step(np.array([0.3 * math.sin(k), 0.6], np.float32))
            frames.append(obs["image"])
        return np.stack(frames), float(obs["speed"][0])

    env = CarrtSimEnv(random_start=True)
    a = rollout(env, 7)
    env.step(env.action_space.sample())
    b = rollout(env, 7)
    assert np.array_equal(a[0], b[0]) and a[1] == b[1]
    assert np.array_equal(a[0], rollout(CarrtSimEnv(random_start=True), 7)[0])
    starts = {CarrtSimEnv(random_start=True).reset(seed=s)[1]["s"] for s in range(4)}
    assert len(starts) > 1  # random_start really draws from the seed


def test_full_throttle_straight_ahead_collides_and_terminates():
    env = CarrtSimEnv(layout="empty")
    env.reset(seed=0)
    for _ in range(200):
        _, reward, terminated, truncated, info = env.step(np.array([0.0, 1.0], np.float32))
        if terminated:
            break
    assert terminated and not truncated
    assert info["collision"] in ("fence", "obstacle")
    assert reward < 0  # the collision penalty outweighs the last step's progress


def test_progress_reward_and_lap_truncation():
    env = CarrtSimEnv(layout="empty", max_laps=1, max_steps=2000)
    obs, info = env.reset(seed=0)
    total, steps = 0.0, 0
    while True:
        obs, reward, terminated, truncated, info = env.step(steer_to_centerline(env, info, 0.5))
        total += reward
        steps += 1
        assert not terminated, info
        if truncated:
            break
    assert info["laps"] == 1
    assert total == pytest.approx(info["progress"]) and total >= env.track.length
    assert obs["speed"][0] > 0.5 and info["speed"] == pytest.approx(float(obs["speed"][0]), 1e-6)


def test_reversing_direction_gives_negative_reward():
    env = CarrtSimEnv(layout="empty")
    env.reset(seed=0, options={"s": 2.0})
    env.car.yaw += math.pi  # facing backwards along the track
    rewards = [env.step(np.array([0.0, 0.4], np.float32))[1] for _ in range(5)]
    assert sum(rewards) < -0.05


def test_max_steps_truncates():
    env = CarrtSimEnv(max_steps=3)
    env.reset(seed=0)
    flags = [env.step(np.array([0.0, 0.0], np.float32))[3] for _ in range(3)]
    assert flags == [False, False, True]


def test_options_switch_layout():
    env = CarrtSimEnv(layout="easy")
    assert len(env.track.obstacles) == 2
    env.reset(seed=0, options={"layout": "hard"})
    assert len(env.track.obstacles) == 8 and env.layout == "hard"
    env.reset(seed=0)
    assert len(env.track.obstacles) == 8  # the switch lasts
    with pytest.raises(ValueError):
        env.reset(options={"layout": "nope"})


def test_gymnasium_make_and_render():
    env = gymnasium.make(ENV_ID, layout="easy", render_mode="rgb_array")
    obs, _ = env.reset(seed=1)
    assert obs["image"].shape == (96, 96, 3)
    obs, *_ = env.step(np.array([0.0, 0.5], np.float32))
    frame = env.render()
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.dtype == np.uint8
    assert env.unwrapped.metadata["render_fps"] == 10.0
    env.close()
    assert CarrtSimEnv().render() is None  # no render_mode, nothing to draw
