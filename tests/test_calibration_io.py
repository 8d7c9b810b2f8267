"""The calibration's edit of car.toml (issue 68, item 4): tomlkit sets the keys in whichever TOML
style the person wrote the table (a header with a comment, dotted keys, an inline table, a
missing one) and keeps the rest; the result is read back by carrt's loader before the file is
replaced, atomically; a file that would not load, or a full disk, leaves it byte-identical and
says so in one line. The property test writes any valid file in mixed styles."""

from __future__ import annotations

import argparse
import io
import os
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import pytest
from hypothesis import given
from strategies import car_toml_files
from test_calibrate_receiver import HANDS, Hands
from test_disk_full import _in_small_filesystem

import carrt
from carrt import calibrate
from carrt import config as car_config
from carrt.calibration_io import commit, plan_edit, update_toml_section
from carrt.cli import main
from carrt.deps import missing_package_message
from carrt.errors import UserError
from firmware_bridge.link import BoardLink
from firmware_bridge.virtual import VirtualBoard

tomllib = car_config.tomllib
# what `carrt calibrate` writes, in its order: neutral, centre, left, right
PWM = {"throttle_neutral_us": 1490, "steer_center_us": 1510, "steer_left_us": 990,
       "steer_right_us": 2010}  # fmt: skip


def _edit(path: Path, text: str, section: str = "pwm", values: dict | None = None) -> str:
    path.write_bytes(text.encode())
    commit(plan_edit(path, section, values or PWM))
    return path.read_bytes().decode()


STYLES = {
    # the regex's failure: `[pwm]  # µs` was not its `[pwm]`, so it added a second one
    "a header with a comment": (
        """\
        # my car
        [serial]
        port = "/dev/ttyACM0"  # the Nano

        [pwm]  # µs, measured on the stand
        steer_left_us = 1000  # full left
        steer_center_us=1500
        throttle_neutral_us = 1500

        # the camera is a cheap one
        [camera]
        fps = 30.0
        """,
        """\
        # my car
        [serial]
        port = "/dev/ttyACM0"  # the Nano

        [pwm]  # µs, measured on the stand
        steer_left_us = 990  # full left
        steer_center_us=1510
        throttle_neutral_us = 1490
        steer_right_us = 2010

        # the camera is a cheap one
        [camera]
        fps = 30.0
        """,
    ),
    # the regex's other failure: dotted keys got a `[pwm]` table that declared pwm twice
    "dotted keys at top level": (
        """\
        serial.port = "/dev/ttyACM0"
        pwm.steer_left_us = 1000  # full left
        pwm.steer_center_us = 1500
        camera.fps = 30.0
        pwm.throttle_neutral_us = 1500

        [receiver]
        deadzone_us = 40
        """,
        """\
        serial.port = "/dev/ttyACM0"
        pwm.steer_left_us = 990  # full left
        pwm.steer_center_us = 1510
        camera.fps = 30.0
        pwm.throttle_neutral_us = 1490
        pwm.steer_right_us = 2010

        [receiver]
        deadzone_us = 40
        """,
    ),
    "an inline table": (
        """\
        serial = { port = "/dev/ttyACM0" }
        pwm = { steer_left_us = 1000, steer_center_us = 1500, max_forward = 0.3 }  # measured

        [camera]
        fps = 30.0
        """,
        """\
        serial = { port = "/dev/ttyACM0" }
        pwm = { steer_left_us = 990, steer_center_us = 1510, max_forward = 0.3, \
throttle_neutral_us = 1490, steer_right_us = 2010 }  # measured

        [camera]
        fps = 30.0
        """,
    ),
    "a quoted, spaced header with indented keys": (
        """\
        [ "pwm" ]
          steer_left_us = 1_000
          steer_center_us = 0x5DC  # the servo's own centre
        [camera]
        fps = 30.0
        """,
        """\
        [ "pwm" ]
          steer_left_us = 990
          steer_center_us = 1510  # the servo's own centre
          throttle_neutral_us = 1490
          steer_right_us = 2010
        [camera]
        fps = 30.0
        """,
    ),
    "a missing table, added at the end": (
        """\
        [serial]
        port = "/dev/ttyACM0"  # [pwm] is not here
        """,
        """\
        [serial]
        port = "/dev/ttyACM0"  # [pwm] is not here

        [pwm]
        throttle_neutral_us = 1490
        steer_center_us = 1510
        steer_left_us = 990
        steer_right_us = 2010
        """,
    ),
}


@pytest.mark.parametrize("style", list(STYLES))
def test_each_style_gets_the_values_and_keeps_its_comments_and_order(tmp_path, style):
    before, after = (textwrap.dedent(t) for t in STYLES[style])
    path = tmp_path / "car.toml"
    assert _edit(path, before) == after
    pwm = car_config.load(path).pwm
    assert {k: getattr(pwm, k) for k in PWM} == PWM


def test_a_windows_file_keeps_its_line_ends(tmp_path):
    text = textwrap.dedent(STYLES["a header with a comment"][0]).replace("\n", "\r\n")
    after = _edit(tmp_path / "car.toml", text)
    assert after == textwrap.dedent(STYLES["a header with a comment"][1]).replace("\n", "\r\n")


def test_a_super_table_of_the_same_name_is_not_ours():
    text = "[car.pwm]\nsteer_left_us = 1000\n"
    after = update_toml_section(text, "pwm", {"steer_left_us": 990})
    assert after == "[car.pwm]\nsteer_left_us = 1000\n\n[pwm]\nsteer_left_us = 990\n"


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("[car.pwm]\nsteer_left_us = 1000\n", "unknown section [car]"),
        ("[pwm\nsteer_left_us = 1000\n", "is not a TOML file carrt can edit"),
        ("pwm = 3\n", "pwm is not a table"),
        ("[pwm]  # a forward end below the new neutral\nthrottle_forward_us = 1450\n",
         "throttle_neutral_us: must lie between reverse and forward"),
    ],
)  # fmt: skip
def test_a_file_that_would_not_load_is_refused_in_one_line_and_left_byte_identical(
    tmp_path, text, reason
):
    path = tmp_path / "car.toml"
    path.write_bytes(text.encode())
    with pytest.raises(UserError) as refused:
        plan_edit(path, "pwm", PWM)
    message = str(refused.value)
    assert "\n" not in message and str(path) in message and reason in message
    assert path.read_bytes() == text.encode() and os.listdir(tmp_path) == ["car.toml"]


def test_calibrate_refuses_a_file_the_calibration_would_break_before_the_board_stores_it(
    tmp_path, monkeypatch, capsys
):
    """`--set` made the walk valid, the file alone would not be: neither file nor EEPROM
    change, and the line says why."""
    path = tmp_path / "car.toml"
    path.write_text("[pwm]  # µs\nthrottle_reverse_us = 1495\n")
    before = path.read_bytes()
    monkeypatch.setattr(sys, "stdin", io.StringIO("1490\n\n\n\n\n"))
    with VirtualBoard() as board:
        argv = ["calibrate", "--config", str(path), "--port", board.port,
                "--set", "pwm.throttle_reverse_us=1000"]  # fmt: skip
        assert main(argv) == 2
        board.reboot()
        with BoardLink(board.port) as link:
            stored = link.read_config()
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"carrt calibrate: error: {path} would not")
    assert "throttle_neutral_us: must lie between reverse and forward" in lines[0]
    assert path.read_bytes() == before
    assert stored.throttle_neutral_us == 1500, "the EEPROM kept its old neutral"


def test_calibrate_writes_into_dotted_keys_and_the_file_loads(tmp_path):
    path = tmp_path / "car.toml"
    path.write_text("pwm.steer_left_us = 1000  # a cheap servo\npwm.throttle_neutral_us = 1500\n")
    answers = "1490\n\n+\n\n--\n\n2050\n\n"  # neutral 1490, centre 1510, left 950, right 2050
    with VirtualBoard() as board:
        args = argparse.Namespace(config=str(path), port=board.port, set=[])
        assert calibrate.run(args, io.StringIO(answers), io.StringIO()) == 0
    assert path.read_text() == (
        "pwm.steer_left_us = 950  # a cheap servo\npwm.throttle_neutral_us = 1490\n"
        "pwm.steer_center_us = 1510\npwm.steer_right_us = 2050\n"
    )
    pwm = car_config.load(path).pwm
    assert (pwm.steer_left_us, pwm.steer_center_us, pwm.steer_right_us) == (950, 1510, 2050)


def test_calibrate_receiver_writes_under_a_commented_header_and_the_file_loads(tmp_path):
    path = tmp_path / "car.toml"
    path.write_text('[receiver]  # my old radio, µs\ncontrols = "both"\n\n# the pad\n[joystick]\n')
    with VirtualBoard() as board:
        args = argparse.Namespace(config=str(path), port=board.port, set=[], receiver=True)
        assert calibrate.run(args, Hands(board, HANDS, "\n" * 7), io.StringIO()) == 0
    text = path.read_text()
    assert text.startswith(
        '[receiver]  # my old radio, µs\ncontrols = "both"\nsteer_left_us = 1930'
    )
    assert text.endswith("estop_us = 1500\n\n# the pad\n[joystick]\n")
    assert text.count("[receiver]") == 1
    assert car_config.load(path).receiver.steer_left_us == 1930


def test_the_mode_is_kept_and_a_link_stays_a_link(tmp_path):
    real = tmp_path / "cars" / "car.toml"
    real.parent.mkdir()
    real.write_text("[pwm]\n")
    real.chmod(0o640)
    link = tmp_path / "car.toml"
    link.symlink_to(real)
    commit(plan_edit(link, "pwm", PWM))
    assert link.is_symlink() and car_config.load(real).pwm.steer_left_us == 990
    assert real.stat().st_mode & 0o777 == 0o640
    assert sorted(os.listdir(real.parent)) == ["car.toml"], "no temporary file left"


def test_a_file_changed_while_calibrating_is_not_overwritten(tmp_path):
    path = tmp_path / "car.toml"
    path.write_text("[pwm]\n")
    edit = plan_edit(path, "pwm", PWM)
    path.write_text("[pwm]\nmax_forward = 0.2  # typed in meanwhile\n")
    with pytest.raises(UserError, match="changed while calibrating"):
        commit(edit)
    assert path.read_text() == "[pwm]\nmax_forward = 0.2  # typed in meanwhile\n"


def test_a_full_disk_leaves_the_file_intact_in_one_line(tmp_path):
    """On a real, full 3 MB filesystem: `carrt calibrate` ends in one line naming the file and
    what was not written; the file is byte-identical and no temporary file is left."""
    original = tmp_path / "car.toml"
    original.write_text("[pwm]  # µs\nsteer_left_us = 1000  # cheap servo\n")
    script = tmp_path / "calibrate.py"
    script.write_text(
        "import io, sys\n"
        "from carrt.cli import main\n"
        "from firmware_bridge.virtual import VirtualBoard\n"
        "sys.stdin = io.StringIO('\\n' * 4)  # Enter at each step: the values as they are\n"
        "with VirtualBoard() as board:\n"
        "    sys.exit(main(['calibrate', '--config', sys.argv[1], '--port', board.port]))\n"
    )
    done = _in_small_filesystem(tmp_path, textwrap.dedent(f"""
        cp {original} $SMALL/car.toml
        dd if=/dev/zero of=$SMALL/fill bs=64k count=100 2>/dev/null
        {sys.executable} {script} $SMALL/car.toml > /dev/null; echo "rc=$?"
        cmp {original} $SMALL/car.toml && echo SAME; ls -A $SMALL
    """))  # fmt: skip
    assert "rc=2" in done.stdout and "SAME" in done.stdout, done.stderr
    assert done.stdout.split()[-2:] == ["car.toml", "fill"], "no temporary file left"
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "car.toml not written (disk full: " in lines[0], done.stderr
    assert "the file is unchanged; the calibration was pwm.throttle_neutral_us = 1500" in lines[0]


@given(car_toml_files())
def test_any_valid_file_in_mixed_styles_takes_the_calibration_and_keeps_the_rest(case):
    text, section, values = case
    before = tomllib.loads(text)
    car_config.from_dict(before)  # the generated file is one carrt loads
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "car.toml"
        path.write_bytes(text.encode())
        commit(plan_edit(path, section, values))
        after_text = path.read_bytes().decode()
        loaded = getattr(car_config.load(path), section)
    assert {k: getattr(loaded, k) for k in values} == values
    after = tomllib.loads(after_text)
    assert {s: v for s, v in after.items() if s != section} == {
        s: v for s, v in before.items() if s != section
    }
    old = before.get(section, {})
    assert {k: v for k, v in after[section].items() if k not in values} == {
        k: v for k, v in old.items() if k not in values
    }
    for line in text.splitlines():
        if "# note-" in line:
            comment = line[line.index("# note-") :]
            assert comment in after_text, f"comment lost: {comment!r}"


def test_without_tomlkit_other_commands_run_and_calibrating_says_what_to_install(
    tmp_path, monkeypatch
):
    """A car's venv made before tomlkit was a dependency: every command imports the
    calibration's module (the CLI builds all parsers), so only calibrating may need it."""
    path = tmp_path / "car.toml"
    path.write_text("[pwm]\n")
    blocked = "import sys; sys.modules['tomlkit'] = None; from carrt.cli import main; "
    check = subprocess.run(
        [sys.executable, "-c", blocked + f"sys.exit(main(['config', 'check', {str(path)!r}]))"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert check.returncode == 0, check.stderr
    monkeypatch.setitem(sys.modules, "tomlkit", None)
    monkeypatch.delitem(sys.modules, "carrt.toml_edit", raising=False)
    monkeypatch.delattr(carrt, "toml_edit", raising=False)  # as if never imported
    with pytest.raises(ModuleNotFoundError) as missing:
        plan_edit(path, "pwm", PWM)
    assert missing_package_message(missing.value) == (
        "this needs tomlkit (editing car.toml), which is not installed: pip install tomlkit "
        "(or reinstall carrt)"
    )
