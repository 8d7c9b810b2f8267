"""The keyboard window on a real X server (Xvfb), driven by real key events (xdotool's XTEST):
drive, crash, clear, re-arm, drive on. `.ci/run` installs xvfb and xdotool."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest

from carrt.episodes.reader import list_episodes, read_episode
from carrt.interfaces import Mode

NEEDED = ("Xvfb", "xdotool")


@pytest.fixture
def x_display(tmp_path):
    missing = [tool for tool in NEEDED if shutil.which(tool) is None]
    assert not missing, f"install {' '.join(missing)} (apt-get install xvfb xdotool; .ci/run does)"
    number = 90 + os.getpid() % 500
    server = subprocess.Popen(
        ["Xvfb", f":{number}", "-screen", "0", "1024x768x24", "-nolisten", "tcp"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    env = {k: v for k, v in os.environ.items() if k not in ("SDL_VIDEODRIVER", "WAYLAND_DISPLAY")}
    env["DISPLAY"] = f":{number}"
    deadline = time.monotonic() + 10
    while subprocess.run(["xdotool", "getmouselocation"], env=env, capture_output=True).returncode:
        assert time.monotonic() < deadline and server.poll() is None, "Xvfb did not start"
        time.sleep(0.1)
    yield env
    server.terminate()
    server.wait(timeout=10)


class Keys:
    """`carrt teleop --sim` with its keyboard window on the X server, and real key events."""

    def __init__(self, env: dict, cwd, *args: str) -> None:
        self.env = env
        self.carrt = subprocess.Popen(
            [sys.executable, "-m", "carrt", "teleop", "--sim", "--layout", "easy", *args],
            env=env, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )  # fmt: skip
        deadline = time.monotonic() + 20
        while not (window := self.xdo("search", "--pid", str(self.carrt.pid))):
            assert self.carrt.poll() is None and time.monotonic() < deadline, (
                self.carrt.stdout.read()
            )
            time.sleep(0.2)
        self.xdo("windowfocus", "--sync", window.split()[0])
        time.sleep(1.0)

    def xdo(self, *args: str) -> str:
        done = subprocess.run(["xdotool", *args], env=self.env, capture_output=True, text=True)
        return done.stdout.strip()

    def press(self, key: str, settle: float = 0.6) -> None:
        self.xdo("key", key)
        time.sleep(settle)

    def hold(self, key: str, seconds: float) -> None:
        self.xdo("keydown", key)
        time.sleep(seconds)
        self.xdo("keyup", key)

    def finish(self) -> str:
        """Escape, and the run's output once it has ended (exit code checked)."""
        self.xdo("key", "Escape")
        text, _ = self.carrt.communicate(timeout=30)
        assert self.carrt.returncode == 0, text
        return text


def test_keyboard_session_drive_crash_clear_rearm_drive_on(tmp_path, x_display):
    out = tmp_path / "keys"
    shot = tmp_path / "window.png"
    keys = Keys(x_display, tmp_path, "--record", "--out", str(out), "--duration", "40",
                "--set", "noise.fraction=0.0")  # fmt: skip
    keys.press("Return")  # arm
    keys.hold("Up", 6.0)  # straight on at full throttle: into the fence at the first bend
    time.sleep(1.0)
    keys.press("c")  # clear the collision's e-stop (the car was lifted back onto the track)
    keys.press("Return")  # arm again
    keys.hold("Up", 1.5)  # and drive on
    keys.press("F12")  # screenshot of the window
    text = keys.finish()

    episodes = [read_episode(p) for p in list_episodes(out)]
    assert len(episodes) >= 2, text
    first, last = episodes[0], episodes[-1]
    assert first.end_reason == "collision", text
    assert "stall" not in text, "the board must not fail-safe on a car stuck in the fence"
    after = last.steps
    assert (after["mode"] == Mode.MANUAL).any()
    assert after["speed_mps"].max() > 0.5, "the car drove on after clear and re-arm"
    assert after["human_action"][:, 1].max() > 0.9
    png = tmp_path / "carrt-window.png"
    assert png.stat().st_size > 10_000, "F12 saved the window"
    shutil.copyfile(png, shot)
    import pygame

    image = pygame.surfarray.array3d(pygame.image.load(str(png)))
    assert image.shape[:2] == (96 * 4 + 380, 96 * 4 + 190)
    assert np.std(image) > 20, "the window shows something"


def test_the_keyboard_as_the_transmitter_drive_crash_clear_rearm(tmp_path, x_display):
    """`receiver.controls = "receiver"`: the keys are the transmitter's sticks and switch, put on
    the virtual board's receiver pins; Enter makes the arm gesture, c flips the switch."""
    out = tmp_path / "radio"
    keys = Keys(x_display, tmp_path, "--record", "--out", str(out), "--duration", "40",
                "--set", "receiver.controls=receiver")  # fmt: skip
    keys.press("Return", settle=2.5)  # the arm gesture: steering full right for a second, let go
    keys.hold("Up", 6.0)  # into the fence at the first bend
    time.sleep(1.0)
    keys.press("c", settle=1.5)  # the switch to e-stop and back: clears the collision's latch
    keys.press("Return", settle=2.5)
    keys.hold("Up", 1.5)
    text = keys.finish()
    assert "RC receiver" in text
    episodes = [read_episode(p) for p in list_episodes(out)]
    assert len(episodes) >= 2, text
    assert episodes[0].end_reason == "collision", text
    after = episodes[-1].steps
    assert after["speed_mps"].max() > 0.5, "the car drove on after clear and re-arm"
    assert after["human_action"][:, 1].max() > 0.5, "the throttle, read back from the board"
