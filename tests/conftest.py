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
    """A small dataset recorded by the real stack in the simulator, once per test session
    (see e2e_rig.record_sim_dataset). Returns the episodes directory."""
    from e2e_rig import record_sim_dataset

    return record_sim_dataset(tmp_path_factory.mktemp("sim-data"))
