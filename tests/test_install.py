"""The car's install, as a user makes it: fresh Python 3.10 venvs (JetPack 6's Python), the plain
`pip install` of a clean copy of this tree, and what it brings, refuses and needs.

Marked `install`: each test builds a venv and installs into it (packages from pip's cache or
the index), so they run once, under the main suite, not again in the 3.10 runtime run.
"""

from __future__ import annotations

import glob
import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import pytest

pytestmark = [pytest.mark.install, pytest.mark.slow, pytest.mark.timeout(600)]

REPO = Path(__file__).resolve().parents[1]
NOT_FOR_THE_CAR = ("torch", "gymnasium", "matplotlib", "onnxruntime", "onnx", "tensorboard")


def python310() -> str:
    found = sorted(glob.glob(os.path.expanduser("~/.pyenv/versions/3.10.*/bin/python3.10")))
    path = found[-1] if found else shutil.which("python3.10")
    if path is None:
        pytest.fail("these tests need a Python 3.10 interpreter (pyenv or python3.10 on PATH)")
    return path


def clean_copy(dest: Path) -> Path:
    """The tree as a clean clone would have it: tracked and new files, nothing git ignores
    (no built library, no venv)."""
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


def run(cmd: list[str], **kwargs) -> subprocess.CompletedProcess:
    kwargs.setdefault("timeout", 300)
    # Never from the checkout: `python -m` would import the tree there, not the install.
    kwargs.setdefault("cwd", Path(tempfile.gettempdir()))
    return subprocess.run(cmd, capture_output=True, text=True, check=False, **kwargs)


def make_venv(path: Path) -> Path:
    done = run([python310(), "-m", "venv", str(path)])
    assert done.returncode == 0, done.stderr
    return path / "bin"


def pip_install(bin_dir: Path, *args: str) -> None:
    done = run([str(bin_dir / "python"), "-m", "pip", "install", "--quiet", *args], timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]


def distributions(bin_dir: Path) -> set[str]:
    done = run([str(bin_dir / "python"), "-m", "pip", "list", "--format=json"])
    return {d["name"].lower() for d in json.loads(done.stdout)}


def site_packages(bin_dir: Path) -> Path:
    return Path(glob.glob(str(bin_dir.parent / "lib" / "python3.*" / "site-packages"))[0])


def tree_listing(root: Path) -> dict[str, tuple[int, int]]:
    return {
        str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
        for p in root.rglob("*")
        if p.is_file() and "__pycache__" not in p.parts
    }


@pytest.fixture(scope="module")
def car_venv(tmp_path_factory) -> Path:
    """A fresh 3.10 venv with the plain install of a clean copy (what goes on the car)."""
    root = tmp_path_factory.mktemp("car")
    source = clean_copy(root / "carrt-src")
    bin_dir = make_venv(root / "venv")
    pip_install(bin_dir, str(source))
    shutil.rmtree(source)  # the installed package must stand on its own
    return bin_dir


def test_plain_install_on_python_310_has_no_torch_simulator_plots_or_wheels(car_venv):
    installed = distributions(car_venv)
    assert "carrt" in installed
    assert not [name for name in installed if name in NOT_FOR_THE_CAR or "opencv" in name]
    version = run([str(car_venv / "carrt"), "--version"])
    assert version.returncode == 0 and version.stdout.startswith("carrt "), version.stderr


def test_config_init_and_check_on_python_310(car_venv, tmp_path):
    config = tmp_path / "car.toml"
    init = run([str(car_venv / "carrt"), "config", "init", "-o", str(config)])
    assert init.returncode == 0, init.stderr
    check = run([str(car_venv / "carrt"), "config", "check", str(config)])
    assert check.returncode == 0, check.stderr
    bad = run([str(car_venv / "carrt"), "config", "check", str(config), "--set", "pwm.max=1"])
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize(
    ("command", "names"),
    [
        (["carrt", "model", "info"], ("onnxruntime", "carrt[laptop]", "onnxruntime-gpu")),
        (["python", "-m", "export", "x.pt", "-o", "x.onnx", "--episodes", "d"], ("carrt[train]",)),
        (["python", "-m", "training.iterate", "--help"], ("carrt[train]",)),
        (["carrt-train", "--help"], ("carrt[train]",)),
        (["carrt-export", "x.pt", "-o", "x.onnx", "--episodes", "d"], ("carrt[train]",)),
    ],
)
def test_a_missing_package_is_one_line_naming_what_to_install(car_venv, tmp_path, command, names):
    done = run([str(car_venv / command[0]), *command[1:]], cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    assert all(name in lines[0] for name in names), lines[0]


def test_virtual_board_and_check_run_without_a_compiler_and_write_nothing(car_venv, tmp_path):
    # Only the venv's own bin directory on PATH: no gcc, no cc, no make.
    env = {"PATH": str(car_venv), "HOME": str(tmp_path), "LANG": "C.UTF-8"}
    assert not any(shutil.which(cc, path=env["PATH"]) for cc in ("gcc", "cc", "clang"))
    packages = site_packages(car_venv)
    before = tree_listing(packages)
    port = tmp_path / "board"
    board = subprocess.Popen(
        [str(car_venv / "python"), "-m", "firmware_bridge.virtual", "--port-path", str(port)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path,
    )  # fmt: skip
    try:
        ready = board.stdout.readline()
        assert "virtual board ready" in ready, ready + board.stderr.read()
        check = run([str(car_venv / "carrt"), "check", "--port", str(port)], env=env, cwd=tmp_path)
        assert check.returncode == 0, check.stdout + check.stderr
        assert "protocol" in check.stdout.lower()
    finally:
        board.terminate()
        board.wait(timeout=10)
    time.sleep(0.1)
    assert tree_listing(packages) == before, "nothing is written into site-packages at run time"


def test_plain_install_beside_onnxruntime_gpu_keeps_nvidias_runtime(tmp_path):
    """NVIDIA's onnxruntime-gpu wheel (here: the index's, standing in for it) installed first;
    the plain install must add no onnxruntime and no OpenCV wheel beside it."""
    bin_dir = make_venv(tmp_path / "venv")
    pip_install(bin_dir, "onnxruntime-gpu")
    before = distributions(bin_dir)
    pip_install(bin_dir, str(clean_copy(tmp_path / "carrt-src")))
    added = distributions(bin_dir) - before
    assert "carrt" in added
    assert not [n for n in added if n.startswith("onnxruntime") or "opencv" in n], added
    providers = run([str(bin_dir / "carrt"), "model", "info"])
    assert providers.returncode == 0, providers.stderr
    assert "CUDAExecutionProvider" in providers.stdout, providers.stdout
