"""`carrt episodes show --verify` tells damage from a cut (issue 60, item 6): a byte flipped
anywhere inside the steps the writer made durable is corruption — exit 2, one line naming the
step and the file, the intact steps after it counted — while a torn tail after a cut is still
reported as one with exit 0, and an episode a crash left empty says so."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from episode_factory import make_step, run_cli, write_episode

from carrt.episodes import format as fmt
from carrt.episodes import read_episode

STEPS = 40


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    return write_episode(tmp_path_factory.mktemp("src"), [make_step(i) for i in range(STEPS)])


def _flip(path: Path, offset: int) -> None:
    with open(path, "r+b") as f:
        f.seek(offset)
        byte = f.read(1)
        f.seek(offset)
        f.write(bytes([byte[0] ^ 0x10]))


# (file, step, offset inside the record or frame): the record's header, its payload and its CRC;
# a frame's first, middle and last byte; the first, a middle and the last step
SWEEP = [
    (fmt.STEPS, step, where) for step in (0, 12, STEPS - 1) for where in ("head", "mid", "end")
]
SWEEP += [
    (fmt.FRAMES, step, where) for step in (0, 12, STEPS - 1) for where in ("head", "mid", "end")
]


@pytest.mark.parametrize("target, step, where", SWEEP)
def test_a_flipped_byte_inside_the_durable_steps_is_reported_as_corruption(
    recorded, tmp_path, capsys, target, step, where
):
    ep_dir = tmp_path / "ep"
    shutil.copytree(recorded, ep_dir)
    size = fmt.FRAME_BYTES if target == fmt.FRAMES else read_episode(recorded).steps.dtype.itemsize
    offset = {"head": 0, "mid": size // 2, "end": size - 1}[where]
    _flip(ep_dir / target, step * size + offset)
    assert run_cli(["episodes", "show", str(ep_dir), "--verify"]) == 2
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert (
        len(lines) == 1 and f"corrupted at step {step} of the {STEPS} written durably" in lines[0]
    )
    assert fmt.STEPS in lines[0] and f"{STEPS - step - 1} intact steps after it" in lines[0]
    if target == fmt.FRAMES:
        assert fmt.FRAMES in lines[0]
    assert "torn tail" not in out and f"CORRUPTED at step {step}" in out
    # --json says the same, and the exit is the same
    assert run_cli(["episodes", "show", str(ep_dir), "--verify", "--json"]) == 2
    damage = json.loads(capsys.readouterr().out)["damage"]
    assert damage["step"] == step and damage["intact_after"] == STEPS - step - 1
    # without --verify the durable steps are trusted (opening stays fast): nothing is claimed
    assert run_cli(["episodes", "show", str(ep_dir)]) == 0
    capsys.readouterr()


def test_a_torn_tail_after_a_cut_is_still_a_torn_tail(recorded, tmp_path, capsys):
    """A power cut: synced.json says 30 steps were durable, the end metadata never came, and
    the last record is half written. --verify reads 39 steps and exits 0."""
    ep_dir = tmp_path / "ep"
    shutil.copytree(recorded, ep_dir)
    meta = json.loads((ep_dir / fmt.META).read_text())
    meta.pop("end", None)
    (ep_dir / fmt.META).write_text(json.dumps(meta))
    (ep_dir / fmt.SYNCED).write_text(json.dumps({"steps": 30}))
    itemsize = read_episode(recorded).steps.dtype.itemsize
    with open(ep_dir / fmt.STEPS, "r+b") as f:
        f.truncate((STEPS - 1) * itemsize + itemsize // 2)
    assert run_cli(["episodes", "show", str(ep_dir), "--verify"]) == 0
    out, err = capsys.readouterr()
    assert "39 frames" in out and "(torn tail ignored)" in out and not err


def test_files_shorter_than_the_durable_steps_are_corruption(recorded, tmp_path, capsys):
    """A finished episode whose files lost their end (a bad copy): not a torn tail."""
    ep_dir = tmp_path / "ep"
    shutil.copytree(recorded, ep_dir)
    with open(ep_dir / fmt.FRAMES, "r+b") as f:
        f.truncate(25 * fmt.FRAME_BYTES)
    assert run_cli(["episodes", "show", str(ep_dir), "--verify"]) == 2
    err = capsys.readouterr().err
    assert f"corrupted at step 25 of the {STEPS} written durably" in err and "end at step" in err


def test_an_episode_a_crash_left_empty_says_so(tmp_path, capsys):
    ep_dir = write_episode(tmp_path, [make_step(0)])
    for name in (fmt.STEPS, fmt.FRAMES):
        (ep_dir / name).write_bytes(b"")
    meta = json.loads((ep_dir / fmt.META).read_text())
    meta.pop("end", None)
    (ep_dir / fmt.META).write_text(json.dumps(meta))
    (ep_dir / fmt.SYNCED).unlink(missing_ok=True)
    assert run_cli(["episodes", "show", str(ep_dir), "--verify"]) == 0
    assert "empty: no step was written before the run ended" in capsys.readouterr().out


def test_salvage_keeps_every_intact_step_in_a_new_episode_that_verifies(recorded, tmp_path, capsys):
    """A flip in step 12's frame: salvage writes the other 39 steps, in order, as a new episode
    that verifies; the damaged one is left as it was; an undamaged one has nothing to salvage."""
    ep_dir = tmp_path / "ep"
    shutil.copytree(recorded, ep_dir)
    _flip(ep_dir / fmt.FRAMES, 12 * fmt.FRAME_BYTES + 7)
    before = (ep_dir / fmt.FRAMES).read_bytes()
    assert run_cli(["episodes", "salvage", str(ep_dir), "-o", str(tmp_path / "out")]) == 0
    out = tmp_path / "out" / "ep-salvaged"
    assert f"wrote {out}: {STEPS - 1} intact steps of {STEPS}" in capsys.readouterr().out
    assert run_cli(["episodes", "show", str(out), "--verify"]) == 0
    capsys.readouterr()
    saved, original = read_episode(out, verify_all=True), read_episode(recorded)
    kept = [i for i in range(STEPS) if i != 12]
    assert saved.n == STEPS - 1 and saved.damage is None
    assert np.array_equal(np.asarray(saved.frames), np.asarray(original.frames)[kept])
    assert np.array_equal(saved.steps["speed_mps"], original.steps["speed_mps"][kept])
    assert json.loads((out / fmt.META).read_text())["salvaged"]["damaged_from_step"] == 12
    assert (ep_dir / fmt.FRAMES).read_bytes() == before
    from carrt.cli import main

    assert main(["episodes", "salvage", str(recorded), "-o", str(tmp_path / "x")]) == 2
    assert "no damage inside its durable steps" in capsys.readouterr().err
