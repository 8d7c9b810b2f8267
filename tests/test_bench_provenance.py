"""bench/provenance.py: every study's and benchmark's results file names what computed it (the
date, the machine, carrt's code version, the libraries' versions), so two runs of the same
design can be told apart by more than their dates."""

from __future__ import annotations

import json
from importlib import metadata

import numpy as np

from bench import provenance
from carrt.version import code_version
from research import check_steps
from research.takeover_config import TakeoverConfig


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


def test_the_cpu_is_named_with_the_simd_paths_the_libraries_choose_by(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text(
        "processor\t: 0\nmodel name\t: AMD EPYC 9654\nflags\t\t: fpu sse4_2 avx avx2 fma\n\n"
        "processor\t: 1\nmodel name\t: AMD EPYC 9654\nflags\t\t: fpu sse4_2 avx avx2 fma\n"
    )
    assert provenance.cpu(str(info)) == {
        "model": "AMD EPYC 9654",
        "simd": ["sse4_2", "avx", "avx2", "fma"],
    }
    assert provenance.cpu(str(tmp_path / "missing")) == {}
    assert "cpu" in provenance.environment()


def test_results_count_the_steps_the_recorder_dropped(tmp_path):
    """A study's data is the same from run to run only while nothing is dropped: its results file
    says how many were."""
    for name, counts in (("a/ep1", {"steps": 30, "dropped": 0}), ("b/ep2", {"steps": 8,
                         "dropped": 2}), ("b/ep3", None)):  # fmt: skip
        (tmp_path / "data" / name).mkdir(parents=True)
        (tmp_path / "data" / name / "meta.json").write_text(json.dumps({"counts": counts}))
    assert provenance.recorded(tmp_path / "data") == {"episodes": 3, "frames": 38, "dropped": 2}
    cfg = TakeoverConfig(out=str(tmp_path))
    check_steps.write_results(cfg, [], 0.0, "-x", lambda rows: [])
    written = json.loads((tmp_path / "results-x.json").read_text())
    assert written["recorded"] == {"episodes": 3, "frames": 38, "dropped": 2}
