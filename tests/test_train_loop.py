"""training/iterate.py's loop (Algorithm 1 with the take-overs): imitation, then rounds of the
policy driving while the person takes over and imitating again, each policy compared with the
one before it; --dirl adds each iteration's refined policy beside it.

In the simulator (--drive sim) the policies drive in worker processes and their episodes join
the next iteration's data, and each iteration's policy and the one before it drive the
validation placements (`carrt eval` processes); with a car (the default) the loop stops when a
policy's drives are missing and says how to drive, then goes on when they are there, and its
reports say how to compare the policies' drives (`carrt report`). Every step is skipped once
finished. The simulator never runs in this (torch) process.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from training import checkpoint as ck  # noqa: E402
from training.iterate import DIRL_STATUS, main  # noqa: E402

TINY = [
    "--profile", "tiny", "--set", "threads=1", "--set", "progress=false",
    "--set", "imitation_batch_size=8", "--set", "world_model_batch_size=4",
    "--set", "refine_batch_size=4", "--set", "eval_windows=32", "--set", "figures=false",
    "--set", "imitation_steps=4", "--set", "world_model_steps=3", "--set", "refine_steps=2",
    "--set", "reimitation_steps=3",
]  # fmt: skip
SIM = ["--drive", "sim", "--drive-tracks", "1000-1001", "--drive-seconds", "4", "--jobs", "2",
       "--compare-tracks", "200", "--compare-seconds", "4", "--compare-seeds", "0"]  # fmt: skip


@pytest.fixture(autouse=True)
def restore_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def loop(sim_episodes: Path, out: Path, *extra: str) -> int:
    return main(["--episodes", str(sim_episodes), "--out", str(out), *TINY, *extra])


def episodes_learnt(run: Path) -> int:
    return json.loads((run / "metrics.json").read_text())["data"]["episodes"]


def test_the_loop_in_the_simulator_takes_over_imitates_again_and_compares(
    sim_episodes, tmp_path, capsys
):
    out = tmp_path / "loop"
    assert loop(sim_episodes, out, "--iterations", "1", *SIM) == 0
    said = capsys.readouterr().out
    demos = episodes_learnt(out / "iter_0")
    assert ck.load_checkpoint(out / "iter_0" / "policy.pt")["iteration"] == 0
    drives = sorted((out / "iter_0" / "drives").glob("*/meta.json"))
    assert drives, "π_0 recorded no episodes"
    first = ck.load_checkpoint(out / "iter_1" / "policy.pt")
    assert first["iteration"] == 1 and first["stage"] == "imitation" and first["step"] == 3
    assert first["config"]["init"] == str(out / "iter_0")  # a take-over round from π_0
    assert episodes_learnt(out / "iter_1") == demos + len(drives)
    assert not list(out.rglob("world_model.pt")) and not list(out.rglob("refined"))
    assert "not validated" not in said  # no --dirl: no status line

    # π_1 against π_0, driven on the validation placement: printed and in iter_1's report
    assert "π_1 against π_0 on validation placements 200 (`hard`, 4 simulated s" in said
    report = (out / "iter_1" / "report.md").read_text()
    assert report.count("## Against the previous iteration, driven (simulator)") == 1
    assert "| π_1 − π_0, per run | 1 |" in report and "laps / min" in report
    against = json.loads((out / "iter_1" / "metrics.json").read_text())["against_previous"]
    assert against["runs"] == 1
    for k in (0, 1):
        ran = json.loads((out / f"iter_{k}" / "validation.json").read_text())
        assert ran["config"]["tracks"] == [200] and len(ran["runs"]) == 1
        new, old = against["completion_ratio"]["new"], against["completion_ratio"]["old"]
        assert ran["aggregate"]["completion_ratio"]["mean"] == pytest.approx((old, new)[k][0])
    kept = (out / "iter_1" / "validation.json").stat().st_mtime_ns

    # one more iteration: the finished steps are skipped, π_1's drives join the data
    assert loop(sim_episodes, out, "--iterations", "2", *SIM) == 0
    said = capsys.readouterr().out
    assert f"{out / 'iter_0'}: imitation (done)" in said
    assert f"{out / 'iter_1'}: take-over round 1: imitation again (done)" in said
    assert f"{out / 'iter_0' / 'drives'}: drives (done)" in said
    more = sorted((out / "iter_1" / "drives").glob("*/meta.json"))
    assert episodes_learnt(out / "iter_2") == demos + len(drives) + len(more)
    assert ck.load_checkpoint(out / "iter_2" / "policy.pt")["iteration"] == 2
    assert (out / "iter_1" / "validation.json").stat().st_mtime_ns == kept  # not driven again
    assert "π_2 against π_1" in said and "2 iteration(s) done" in said


def test_the_loop_with_dirl_refines_beside_each_iteration_and_drives_both(
    sim_episodes, tmp_path, capsys
):
    """--dirl: every iteration has refined/ beside its imitated policy, driven against it; the
    rounds go on from the imitated policies; the status line is printed once."""
    out = tmp_path / "loop"
    assert loop(sim_episodes, out, "--iterations", "1", "--dirl", *SIM) == 0
    said = capsys.readouterr().out
    assert said.count(DIRL_STATUS) == 1
    for k in (0, 1):
        here = out / f"iter_{k}"
        assert ck.load_checkpoint(here / "policy.pt")["stage"] == "imitation"
        assert ck.load_checkpoint(here / "refined" / "policy.pt")["stage"] == "refine"
        assert (here / "refined" / "policy.onnx").is_file()
        assert (here / "refined" / "world_model.pt").is_file()
        assert not (here / "world_model.pt").exists()
        report = (here / "report.md").read_text()
        assert "## The world model and refinement (--dirl)" in report
        assert report.count("## The refined policy against the imitated one, driven") == 1
        assert f"π_{k} refined against π_{k} on validation placements 200" in said
        assert (here / "refined" / "validation.json").is_file()
    assert ck.load_checkpoint(out / "iter_1" / "policy.pt")["config"]["init"] == str(
        out / "iter_0"
    )  # the round goes on from the imitated policy, not the refined one
    assert "## Against the previous iteration, driven" in (out / "iter_1" / "report.md").read_text()


def test_with_a_car_the_loop_stops_for_the_drives_and_goes_on_when_they_are_there(
    sim_episodes, tmp_path, capsys
):
    """The person is told to drive the policy and take over; the next iteration imitates their
    labels again, and its report says how to compare the two policies' drives on the car."""
    out = tmp_path / "car"
    assert loop(sim_episodes, out, "--iterations", "2") == 0
    said = capsys.readouterr().out
    assert (out / "iter_0" / "policy.onnx").is_file()
    assert "carrt drive --model policy.onnx" in said and "--record" in said
    assert "take over with the stick" in said
    assert str(out / "iter_0" / "drives") in said
    assert not (out / "iter_1").exists() and "iteration(s) done" not in said

    assert loop(sim_episodes, out, "--iterations", "2") == 0  # not driven yet
    said = capsys.readouterr().out
    assert "(done)" in said and "carrt drive --model" in said and not (out / "iter_1").exists()

    recorded = sorted(p.parent for p in Path(sim_episodes).glob("*/meta.json"))[0]
    shutil.copytree(recorded, out / "iter_0" / "drives" / recorded.name)
    assert loop(sim_episodes, out, "--iterations", "2") == 0
    said = capsys.readouterr().out
    assert "take-over round 1: imitation again" in said and str(out / "iter_1" / "drives") in said
    assert (out / "iter_1" / "checkpoints" / "imitation.pt").is_file()
    assert not (out / "iter_2").exists()
    report = (out / "iter_1" / "report.md").read_text()
    assert "## Against the previous iteration (on the car)" in report
    assert f"carrt report {out / 'iter_0' / 'drives'}" in report
    assert f"carrt report {out / 'iter_0' / 'drives'}" in said
    assert not list(out.rglob("validation.json"))  # nothing driven in the simulator


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--iterations", "0"], "--iterations must be >= 1"),
        (["--iterations", "1", "--init", "x"], "no --init"),
        (["--iterations", "1", "--set", "export=false"], "export must stay on"),
        (["--iterations", "1", "--drive", "boat"], "invalid choice"),
        (["--iterations", "1", "--takeovers"], "unrecognized arguments: --takeovers"),
        (["--iterations", "1", "--compare-tracks", "100-104"], "not a validation placement"),
        (["--iterations", "1", "--compare-seconds", "0"], "--compare-seconds must be > 0"),
        (["--iterations", "1", "--compare-seeds", "x"], "--compare-seeds"),
        (
            ["--iterations", "1", "--drive-tracks", "200-210", "--compare-tracks", "210-219"],
            "share placement 210",
        ),
    ],
)
def test_bad_loop_input_is_one_line_and_exit_2(sim_episodes, tmp_path, capsys, extra, message):
    assert loop(sim_episodes, tmp_path / "o", *extra) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
