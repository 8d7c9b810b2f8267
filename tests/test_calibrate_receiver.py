"""`carrt calibrate --receiver` and `carrt check`'s receiver line, against the virtual board with
a receiver on its pins: the person's hands are the only stand-in (they move the sticks before
each Enter)."""

from __future__ import annotations

import argparse
import io
import time

import pytest

from carrt import calibrate, check
from carrt import config as car_config
from carrt.errors import UserError
from firmware_bridge import messages as m
from firmware_bridge.link import BoardLink
from firmware_bridge.virtual import VirtualBoard

# (steering, throttle, switch) the person holds at each prompt: a transmitter whose steering is
# reversed (left is the longer pulse) and whose centres are trimmed off 1500
HANDS = [
    (1512, 1488, 1010),  # centred, switch at run
    (1930, 1488, 1010),  # full left
    (1090, 1488, 1010),  # full right
    (1512, 1985, 1010),  # full forward
    (1512, 1020, 1010),  # full brake
    (1512, 1488, 1990),  # switch at e-stop
    (1512, 1488, 1010),  # and back
]


class Hands(io.StringIO):
    """stdin whose every line first puts the transmitter in the next position."""

    def __init__(self, board: VirtualBoard, positions, answers: str) -> None:
        super().__init__(answers)
        self.board, self.positions = board, list(positions)

    def readline(self, *args):
        if self.positions:
            self.board.set_receiver(*self.positions.pop(0))
            time.sleep(0.2)  # the receiver's next frames, then the telemetry that reports them
        return super().readline(*args)


def _run(tmp_path, board, positions, answers="\n" * 7):
    path = tmp_path / "car.toml"
    path.write_text(car_config.render().replace("[receiver]", "[receiver]\n# my old radio"))
    out = io.StringIO()
    args = argparse.Namespace(config=str(path), port=board.port, set=[], receiver=True)
    code = calibrate.run(args, Hands(board, positions, answers), out)
    return code, path, out.getvalue()


def test_the_transmitter_is_learnt_into_the_file_and_the_board(tmp_path):
    with VirtualBoard() as board:
        code, path, text = _run(tmp_path, board, HANDS)
        assert code == 0, text
        with BoardLink(board.port) as link:
            stored = link.read_config()
    rc = car_config.load(path).receiver
    assert (rc.steer_left_us, rc.steer_center_us, rc.steer_right_us) == (1930, 1512, 1090)
    assert (rc.throttle_reverse_us, rc.throttle_neutral_us, rc.throttle_forward_us) == (
        1020, 1488, 1985,
    )  # fmt: skip
    assert rc.estop_us == (1990 + 1010) // 2
    assert "# my old radio" in path.read_text()
    assert (stored.rc_steer_center_us, stored.rc_throttle_center_us, stored.rc_estop_us) == (
        1512, 1488, 1500,
    )  # fmt: skip
    assert stored.persist == 1
    assert 'receiver.controls = "receiver"' in text  # still the pad's: says how to switch


def test_a_switch_whose_estop_is_the_shorter_pulse_is_refused(tmp_path):
    hands = [*HANDS[:5], (1512, 1488, 1010), (1512, 1488, 1990)]
    with VirtualBoard() as board, pytest.raises(UserError, match="reverse channel 3"):
        _run(tmp_path, board, hands)


def test_a_stick_that_does_not_move_is_named(tmp_path):
    hands = [HANDS[0], HANDS[0], *HANDS[2:]]
    with VirtualBoard() as board, pytest.raises(UserError, match=r"steering .* barely moved"):
        _run(tmp_path, board, hands)


def test_no_receiver_is_one_line(tmp_path):
    with VirtualBoard() as board, pytest.raises(UserError, match="no signal from the RC receiver"):
        _run(tmp_path, board, [])


def test_quitting_writes_nothing(tmp_path):
    with VirtualBoard() as board:
        code, path, text = _run(tmp_path, board, HANDS, answers="\n\nq\n")
    assert code == 1 and "nothing written" in text
    assert car_config.load(path).receiver.steer_left_us == 1000


@pytest.mark.parametrize("controls", [m.Controls.PAD, m.Controls.RECEIVER])
def test_check_reports_the_receiver(controls):
    with VirtualBoard() as board, BoardLink(board.port) as link:
        link.send_config(m.Config(controls=int(controls)))
        report = check.run_check(link, pings=3, duration_s=0.3)
        line = next(row for row in report.lines if row[0] == "receiver")
        assert line[1] == (controls == m.Controls.PAD), line  # missing fails only when it rules
        assert "no signal" in line[2]
        board.set_receiver(1550, 1500, 1000)
        report = check.run_check(link, pings=3, duration_s=0.3)
        line = next(row for row in report.lines if row[0] == "receiver")
    assert line[1] and "steering 1550 us" in line[2] and "switch 1000 us" in line[2]
