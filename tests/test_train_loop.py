"""training/iterate.py's loop (Algorithm 1): imitation, then world model → refine → drive.

In the simulator (--drive sim) the policies drive in worker processes and their episodes join
the next iteration's data; with a car (the default) the loop stops after exporting and says
how to drive, then goes on when the drives are there. Every step is skipped once finished.
The simulator never runs in this (torch) process: the drives run in sim_data's pool workers.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from training import checkpoint as ck  # noqa: E402
from training.iterate import main  # noqa: E402

TINY = [
    "--profile", "tiny", "--set", "threads=1", "--set", "progress=false",
    "--set", "imitation_batch_size=8", "--set", "world_model_batch_size=4",
    "--set", "refine_batch_size=4", "--set", "eval_windows=32", "--set", "figures=false",
    "--set", "imitation_steps=4", "--set", "world_model_steps=3", "--set", "refine_steps=2",
]  # fmt: skip
SIM = ["--drive", "sim", "--drive-tracks", "1000-1001", "--drive-seconds", "4", "--jobs", "2"]


@pytest.fixture(autouse=True)
def restore_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def loop(sim_episodes: Path, out: Path, *extra: str) -> int:
    return main(["--episodes", str(sim_episodes), "--out", str(out), *TINY, *extra])


def episodes_learnt(run: Path) -> int:
    return json.loads((run / "metrics.json").read_text())["data"]["episodes"]


def test_the_loop_in_the_simulator_drives_and_learns_from_the_drives(
    sim_episodes, tmp_path, capsys
):
    out = tmp_path / "loop"
    assert loop(sim_episodes, out, "--iterations", "1", *SIM) == 0
    demos = episodes_learnt(out / "iter_0")
    # imitation only in iter_0; iteration 1 continues from it: world model and refinement
    assert ck.load_checkpoint(out / "iter_0" / "policy.pt")["iteration"] == 0
    first = ck.load_checkpoint(out / "iter_1" / "policy.pt")
    assert first["iteration"] == 1 and first["stage"] == "refine"
    assert not (out / "iter_1" / "checkpoints" / "imitation.pt").exists()
    for k in (0, 1):
        assert (out / f"iter_{k}" / "policy.onnx").is_file()
    assert episodes_learnt(out / "iter_1") == demos
    drives = sorted((out / "iter_1" / "drives").glob("*/meta.json"))
    assert drives, "π_1 recorded no episodes"
    capsys.readouterr()

    # one more iteration: the finished steps are skipped, the drives join the data
    assert loop(sim_episodes, out, "--iterations", "2", *SIM) == 0
    said = capsys.readouterr().out
    assert f"{out / 'iter_0'}: imitation (done)" in said
    assert f"{out / 'iter_1'}: iteration 1: world model → refinement (done)" in said
    assert f"{out / 'iter_1' / 'drives'}: drives (done)" in said
    assert episodes_learnt(out / "iter_2") == demos + len(drives)
    assert ck.load_checkpoint(out / "iter_2" / "policy.pt")["iteration"] == 2
    assert "2 iteration(s) done" in said


def test_with_a_car_the_loop_stops_after_exporting_and_goes_on_when_the_drives_are_there(
    sim_episodes, tmp_path, capsys
):
    """With --takeovers the person is told to take over, and the next iteration learns their
    labels by imitation again before its world model."""
    out = tmp_path / "car"
    assert loop(sim_episodes, out, "--iterations", "2", "--takeovers") == 0
    said = capsys.readouterr().out
    assert (out / "iter_1" / "policy.onnx").is_file()
    assert "carrt drive --model policy.onnx" in said and "--record" in said
    assert "Take over with the stick" in said
    assert str(out / "iter_1" / "drives") in said
    assert not (out / "iter_2").exists() and "iteration(s) done" not in said

    assert loop(sim_episodes, out, "--iterations", "2", "--takeovers") == 0  # not driven yet
    said = capsys.readouterr().out
    assert "(done)" in said and "carrt drive --model" in said and not (out / "iter_2").exists()

    recorded = sorted(p.parent for p in Path(sim_episodes).glob("*/meta.json"))[0]
    shutil.copytree(recorded, out / "iter_1" / "drives" / recorded.name)
    assert loop(sim_episodes, out, "--iterations", "2", "--takeovers") == 0
    said = capsys.readouterr().out
    assert "iteration 2: world model" in said and str(out / "iter_2" / "drives") in said
    assert (out / "iter_2" / "checkpoints" / "imitation.pt").is_file()  # re-imitation
    assert not (out / "iter_1" / "checkpoints" / "imitation.pt").exists()


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--iterations", "0"], "--iterations must be >= 1"),
        (["--iterations", "1", "--init", "x"], "no --init"),
        (["--iterations", "1", "--set", "export=false"], "export must stay on"),
        (["--iterations", "1", "--drive", "boat"], "invalid choice"),
    ],
)
def test_bad_loop_input_is_one_line_and_exit_2(sim_episodes, tmp_path, capsys, extra, message):
    assert loop(sim_episodes, tmp_path / "o", *extra) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
