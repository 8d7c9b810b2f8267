"""Shared test setup: deterministic hypothesis runs, so CI never fails on a new random draw;
`--runtime-only`, the suite of the car's runtime without the train extra (Python 3.10 run)."""

import importlib.util
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


@pytest.fixture
def one_thread():
    """One torch intra-op thread for the test: two cores shared with other tests make one
    thread several times faster here (torch imported only by the training tests that ask)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def sim_episodes(tmp_path_factory):
    """A small dataset recorded by the real stack in the simulator, once per test session
    (see e2e_rig.record_sim_dataset). Returns the episodes directory."""
    from e2e_rig import record_sim_dataset

    return record_sim_dataset(tmp_path_factory.mktemp("sim-data"))


# Test modules that need the train extra (torch, training/, export/) or a laptop tool without a
# Python 3.10 build: `make test` runs every test under 3.11, then everything else with
# --runtime-only under 3.10 in a venv without torch.
TRAIN_TEST_MODULES = (
    "test_train_*.py", "test_export.py", "test_research_train_*.py",
    "test_research_redrive.py",  # research.redrive reads training.sim_data's held-out placements
    "test_research_ceiling.py",  # research.ceiling takes the objective weights from training
    "test_docs_*.py",  # the docs' commands include carrt-train's: checked once, under 3.11
    "test_episodes_rerun.py",  # a laptop tool: the Rerun SDK's chunk reader needs Python 3.11+
    "test_episodes_lerobot_reader.py",  # LeRobot's reader (its own 3.11 venv) reads one export
)  # fmt: skip


def pytest_addoption(parser):
    parser.addoption(
        "--runtime-only",
        action="store_true",
        help="leave out the modules that need the train extra; fails if torch is installed",
    )


def pytest_configure(config):
    if config.getoption("--runtime-only") and importlib.util.find_spec("torch") is not None:
        raise pytest.UsageError("--runtime-only is for a venv without torch, and torch is here")


def pytest_ignore_collect(collection_path, config):
    if config.getoption("--runtime-only") and any(
        collection_path.match(pattern) for pattern in TRAIN_TEST_MODULES
    ):
        return True
    return None


# A process that imported torch has crashed AFTER the suite finished, while the interpreter
# shut down: a general protection fault inside libtorch_cpu.so (same offset every time, in about
# one in five runs of the training tests; seen before and after this session's changes; cause
# not found, see docs/architecture.md). Every test had passed and been reported. Such a process
# ends with the suite's own exit status, without running native static destructors.
_exit_status: list[int] = []


def pytest_sessionfinish(session, exitstatus):
    _exit_status.append(int(exitstatus))


def pytest_unconfigure(config):
    import sys

    if _exit_status and "torch" in sys.modules and not hasattr(config, "workerinput"):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(_exit_status[-1])
