"""bench/provenance.py: every study's and benchmark's results file names what computed it (the
date, the machine, carrt's code version, the libraries' versions), so two runs of the same
design can be told apart by more than their dates."""

from __future__ import annotations

import json
from importlib import metadata

import numpy as np

from bench import check_steps, provenance
from bench.takeover_check import TakeoverConfig
from carrt.version import code_version


def test_the_environment_names_the_code_and_the_installed_libraries():
    env = provenance.environment()
    assert env["code_version"] == code_version() and env["cpus"] >= 1
    assert env["packages"]["numpy"] == np.__version__
    assert env["packages"]["numpy"] == metadata.version("numpy")
    assert set(env["packages"]) <= set(provenance.PACKAGES)
    assert "not-a-package" not in provenance.package_versions()
    assert env["date"].endswith("+00:00"), "UTC"


def test_a_checks_results_file_carries_its_environment(tmp_path):
    cfg = TakeoverConfig(out=str(tmp_path))
    check_steps.write_results(cfg, [], 0.0, "-x", lambda rows: [])
    written = json.loads((tmp_path / "results-x.json").read_text())
    assert written["environment"]["code_version"] == code_version()
    assert written["environment"]["packages"]["numpy"] == np.__version__
