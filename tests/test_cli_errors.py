"""Bad input: one line and exit code 2. A killed `carrt` loses nothing but its last second."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from e2e_rig import PAD_SETTINGS, write_video
from onnx_models import build_policy

from carrt.episodes.reader import list_episodes, read_episode
from firmware_bridge import messages as m
from firmware_bridge.virtual import VirtualBoard

TESTS = Path(__file__).parent
ENV = {**os.environ, "SDL_VIDEODRIVER": "dummy", "SDL_AUDIODRIVER": "dummy"}


def carrt(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "carrt", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=60,
        env=ENV,
        cwd=cwd,
    )


def assert_one_line_error(result, *needles):
    assert result.returncode == 2, result.stdout + result.stderr
    assert result.stderr.count("\n") == 1, result.stderr
    assert "Traceback" not in result.stderr
    for needle in needles:
        assert needle in result.stderr, result.stderr


@pytest.mark.parametrize(
    ("variant", "needle"),
    [
        ({"image_shape": (None, 64, 64, 3)}, "image"),
        ({"drop_metadata": ("carrt.horizon",)}, "carrt.horizon"),
        ({"metadata_overrides": {"carrt.schema": "other/9"}}, "carrt.schema"),
        ({"corrupt": True}, "not a valid ONNX model"),
    ],
)
def test_a_wrong_model_is_refused_before_anything_starts(tmp_path, variant, needle):
    model = build_policy(tmp_path / "bad.onnx", **variant)
    result = carrt("drive", "--model", model, "--port", "/dev/null/none")
    assert_one_line_error(result, needle)


def test_missing_model_file(tmp_path):
    assert_one_line_error(carrt("drive", "--model", tmp_path / "nope.onnx"), "nope.onnx")


def test_bad_config(tmp_path):
    config = tmp_path / "car.toml"
    config.write_text("[camera]\ncrop_top = 2.0\n")
    assert_one_line_error(carrt("teleop", "--config", config), "camera.crop_top")


def test_missing_camera_and_missing_port(tmp_path):
    assert_one_line_error(carrt("teleop", "--camera", tmp_path / "none.avi"), "none.avi")
    video = write_video(tmp_path / "cam.avi", seconds=1.0)
    result = carrt("teleop", "--camera", video, "--port", tmp_path / "ttyUSB7")
    assert_one_line_error(result, "ttyUSB7", "does not exist")


def test_empty_or_wrong_episode_directory(tmp_path):
    (tmp_path / "empty").mkdir()
    assert_one_line_error(carrt("episodes", "ls", tmp_path / "empty"), "no episodes")
    assert_one_line_error(carrt("report", tmp_path / "empty"), "no episodes")
    assert_one_line_error(carrt("episodes", "show", tmp_path / "empty"), "empty")


CHILD = """
import sys, threading, time
sys.path.insert(0, {tests!r})
from e2e_rig import SyntheticPad
from carrt.cli import main

def drive_the_pad():
    pad = SyntheticPad()
    pad.wait_ready()
    pad.connect_neutral()
    time.sleep(0.3)
    for lap in range(100):
        pad.press("arm")          # arm: an episode starts
        time.sleep(0.1)
        pad.sticks(0.2, 0.3)
        time.sleep(1.5 if lap == 0 else 30)
        pad.sticks(0.0, 0.0)
        time.sleep(0.3)
        pad.press("arm")          # disarm: the episode ends
        time.sleep(1.0)           # wheels still before the next arm
        print("episode", lap, "done", flush=True)

threading.Thread(target=drive_the_pad, daemon=True).start()
sys.exit(main({argv!r}))
"""


@pytest.mark.realtime  # a pad pressed in real time must be seen by the 10 Hz loop
def test_killed_mid_recording_keeps_earlier_episodes_and_the_current_one(tmp_path):
    video = write_video(tmp_path / "cam.avi")
    out = tmp_path / "episodes"
    with VirtualBoard() as board:
        argv = [
            "teleop", "--record", "--port", board.port, "--camera", str(video), "--out", str(out),
            "--set", "camera.loop_video=true", "--set", "pwm.max_forward=1.0",
            *(x for s in PAD_SETTINGS for x in ("--set", s)),
        ]  # fmt: skip
        child = subprocess.Popen(
            [sys.executable, "-c", CHILD.format(tests=str(TESTS), argv=argv)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=ENV,
        )
        try:
            lines = iter(child.stdout.readline, "")
            assert any(line.startswith("episode 0 done") for line in lines), child.stderr.read()
            first = list_episodes(out)[0]
            snapshot = {p.name: p.read_bytes() for p in first.iterdir()}
            time.sleep(3.0)  # the second episode records for a while
            assert board.state == m.State.ARMED
            child.send_signal(signal.SIGKILL)
            child.wait()
            killed = time.monotonic()
            while board.state != m.State.FAILSAFE and time.monotonic() - killed < 1:
                time.sleep(0.002)
            assert board.state == m.State.FAILSAFE and board.throttle_us == 1500
        finally:
            child.kill()
            child.wait()

    paths = list_episodes(out)
    assert len(paths) == 2
    assert {p.name: p.read_bytes() for p in paths[0].iterdir()} == snapshot
    earlier, current = read_episode(paths[0]), read_episode(paths[1])
    assert earlier.meta.get("end_reason") == "disarmed"
    assert current.n >= 15, "at least the part more than a second old survives"
    assert current.duration_s >= 1.5


def test_a_directory_where_a_file_belongs_is_named_as_such(tmp_path):
    assert_one_line_error(carrt("config", "check", tmp_path), "is a directory")
    assert_one_line_error(carrt("drive", "--model", tmp_path), "is a directory")
    assert_one_line_error(carrt("eval", "--model", tmp_path), "is a directory")


def test_episodes_ls_prints_nothing_before_its_error(tmp_path):
    from episode_factory import make_step, write_episode

    steps = [make_step(i) for i in range(5)]
    write_episode(tmp_path / "eps", steps)
    time.sleep(1.1)  # episode names carry the second they began
    bad = write_episode(tmp_path / "eps", steps)
    (bad / "meta.json").write_text("{ not json")
    result = carrt("episodes", "ls", tmp_path / "eps")
    assert_one_line_error(result, bad.name)
    assert result.stdout == "", "no header or rows before the error"


@pytest.mark.parametrize("command", ["report", "episodes show", "episodes ls"])
def test_a_reader_that_stops_early_gets_no_traceback(tmp_path, command):
    """`carrt report DIR | head -1`: the pipe closes before carrt has printed."""
    from episode_factory import make_step, write_episode

    episode = write_episode(tmp_path / "eps", [make_step(i) for i in range(20)])
    target = episode if command == "episodes show" else tmp_path / "eps"
    proc = subprocess.Popen(
        [sys.executable, "-m", "carrt", *command.split(), str(target)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=ENV,
    )  # fmt: skip
    proc.stdout.close()  # like `head` exiting before the first line arrives
    err = proc.stderr.read().decode()
    code = proc.wait(timeout=60)
    assert "Traceback" not in err and "BrokenPipeError" not in err, err
    assert code == 141, (code, err)


def test_every_subcommand_has_a_description_an_example_and_helped_options():
    import argparse

    from carrt.cli import build_parser

    def walk(parser, path):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    yield " ".join([*path, name]), sub
                    yield from walk(sub, [*path, name])

    seen = 0
    for name, sub in walk(build_parser(), []):
        seen += 1
        assert sub.description, f"carrt {name}: no description"
        assert sub.epilog and "carrt " in sub.epilog, f"carrt {name}: no example"
        for action in sub._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            assert action.help, f"carrt {name} {action.option_strings or action.dest}: no help"
    assert seen >= 15


def test_quiet_keeps_the_results_and_drops_the_chatter():
    loud = carrt("drive", "--sim", "--autopilot", "--model", "demo", "--duration", "2")
    quiet = carrt("-q", "drive", "--sim", "--autopilot", "--model", "demo", "--duration", "2")
    assert loud.returncode == quiet.returncode == 0, quiet.stderr
    assert "mode MANUAL" in loud.stdout and "mode MANUAL" not in quiet.stdout
    assert "completion ratio" in quiet.stdout, "the run's results still print"


def test_ctrl_c_ends_a_drive_cleanly_with_exit_130(tmp_path):
    """Like every other command stopped by Ctrl-C (iterate.py included): 130, and the run still
    ends through its normal shutdown (summary printed, episodes closed)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "carrt", "drive", "--sim", "--autopilot", "--model", "demo",
         "--record", "--out", str(tmp_path / "eps"), "--duration", "3000"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV,
    )  # fmt: skip
    seen = []  # wait until the loop runs (a slow start must not race the signal)
    deadline = time.monotonic() + 60
    while not any("mode AUTO" in line for line in seen):
        assert time.monotonic() < deadline and proc.poll() is None, seen
        seen.append(proc.stdout.readline())
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "completion ratio" in out
    assert all(read_episode(p).end_reason != "crashed" for p in list_episodes(tmp_path / "eps"))


@pytest.mark.parametrize("command", ["calibrate", "teleop", "config check"])
def test_nan_in_a_setting_is_one_line_and_exit_2(tmp_path, command):
    car = tmp_path / "car.toml"
    car.write_text("")
    args = {
        "calibrate": ["calibrate", "--config", car, "--port", tmp_path / "ttyUSB0"],
        "teleop": ["teleop", "--port", tmp_path / "ttyUSB0"],
        "config check": ["config", "check", car],
    }[command]
    result = carrt(*args, "--set", "pwm.max_forward=nan")
    assert_one_line_error(result, "pwm.max_forward", "finite")


def test_drive_on_a_machine_without_a_camera_names_the_simulator():
    result = carrt("drive", "--model", "demo", "--camera", "/dev/video97")
    assert_one_line_error(result, "/dev/video97", "--sim drives the built-in simulator")
