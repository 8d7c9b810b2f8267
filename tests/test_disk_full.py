"""A full disk is a loud, safe event (issue 60, item 5), on a real 3 MB filesystem: a tmpfs
mounted in a private mount namespace (unshare), so nothing leaks to the machine. Recording
refuses to start below the floor of minutes it has room for; filling up while driving, the
disk-full line comes at once, before the end-of-run summary, the run ends with one line and a
non-zero exit, no traceback, and every episode written verifies."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from carrt.disk_space import check_room, minutes_left, step_bytes
from carrt.errors import UserError

CARRT = [sys.executable, "-m", "carrt"]


def _in_small_filesystem(tmp_path: Path, script: str) -> subprocess.CompletedProcess:
    """Run `script` (sh) with a 3 MB tmpfs at $SMALL, in a mount namespace of its own."""
    if shutil.which("unshare") is None:
        pytest.fail("unshare (util-linux) is needed to mount the test's small filesystem")
    small = tmp_path / "small"
    small.mkdir()
    user = [] if os.geteuid() == 0 else ["-r"]  # a user namespace gives a non-root user a mount
    body = f"mount -t tmpfs -o size=3m tmpfs {small} && SMALL={small} && {script}"
    root = Path(__file__).resolve().parents[1]
    argv = ["unshare", *user, "-m", "sh", "-c", body]
    return subprocess.run(argv, capture_output=True, text=True, timeout=300, cwd=root)


def _carrt(*args: str) -> str:
    return " ".join([*CARRT, *args])


def test_recording_refuses_to_start_without_room_for_the_floor(tmp_path):
    done = _in_small_filesystem(tmp_path, textwrap.dedent(f"""
        {_carrt("teleop", "--sim", "--expert", "auto", "--record", "--out", "$SMALL/rec",
                "--duration", "30")}
        echo "rc=$?"; ls -A $SMALL
    """))  # fmt: skip
    assert "rc=2" in done.stdout and "Traceback" not in done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "room for 0.2 min of recording, under the 1 min floor" in lines[0]
    assert done.stdout.strip().endswith("rc=2"), "nothing was written"


def test_filling_up_while_driving_is_loud_and_every_episode_verifies(tmp_path):
    done = _in_small_filesystem(tmp_path, textwrap.dedent(f"""
        {_carrt("teleop", "--sim", "--expert", "auto", "--record", "--out", "$SMALL/rec",
                "--duration", "120", "--set", "episodes.min_free_minutes=0.1")}
        echo "rc=$?"
        for ep in $SMALL/rec/2*; do {_carrt("episodes", "show", "$ep", "--verify")} \\
            > /dev/null || echo "BAD $ep"; done
        echo "episodes=$(ls -d $SMALL/rec/2* | wc -l)"
    """))  # fmt: skip
    out, err = done.stdout, done.stderr
    assert "rc=2" in out and "BAD" not in out and "episodes=1" in out
    assert "Traceback" not in err
    lines = [line for line in err.replace("\r", "\n").splitlines() if line.strip()]
    loud = [i for i, line in enumerate(lines) if "RECORDING FAILED: disk full" in line]
    assert loud and "stopping the car" in lines[loud[0]]
    assert lines[-1].startswith("carrt teleop: error: recording failed: disk full")
    assert "RECORDING FAILED: disk full" in out  # the summary says it too, after the loud line
    assert out.index("RECORDING FAILED") > out.index("loop:")


def test_room_is_counted_in_minutes_of_recording(tmp_path):
    per_minute = step_bytes() * 10 * 60
    free = shutil.disk_usage(tmp_path).free
    assert minutes_left(tmp_path / "not" / "yet", 10) == pytest.approx(free / per_minute, rel=0.01)
    assert check_room(tmp_path, 10, 0.1).startswith(f"recording into {tmp_path}: room for about")
    with pytest.raises(UserError, match=r"under the 1e\+09 min floor"):
        check_room(tmp_path, 10, 1e9)


def test_every_other_writer_ends_in_one_line_on_a_full_disk(tmp_path):
    """A video of an episode into a filesystem already full: `disk full`, one line, exit 2."""
    episodes = tmp_path / "episodes"
    subprocess.run([*CARRT, "teleop", "--sim", "--expert", "auto", "--record", "--out",
                    str(episodes), "--duration", "3"], check=True, capture_output=True)  # fmt: skip
    done = _in_small_filesystem(tmp_path, textwrap.dedent(f"""
        dd if=/dev/zero of=$SMALL/fill bs=64k count=100 2>/dev/null
        {_carrt("episodes", "video", str(episodes), "-o", "$SMALL/run.mp4")}
        echo "rc=$?"
    """))  # fmt: skip
    assert "rc=2" in done.stdout and "Traceback" not in done.stderr
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("carrt episodes: error: disk full: ")
