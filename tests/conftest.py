"""Shared test setup: deterministic hypothesis runs, so CI never fails on a new random draw."""

import os

from hypothesis import HealthCheck, settings

settings.register_profile(
    "ci",
    derandomize=True,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
    print_blob=True,
)
settings.register_profile("explore", deadline=None, max_examples=2000)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


import pytest  # noqa: E402


@pytest.fixture(scope="session")
def sim_episodes(tmp_path_factory):
    """A small dataset recorded by the real stack in the simulator, once per test session.

    Expert laps with the paper's noise (collision-free), plus episodes in which a policy that
    steers wrongly crashes into the fence (collision labels), on the simulated clock: a few
    seconds of wall time. Returns the episodes directory.
    """
    from e2e_rig import CliRun
    from onnx_models import build_policy

    root = tmp_path_factory.mktemp("sim-data")
    out = root / "episodes"
    expert = ["teleop", "--sim", "--expert", "auto", "--record", "--layout", "easy",
              "--episodes", "3", "--laps", "1", "--out", str(out), "--duration", "600"]  # fmt: skip
    assert CliRun(expert).result(timeout_s=300) == 0
    crash = build_policy(root / "crash.onnx", steering=0.0, throttle=(0.8, 0.0))
    crashes = ["drive", "--sim", "--autopilot", "--model", str(crash), "--record", "--layout",
               "easy", "--episodes", "3", "--out", str(out), "--duration", "600"]  # fmt: skip
    assert CliRun(crashes).result(timeout_s=300) == 0
    return out
