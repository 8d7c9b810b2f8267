"""research/paths.py and the entry points run from anywhere: a study's relative OUT is the
repository's whatever the current directory, and `python /path/research/x.py` or
`python /path/bench/__main__.py` import from any directory."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from research import dirl_sim, refine_loop, takeover_check, world_model_swap
from research.paths import ROOT, at_root, outs_at_root

REPO = Path(__file__).resolve().parents[1]


def test_root_is_the_repository():
    assert ROOT == REPO


def test_relative_out_is_the_repositorys_and_absolute_stays(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert takeover_check.parse(["--set", "out=research/runs/x"]).out == str(
        REPO / "research/runs/x"
    )
    assert takeover_check.parse(["--set", f"out={tmp_path}"]).out == str(tmp_path)
    assert at_root("") == ""


def test_defaults_write_under_research_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    runs = REPO / "research" / "runs"
    cfg = takeover_check.parse([])
    assert Path(cfg.out).parent == runs and Path(cfg.study.out).parent == runs
    assert Path(refine_loop.parse([]).out).parent == runs
    assert Path(dirl_sim.parse([]).out).parent == runs


def test_swap_reads_its_checks_at_the_repository():
    """`policy_out` and `world_out` name the checks a swap reads back: the repository's too."""
    cfg = world_model_swap.SwapConfig(policy_out="research/runs/a", world_out="/abs/b")
    moved = outs_at_root(cfg)
    assert moved.policy_out == str(REPO / "research/runs/a") and moved.world_out == "/abs/b"


def test_entry_points_run_as_files_from_another_directory(tmp_path):
    py = sys.executable
    out = subprocess.run([py, str(REPO / "research" / "takeover_check.py"), "--help"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=60)  # fmt: skip
    assert out.returncode == 0 and "--set FIELD=VALUE" in out.stdout, out.stderr
    out = subprocess.run([py, str(REPO / "bench" / "__main__.py"), "no_such_bench"],
                         cwd=tmp_path, capture_output=True, text=True, timeout=60)  # fmt: skip
    assert out.returncode == 2
    (line,) = out.stderr.strip().splitlines()  # one line, no traceback
    assert "no benchmark 'no_such_bench'" in line
