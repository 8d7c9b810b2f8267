"""A drive is a function of its config: `run_session(DriveConfig(...))` from code returns what
the run did, says nothing unless asked, and is the same drive the command line runs."""

from __future__ import annotations

import io
import pickle

import pytest

from carrt.cli import build_parser
from carrt.errors import UserError
from carrt.session import DriveConfig, run_session
from carrt.session_cmd import drive_config


def test_a_drive_from_code_returns_its_laps_and_collisions_and_prints_nothing(capsys):
    cfg = DriveConfig(model="demo", rig="sim", autopilot=True, layout="hard", track_seed=100,
                      duration=20.0)  # fmt: skip
    result = run_session(cfg)
    assert capsys.readouterr() == ("", ""), "no stdout to redirect: a quiet run is the default"
    assert result.summary.laps >= 1, "20 s is more than a lap of the shipped policy"
    assert result.summary.collisions == result.rig.metrics.collisions
    assert result.summary.laps == result.rig.metrics.laps, "the loop and the simulator agree"
    assert result.exit_code == 0 and result.stopped_by is None


def test_the_report_goes_where_it_is_asked(tmp_path):
    out = io.StringIO()
    cfg = DriveConfig(rig="sim", expert=True, duration=3.0, plot=str(tmp_path / "run.png"))
    result = run_session(cfg, out=out)
    said = out.getvalue()
    assert said.startswith("loop: ") and "completion ratio" in said
    assert f"trajectory plot: {tmp_path / 'run.png'}" in said
    assert result.summary.steps > 0 and (tmp_path / "run.png").is_file()


def test_the_command_line_makes_the_same_config_and_it_travels_to_a_worker():
    argv = ["drive", "--sim", "--autopilot", "--model", "demo", "--layout", "hard",
            "--track-seed", "7", "--set", "noise.during_auto=true", "--duration", "5"]  # fmt: skip
    cfg = drive_config(build_parser().parse_args(argv))
    sets = ("noise.during_auto=true",)
    assert cfg == DriveConfig(model="demo", rig="sim", autopilot=True, layout="hard",
                              track_seed=7, sets=sets, duration=5.0)  # fmt: skip
    assert pickle.loads(pickle.dumps(cfg)) == cfg
    teleop = drive_config(build_parser().parse_args(["teleop", "--sim", "--expert", "auto"]))
    assert teleop.command == "teleop" and teleop.expert and teleop.model is None


def test_an_unknown_rig_from_code_is_a_user_error():
    with pytest.raises(UserError, match="unknown rig 'boat'"):
        run_session(DriveConfig(rig="boat"))
