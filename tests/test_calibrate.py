"""`carrt calibrate` against the virtual board, answered through stdin as a user would."""

from __future__ import annotations

import argparse
import io

from carrt import calibrate, calibration_io
from carrt import config as car_config
from firmware_bridge import messages as m
from firmware_bridge.link import BoardLink
from firmware_bridge.virtual import VirtualBoard


def test_calibration_walks_the_steps_and_writes_file_and_board(tmp_path):
    path = tmp_path / "car.toml"
    path.write_text(car_config.render().replace("[pwm]", "[pwm]\n# my servo is a cheap one"))
    answers = "\n".join(
        [
            "1900", "1490", "",  # neutral: try 1900 (the wheels creep), settle on 1490
            "+", "+", "",  # centre 1500 -> 1520
            "--", "x", "",  # left 1000 -> 950 (and one line it does not understand)
            "2190", "2050", "",  # right: try 2190, settle on 2050
        ]
    ) + "\n"  # fmt: skip
    out = io.StringIO()
    with VirtualBoard() as board:
        args = argparse.Namespace(config=str(path), port=board.port, set=[])
        assert calibrate.run(args, io.StringIO(answers), out) == 0
        assert board.state == m.State.DISARMED
        assert board.steer_us == 1520, "the new centre is what a disarmed board holds"
        with BoardLink(board.port) as link:
            stored = link.read_config()
    text = out.getvalue()
    assert "not understood: 'x'" in text
    config = car_config.load(path)
    assert (config.pwm.steer_center_us, config.pwm.steer_left_us) == (1520, 950)
    assert (config.pwm.steer_right_us, config.pwm.throttle_neutral_us) == (2050, 1490)
    assert "# my servo is a cheap one" in path.read_text(), "comments are kept"
    assert (stored.steer_left_us, stored.steer_center_us, stored.steer_right_us) == (
        950,
        1520,
        2050,
    )
    assert stored.throttle_neutral_us == 1490 and stored.persist == 1


def test_a_value_the_board_refuses_cannot_be_accepted(tmp_path):
    path = tmp_path / "car.toml"
    path.write_text(car_config.render())
    # A centre outside left..right is refused by the board; Enter must not accept it.
    answers = "\n2150\n\n1500\n\nq\n"
    out = io.StringIO()
    with VirtualBoard() as board:
        args = argparse.Namespace(config=str(path), port=board.port, set=[])
        assert calibrate.run(args, io.StringIO(answers), out) == 1
    text = out.getvalue()
    assert "board refused it (rejected invalid)" in text
    assert "fix the value first" in text
    assert "nothing written" in text
    assert car_config.load(path) == car_config.CarConfig()


def test_update_toml_section_adds_missing_keys():
    text = "[serial]\nport = 'x'\n\n[pwm]\nsteer_left_us = 1000  # measured\n"
    updated = calibration_io.update_toml_section(
        text, "pwm", {"steer_left_us": 990, "steer_right_us": 2010}
    )
    assert "steer_left_us = 990  # measured" in updated
    assert "steer_right_us = 2010" in updated
    assert car_config.from_dict(car_config.tomllib.loads(updated)).pwm.steer_right_us == 2010
