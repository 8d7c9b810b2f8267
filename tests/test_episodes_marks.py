"""Marks (issue 60, item 1): a person excludes seconds of an episode, or all of it, on the
command line; the recorded files' bytes never change; the marks are listed, cleared and undone;
`ls`/`show` report them; and training leaves every excluded step out of every stage."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest
from episode_factory import make_step, run_cli, write_episode

from carrt.episodes import format as fmt
from carrt.episodes.marks import MARKS

STEPS = 50  # 0.1 s apart: step k at k/10 s


def _bytes(ep: Path) -> dict[str, str]:
    return {name: hashlib.sha256((ep / name).read_bytes()).hexdigest()
            for name in (fmt.STEPS, fmt.FRAMES, fmt.META, fmt.SYNCED)}  # fmt: skip


@pytest.fixture
def episode(tmp_path) -> Path:
    return write_episode(tmp_path / "eps", [make_step(i) for i in range(STEPS)])


def test_marks_are_added_listed_undone_and_cleared_without_touching_the_recording(episode, capsys):
    before = _bytes(episode)
    assert run_cli(["episodes", "mark", str(episode), "--exclude", "1.0-1.5"]) == 0
    assert "excluded 1–1.5 s (5 of 50 steps excluded)" in capsys.readouterr().out
    assert (
        run_cli(["episodes", "mark", str(episode), "--exclude-last", "1s", "--note", "fence"]) == 0
    )
    out = capsys.readouterr().out
    assert "excluded 1–1.5 s; excluded 3.901–5.9 s" in out and "note: fence" in out
    assert "(15 of 50 steps excluded)" in out  # 1.0–1.5 s and the last second: 4.0–4.9 s
    assert _bytes(episode) == before  # the recorded files never change
    assert run_cli(["episodes", "mark", str(episode), "--list"]) == 0
    assert "(15 of 50 steps excluded)" in capsys.readouterr().out
    assert run_cli(["episodes", "mark", str(episode), "--undo"]) == 0
    assert "excluded 1–1.5 s (5 of 50 steps excluded)" in capsys.readouterr().out
    assert run_cli(["episodes", "mark", str(episode), "--clear"]) == 0
    assert ": none (0 of 50 steps excluded)" in capsys.readouterr().out
    assert run_cli(["episodes", "mark", str(episode), "--undo"]) == 0  # the clear, undone
    assert "(5 of 50 steps excluded)" in capsys.readouterr().out
    assert _bytes(episode) == before
    json.loads((episode / MARKS).read_text())  # whole JSON, written atomically


def test_ls_and_show_report_the_marks(episode, capsys):
    run_cli(["episodes", "mark", str(episode), "--exclude", "0-1"])
    capsys.readouterr()
    assert run_cli(["episodes", "show", str(episode)]) == 0
    assert "marks          excluded 0–1 s (10 steps out of training)" in capsys.readouterr().out
    assert run_cli(["episodes", "ls", str(episode.parent)]) == 0
    assert "(10 excluded)" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, message",
    [(["--exclude", "5"], "--exclude 5: expected START-END in seconds, e.g. 12.5-15.0"),
     (["--exclude", "3-2"], "--exclude 3-2: expected START-END in seconds"),
     (["--exclude", "nan-2"], "--exclude nan-2: expected START-END in seconds"),
     (["--exclude-last=0s"], "--exclude-last 0s: expected a positive duration, e.g. 3s"),
     (["--clear", "--exclude", "1-2"], "--clear and --undo stand alone")],
)  # fmt: skip
def test_bad_marks_are_one_line(episode, capsys, argv, message):
    from carrt.cli import main

    assert main(["episodes", "mark", str(episode), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err
    assert not (episode / MARKS).exists()


def test_undo_with_nothing_to_undo_and_a_broken_marks_file_are_one_line(episode, capsys):
    from carrt.cli import main

    assert main(["episodes", "mark", str(episode), "--undo"]) == 2
    assert "no earlier marks to go back to" in capsys.readouterr().err
    (episode / MARKS).write_text('{"exclude": [[2, 1]]}')
    assert main(["episodes", "show", str(episode)]) == 2
    assert f"{episode / MARKS}: not a marks file" in capsys.readouterr().err
