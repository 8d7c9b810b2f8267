"""The built wheel holds the product only: research/ (the study), bench/ (the benchmarks) and
tests/ stay in the repository and never reach an install.

Marked `install`: it builds the wheel of a clean copy of the tree (what a clone has), once, in
the install process of `make test`."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

pytestmark = [pytest.mark.install, pytest.mark.slow, pytest.mark.timeout(600)]

REPO = Path(__file__).resolve().parents[1]
NOT_SHIPPED = ("research", "bench", "tests")
SHIPPED = ("carrt", "firmware_bridge", "training", "export")


def clean_copy(dest: Path) -> Path:
    """Tracked and new files, nothing git ignores (no built library, no venv, no run folders)."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=REPO, capture_output=True, check=True,
    ).stdout.decode().split("\0")  # fmt: skip
    for name in filter(None, listed):
        source = REPO / name
        if source.is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, dest / name)
    return dest


@pytest.fixture(scope="module")
def wheel_files(tmp_path_factory) -> list[str]:
    tree = clean_copy(tmp_path_factory.mktemp("tree"))
    out = tmp_path_factory.mktemp("wheel")
    built = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
         "-w", str(out), str(tree)],
        capture_output=True, text=True, timeout=540, cwd=out,
    )  # fmt: skip
    assert built.returncode == 0, built.stderr[-3000:]
    (wheel,) = out.glob("carrt-*.whl")
    with zipfile.ZipFile(wheel) as zf:
        return zf.namelist()


def test_the_wheel_holds_no_research_bench_or_tests(wheel_files):
    tops = {name.split("/", 1)[0] for name in wheel_files}
    assert not tops & set(NOT_SHIPPED), sorted(tops)


def test_the_wheel_holds_the_product(wheel_files):
    """The same listing holds the product's packages, so an empty or foreign wheel fails."""
    tops = {name.split("/", 1)[0] for name in wheel_files}
    assert set(SHIPPED) <= tops, sorted(tops)
    assert "carrt/assets/demo_policy.onnx" in wheel_files
