"""The rigs are one table of named factories (carrt/rig_table.py): every name in it opens, an
unknown name is one line and exit 2, and a new board is one class and one row."""

from __future__ import annotations

import inspect

import pytest

from carrt import rig_table
from carrt.cli import build_parser, main
from carrt.session_cmd import drive_config
from firmware_bridge.virtual import VirtualBoard


class TableBoard(VirtualBoard):
    """A board added the documented way: its own class (here, the virtual board renamed)."""

    LABEL = "board added by one row"


def parse(*argv: str):
    return build_parser().parse_args(["drive", "--model", "demo", *argv])


def chosen(args):
    """The row the command line's drive names."""
    return rig_table.lookup(drive_config(args).rig)


@pytest.mark.parametrize("name", sorted(rig_table.RIGS))
def test_every_registered_rig_resolves(name):
    kind = chosen(parse("--rig", name))
    assert kind is rig_table.RIGS[name] and kind.name == name and kind.summary
    factory = rig_table.load(kind.factory)
    assert {"stack", "drive", "config", "driving", "kind"} <= set(
        inspect.signature(factory).parameters
    )
    assert (kind.board is not None) == kind.simulator, "a simulator rig names its board"
    if kind.board is not None:
        board = rig_table.load(kind.board)
        assert board.LABEL and callable(board.start) and callable(board.stop)


def test_the_older_flags_choose_rows_of_the_same_table():
    assert chosen(parse()).name == "car"
    assert chosen(parse("--sim")).name == "sim"
    assert chosen(parse("--sim", "--board", "virtual")).name == "sim"
    assert chosen(parse("--sim", "--board", "avr")).name == "avr"
    assert set(rig_table.BOARD_RIGS.values()) <= set(rig_table.RIGS)


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--rig", "hovercraft"], ["--rig", "'hovercraft'", "car, sim, avr"]),
        (["--rig", "avr", "--sim"], ["--rig", "--sim"]),
    ],
)
def test_an_unknown_or_doubly_given_rig_is_one_line_and_exit_2(capsys, argv, words):
    # the model does not exist: the rig is checked first, before anything loads
    assert main(["drive", "--model", "no-such.onnx", "--autopilot", *argv]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("carrt drive: error: "), captured.err
    assert all(word in lines[0] for word in words), lines[0]


def test_rig_sim_drives_the_simulator(capsys):
    code = main(["drive", "--rig", "sim", "--autopilot", "--model", "demo", "--duration", "2"])
    assert code == 0
    out = capsys.readouterr().out
    assert "simulator, layout easy" in out and "on the simulated clock" in out
    assert "completion ratio" in out


def test_a_new_board_is_one_class_and_one_row(monkeypatch, capsys):
    row = rig_table.RigKind(
        "table-board",
        "the simulator on a board registered by a test",
        "carrt.sim.rig:open_sim_rig",
        board=f"{__name__}:TableBoard",
        simulator=True,
        always_realtime=True,
    )
    monkeypatch.setitem(rig_table.RIGS, row.name, row)
    argv = ["drive", "--rig", row.name, "--autopilot", "--model", "demo", "--duration", "2"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert f"in real time, {TableBoard.LABEL} on " in out, out
    assert "completion ratio" in out
