"""The system packages of `make demo` and `make test` (.ci/system-packages), on a machine made bare
for the test: a PATH holding only the shell (and make where make runs), header folders pointed at
empty ones, and fakes at the edge only: `id` saying who runs it, `sudo` with or without a
password, `apt-get` and `apt-cache` that record what they were asked and install nothing.

Why: on a fresh machine `make test` must either install what the tests need or stop, before any
test runs, with one line naming the packages and the command that installs them.
"""

from __future__ import annotations

import glob
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / ".ci" / "system-packages"

# What a bare Debian lacks for `make test`, in the order the script names them (the headers of
# libc and of this interpreter are on the test machine, so they are not among them).
TEST_TOOLS = [
    "xvfb", "xdotool", "chromium", "chromium-driver", "gcc-avr", "avr-libc", "arduino-core-avr",
    "simavr", "libsimavr-dev", "git", "libavcodec59", "libavformat59", "libavutil57", "libswscale6",
    "libswresample4", "libavdevice59", "libavfilter8",
]  # fmt: skip
NO_PY310 = (
    "no Python 3.10 (the car's Python, for make test-py310 and the install tests): install one "
    "(pyenv install 3.10) and pass PYTHON310=/path/to/python3.10 unless it is "
    "~/.pyenv/versions/3.10.* or python3.10 on PATH"
)


def write_tool(folder: Path, name: str, body: str) -> None:
    path = folder / name
    assert not path.exists() and not path.is_symlink(), path  # never write through a link
    path.write_text("#!/bin/sh\n" + body + "\n")
    path.chmod(0o755)


def bare_machine(
    tmp: Path, *, uid: int | None, sudo: str | None, apt: bool, tools=("bash",)
) -> dict:
    """The environment of a machine without the packages: PATH = a folder with `tools` (linked
    to the real ones) and the fakes (`id` saying `uid`, unless None: then the real one); the
    header folders the script checks point into tmp."""
    bin_dir = tmp / "bin"
    bin_dir.mkdir()
    for tool in tools:
        (bin_dir / tool).symlink_to(shutil.which(tool))
    if uid is not None:
        write_tool(bin_dir, "id", f'[ "$1" = -u ] && echo {uid}')
    log = tmp / "calls.log"
    if sudo == "password":
        write_tool(
            bin_dir, "sudo", f'echo "sudo $*" >> {log}; echo "a password is required" >&2; exit 1'
        )
    elif sudo == "passwordless":
        write_tool(
            bin_dir,
            "sudo",
            f'echo "sudo $*" >> {log}; [ "$1" = -n ] && shift; [ "$*" = true ] || exec "$@"',
        )
    if apt:
        write_tool(
            bin_dir, "apt-get", f'echo "apt-get $* DEBIAN_FRONTEND=$DEBIAN_FRONTEND" >> {log}'
        )
    return {
        "PATH": str(bin_dir),
        "HOME": str(tmp),
        "PYTHON": sys.executable,
        "PYTHON310": "python3.10",
        "AVR_LIBC_INCLUDE": str(tmp / "none"),
        "ARDUINO_AVR": str(tmp / "none"),
        "SIMAVR_INCLUDE": str(tmp / "none"),
        "FFMPEG_LIB_DIRS": str(tmp / "none"),
    }


def run_script(profile: str, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(SCRIPT), profile], env=env, capture_output=True, text=True, timeout=60, check=False
    )


def calls(tmp: Path) -> list[str]:
    log = tmp / "calls.log"
    return log.read_text().splitlines() if log.exists() else []


def missing_line(profile: str, packages: list[str], note: str | None = None) -> str:
    names = " ".join(packages)
    line = f"make {profile}: missing system packages {names}: run  sudo apt-get install -y {names}"
    line += "  (or as root)" + (f"; {note}" if note else "")
    return line + f", then make {profile} again\n"


def test_without_root_or_sudo_it_stops_with_one_line_naming_the_packages(tmp_path):
    env = bare_machine(tmp_path, uid=1000, sudo="password", apt=True)
    done = run_script("test", env)
    assert done.returncode == 2
    assert done.stdout == ""
    assert done.stderr == missing_line("test", ["gcc", "make", *TEST_TOOLS], NO_PY310)
    # It asked sudo whether a password is needed, and ran no apt-get.
    assert calls(tmp_path) == ["sudo -n true"]


def test_as_a_real_user_without_root_it_stops_the_same_way():
    """No fake `id`: the real one, as this user, or as nobody (setpriv) when the tests run as
    root; the script and the bare PATH in a folder every user can read."""
    folder = Path(tempfile.mkdtemp())
    try:
        folder.chmod(0o755)
        env = bare_machine(folder, uid=None, sudo=None, apt=True, tools=("bash", "id"))
        shutil.copy2(SCRIPT, folder / "system-packages")
        as_user = (
            []
            if os.geteuid()
            else [shutil.which("setpriv"), "--reuid=65534", "--regid=65534", "--clear-groups"]
        )
        done = subprocess.run(
            [*as_user, str(folder / "system-packages"), "test"],
            env=env, capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
        assert done.returncode == 2
        # (The interpreter may be out of nobody's reach, then the line says so too.)
        names = " ".join(["gcc", "make", *TEST_TOOLS])
        assert done.stderr.startswith(f"make test: missing system packages {names}: run  sudo")
        assert done.stderr.count("\n") == 1
        assert done.stderr.endswith(f"; {NO_PY310}, then make test again\n")
        assert calls(folder) == []
    finally:
        shutil.rmtree(folder)


def test_demo_needs_only_the_compiler_make_and_the_python(tmp_path):
    env = bare_machine(tmp_path, uid=1000, sudo=None, apt=True)
    done = run_script("demo", env)
    assert (done.returncode, done.stderr) == (2, missing_line("demo", ["gcc", "make"]))
    assert calls(tmp_path) == []


def test_as_root_without_apt_get_it_stops_the_same_way(tmp_path):
    env = bare_machine(tmp_path, uid=0, sudo=None, apt=False)
    done = run_script("test", env)
    assert done.returncode == 2
    assert done.stderr == missing_line("test", ["gcc", "make", *TEST_TOOLS], NO_PY310)


def test_as_root_it_installs_exactly_the_missing_packages(tmp_path):
    env = bare_machine(tmp_path, uid=0, sudo=None, apt=True)
    # apt knows python3.10 (Ubuntu 22.04): it is installed with its venv and headers.
    write_tool(tmp_path / "bin", "apt-cache", '[ "$1 $2" = "show python3.10" ]')
    done = run_script("test", env)
    wanted = ["gcc", "make", *TEST_TOOLS, "python3.10", "python3.10-venv", "python3.10-dev"]
    assert calls(tmp_path) == [
        "apt-get update -q DEBIAN_FRONTEND=noninteractive",
        "apt-get install -y -q " + " ".join(wanted) + " DEBIAN_FRONTEND=noninteractive",
    ]
    # The fake installed nothing: checked again afterwards, they are still missing, and it says so.
    assert f"make test: installing system packages {' '.join(wanted)}\n" in done.stderr
    assert done.stderr.endswith(missing_line("test", wanted))
    assert done.returncode == 2


def test_with_passwordless_sudo_it_installs_through_sudo(tmp_path):
    env = bare_machine(tmp_path, uid=1000, sudo="passwordless", apt=True, tools=("bash", "env"))
    run_script("demo", env)
    assert calls(tmp_path) == [
        "sudo -n true",
        "sudo -n env DEBIAN_FRONTEND=noninteractive apt-get update -q",
        "apt-get update -q DEBIAN_FRONTEND=noninteractive",
        "sudo -n env DEBIAN_FRONTEND=noninteractive apt-get install -y -q gcc make",
        "apt-get install -y -q gcc make DEBIAN_FRONTEND=noninteractive",
    ]


def test_with_everything_present_it_checks_quickly_and_installs_nothing(tmp_path):
    fakes = tmp_path / "bin"
    fakes.mkdir()
    for tool in ("apt-get", "apt-cache", "sudo"):
        write_tool(fakes, tool, f'echo "{tool} must not run" >&2; exit 99')
    pyenv310 = sorted(glob.glob(os.path.expanduser("~/.pyenv/versions/3.10.*/bin/python3.10")))
    env = {
        **os.environ,
        "PATH": f"{fakes}:{os.environ['PATH']}",
        "PYTHON": sys.executable,
        "PYTHON310": pyenv310[-1] if pyenv310 else "python3.10",  # the Makefile's choice
    }
    for profile in ("demo", "test"):
        start = time.monotonic()
        done = run_script(profile, env)
        assert (done.returncode, done.stdout, done.stderr) == (0, "", "")
        assert time.monotonic() - start < 3


def test_a_wrong_profile_is_one_line_and_exit_2():
    done = run_script("tests", {"PATH": os.environ["PATH"]})
    assert done.returncode == 2
    assert done.stderr == (
        "usage: .ci/system-packages demo|test (the make target whose system packages to check)\n"
    )


def test_make_stops_at_the_check_before_the_venv_or_any_test(tmp_path):
    """`make test` and `make demo` in a copy of the Makefile on the bare machine: the script's
    line, make's own error line, and the interpreter was only ever asked the script's probe
    (no venv made, no pytest, no demo)."""
    machine = tmp_path / "machine"
    machine.mkdir()
    env = bare_machine(machine, uid=1000, sudo=None, apt=True, tools=("bash", "make"))
    tree = tmp_path / "tree"
    (tree / ".ci").mkdir(parents=True)
    shutil.copy2(REPO / "Makefile", tree / "Makefile")
    shutil.copy2(SCRIPT, tree / ".ci" / "system-packages")
    for name in ("pyproject.toml", "setup.py"):
        (tree / name).write_text("")
    python_log = tmp_path / "python.log"
    python = machine / "bin" / "python-recorded"
    python.write_text(f'#!/bin/sh\necho "$1 $2" >> {python_log}\nexec {sys.executable} "$@"\n')
    python.chmod(0o755)
    for target, packages, note in (
        ("test", ["gcc", *TEST_TOOLS], NO_PY310),
        ("demo", ["gcc"], None),
    ):
        done = subprocess.run(
            ["make", "-s", "-C", str(tree), target, f"PYTHON={python}", "--no-print-directory"],
            env=env, capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
        assert done.returncode == 2
        assert done.stdout == ""
        first, *rest = done.stderr.splitlines(keepends=True)
        assert first == missing_line(target, packages, note)
        assert all(line.startswith("make: ***") for line in rest), rest
        probes = python_log.read_text().splitlines()
        assert probes and all(line == "-I -c" for line in probes), probes
        python_log.unlink()


def test_ci_runs_make_test_and_sets_up_nothing_of_its_own():
    commands = [
        line.strip()
        for line in (REPO / ".ci" / "run").read_text().splitlines()
        if line.strip() and not line.lstrip().startswith("#")
    ]
    assert commands == ["set -euo pipefail", 'cd "$(dirname "$0")/.."', "exec make test"]
