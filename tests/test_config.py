"""Car config: defaults valid, every bad input named in one line, overrides, `carrt config`."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import pytest

from carrt import config as car_config
from carrt.errors import UserError


def test_defaults_are_valid_and_render_round_trips(tmp_path):
    path = tmp_path / "car.toml"
    path.write_text(car_config.render())
    assert car_config.load(path) == car_config.CarConfig()


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[pwm]\nmax_forwrd = 0.3\n", "pwm.max_forwrd: unknown key (did you mean max_forward?)"),
        ("[pwn]\nmax_forward = 0.3\n", "unknown section [pwn] (did you mean pwm?)"),
        ("[pwm]\nmax_forward = 3.0\n", "pwm.max_forward: 3.0 is above the maximum 1.0"),
        ("[pwm]\nsteer_left_us = 500\n", "pwm.steer_left_us: 500 is below the minimum 800"),
        ('[serial]\nbaud = "fast"\n', "serial.baud: expected int"),
        ("[camera]\nloop_video = 1\n", "camera.loop_video: expected bool"),
        ("[serial]\nbaud = true\n", "serial.baud: expected int"),
        ('[joystick]\npreset = "n64"\n', "joystick.preset: 'n64' is not one of"),
        ("[pwm]\nsteer_center_us = 2100\n", "pwm.steer_center_us: must lie between"),
        ("[noise]\nhold_min_s = 3.0\nhold_max_s = 1.0\n", "noise.hold_min_s"),
        ("pwm = 3\n", "config pwm: expected a [pwm] table"),
        ("[pwm\n", "not valid TOML"),
    ],
)
def test_bad_config_names_the_key(tmp_path, text, message):
    path = tmp_path / "car.toml"
    path.write_text(text)
    with pytest.raises(UserError) as info:
        car_config.load(path)
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_integers_are_accepted_for_floats_and_overrides_win(tmp_path):
    path = tmp_path / "car.toml"
    path.write_text("[pwm]\nmax_forward = 1\n[camera]\nsource = 'a.mp4'\n")
    config = car_config.load(path, ["camera.source=b.mp4", "pwm.max_forward=0.25"])
    assert config.camera.source == "b.mp4"
    assert config.pwm.max_forward == 0.25
    with pytest.raises(UserError, match=r"expected section\.key=value"):
        car_config.load(None, ["max_forward=0.2"])


def test_missing_file_is_a_user_error(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        car_config.load(tmp_path / "nope.toml")


def test_board_config_carries_the_limits():
    config = car_config.load(None, ["pwm.max_forward=0.4", "pwm.slew_per_s=1.5"])
    board = car_config.board_config(config, persist=True)
    assert (board.max_forward, board.slew_per_s, board.persist) == (4000, 15000, 1)


def run_carrt(*args, cwd):
    return subprocess.run(
        [sys.executable, "-m", "carrt", *args], capture_output=True, text=True, cwd=cwd, timeout=60
    )


def test_config_init_and_check_commands(tmp_path):
    result = run_carrt("config", "init", "-o", "car.toml", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    text = (tmp_path / "car.toml").read_text()
    assert "# largest forward throttle the board allows" in text
    assert run_carrt("config", "check", "car.toml", cwd=tmp_path).returncode == 0
    again = run_carrt("config", "init", "-o", "car.toml", cwd=tmp_path)
    assert again.returncode == 2 and "already exists" in again.stderr
    (tmp_path / "car.toml").write_text(text.replace("max_forward = 0.5", "max_forward = 7"))
    bad = run_carrt("config", "check", "car.toml", cwd=tmp_path)
    assert bad.returncode == 2
    assert bad.stderr.strip() == (
        "carrt config: error: config pwm.max_forward: 7.0 is above the maximum 1.0"
    )


FLOAT_KEYS = [
    f"{section}.{f.name}"
    for section in car_config.SECTIONS
    for f in dataclasses.fields(getattr(car_config.CarConfig(), section))
    if isinstance(getattr(getattr(car_config.CarConfig(), section), f.name), float)
]


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_every_float_key_refuses_nan_and_infinities(tmp_path, value):
    """NaN compares False with every bound: without its own check it passed as 'ok'."""
    assert len(FLOAT_KEYS) >= 10 and "camera.max_age_s" in FLOAT_KEYS
    for key in FLOAT_KEYS:
        section, name = key.split(".")
        path = tmp_path / "car.toml"
        path.write_text(f"[{section}]\n{name} = {value}\n")
        with pytest.raises(UserError) as info:
            car_config.load(path)
        assert str(info.value) == f"config {key}: expected a finite number, got {float(value)!r}"
        with pytest.raises(UserError, match="finite"):
            car_config.load(None, [f"{key}={value}"])


def test_config_check_refuses_nan_in_one_line(tmp_path):
    (tmp_path / "car.toml").write_text("[camera]\nmax_age_s = nan\n")
    bad = run_carrt("config", "check", "car.toml", cwd=tmp_path)
    assert bad.returncode == 2
    assert bad.stderr.strip() == (
        "carrt config: error: config camera.max_age_s: expected a finite number, got nan"
    )
