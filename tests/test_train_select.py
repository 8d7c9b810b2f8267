"""Choosing how far to refine by driving: refinement keeps candidates, selection drives each one
on validation placements through `carrt eval` and keeps the best (training/select_by_driving.py).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from training import checkpoint as ck  # noqa: E402
from training import select_by_driving as sel  # noqa: E402
from training.iterate import main as train  # noqa: E402

TINY = [
    "--profile", "tiny", "--set", "threads=1", "--set", "progress=false",
    "--set", "imitation_batch_size=8", "--set", "world_model_batch_size=4",
    "--set", "refine_batch_size=4", "--set", "eval_windows=64", "--set", "figures=false",
]  # fmt: skip


@pytest.fixture(scope="module")
def refined(sim_episodes, tmp_path_factory):
    """An imitation run, then an iteration that refines for 4 steps keeping a candidate every 2."""
    before = torch.get_num_threads()
    runs = tmp_path_factory.mktemp("runs")
    start, out = runs / "il", runs / "iter"
    steps = ["--set", "imitation_steps=20", "--set", "world_model_steps=0",
             "--set", "refine_steps=0"]  # fmt: skip
    assert train(["--episodes", str(sim_episodes), "--out", str(start), *TINY, *steps]) == 0
    refine = ["--set", "world_model_steps=4", "--set", "refine_steps=4",
              "--set", "refine_candidates_every=2"]  # fmt: skip
    assert train(["--episodes", str(sim_episodes), "--out", str(out), "--init", str(start), *TINY,
                  *refine]) == 0  # fmt: skip
    torch.set_num_threads(before)
    return start, out


def test_refinement_keeps_a_candidate_every_n_steps_the_last_being_the_final_policy(refined):
    _, out = refined
    names = sorted(p.name for p in (out / "candidates").iterdir())
    assert names == ["refine2.pt", "refine4.pt"]
    two, four = (ck.load_checkpoint(out / "candidates" / n) for n in names)
    final = ck.load_checkpoint(out / "policy.pt")
    assert (two["step"], four["step"]) == (2, 4) and four["profile"] == "tiny"
    assert all(torch.equal(four["policy"][k], v) for k, v in final["policy"].items())
    assert not all(torch.equal(two["policy"][k], v) for k, v in four["policy"].items())


def test_selection_drives_every_candidate_and_keeps_the_best_scoring_one(
    refined, sim_episodes, tmp_path
):
    start, out = refined
    chosen = tmp_path / "selected"
    argv = ["--out", str(chosen), "--candidates", f"start={start / 'policy.pt'}",
            str(out / "candidates" / "refine2.pt"), str(out / "candidates" / "refine4.pt"),
            "--episodes", str(sim_episodes), "--tracks", "200", "--seconds", "4", "--jobs", "1",
            "--keep", str(out / "world_model.pt")]  # fmt: skip
    assert sel.main(argv) == 0
    selection = json.loads((chosen / "selection.json").read_text())
    assert [c["name"] for c in selection["candidates"]] == ["start", "refine2", "refine4"]
    for c in selection["candidates"]:  # each one was driven: 4 simulated seconds at 10 Hz
        assert c["aggregate"]["completion_ratio"]["mean"] >= 0.0
        assert (chosen / "candidates" / f"{c['name']}.onnx").is_file()
    picked = next(c for c in selection["candidates"] if c["name"] == selection["chosen"])
    assert picked["score"] == max(c["score"] for c in selection["candidates"])
    assert (chosen / "policy.pt").read_bytes() == Path(picked["checkpoint"]).read_bytes()
    assert (chosen / "world_model.pt").is_file()
    assert not (tmp_path / ".selected.partial").exists()
    # The chosen folder is a run directory the next iteration starts from.
    nxt = tmp_path / "next"
    assert train(["--episodes", str(sim_episodes), "--out", str(nxt), "--init", str(chosen), *TINY,
                  "--set", "world_model_steps=1", "--set", "refine_steps=1",
                  "--set", "export=false"]) == 0  # fmt: skip


def test_reuse_takes_the_numbers_of_identical_weights_and_drives_the_rest(
    refined, sim_episodes, tmp_path, monkeypatch
):
    """The next selection's start is this one's choice: with --reuse it is not driven again, and
    its reused numbers are what driving it again gives (the simulator is deterministic)."""
    import carrt.sim.evaluate as sim_evaluate

    start, out = refined
    first = tmp_path / "first"
    common = ["--episodes", str(sim_episodes), "--tracks", "200", "--seconds", "4", "--jobs", "1"]
    assert sel.main(["--out", str(first), "--candidates", f"start={start / 'policy.pt'}",
                     str(out / "candidates" / "refine2.pt"), *common]) == 0  # fmt: skip
    earlier = json.loads((first / "selection.json").read_text())
    picked = next(c for c in earlier["candidates"] if c["name"] == earlier["chosen"])

    driven = []
    real = sim_evaluate.evaluate
    monkeypatch.setattr(sim_evaluate, "evaluate", lambda m, *a: driven.append(m) or real(m, *a))
    second = tmp_path / "second"
    assert sel.main(["--out", str(second), "--candidates", f"start={first / 'policy.pt'}",
                     str(out / "candidates" / "refine4.pt"), *common,
                     "--reuse", str(first / "selection.json")]) == 0  # fmt: skip
    by_name = {c["name"]: c for c in json.loads((second / "selection.json").read_text())
               ["candidates"]}  # fmt: skip
    assert by_name["start"]["reused_from"].endswith(f"selection.json:{earlier['chosen']}")
    assert by_name["start"]["aggregate"] == picked["aggregate"]
    assert by_name["refine4"]["reused_from"] is None
    assert [Path(m).name for m in driven] == ["refine4.onnx"], "only the new weights are driven"
    # Other placements or seconds are not the same drive: nothing is reused.
    third = tmp_path / "third"
    assert sel.main(["--out", str(third), "--candidates", f"start={first / 'policy.pt'}",
                     *common[:-4], "--seconds", "3", "--jobs", "1",
                     "--reuse", str(first / "selection.json")]) == 0  # fmt: skip
    assert (
        json.loads((third / "selection.json").read_text())["candidates"][0]["reused_from"] is None
    )
    # Driving the chosen weights again gives the numbers that were reused.
    again = real(second / "candidates" / "start.onnx", "hard", [200], 4.0, (0,), 1)
    assert again["aggregate"] == picked["aggregate"]


def test_a_failure_part_way_leaves_out_as_it_was_and_no_staging(
    refined, sim_episodes, tmp_path, capsys
):
    """The second candidate is not a checkpoint: one line, exit 2, the previous choice at OUT
    untouched and no half-written staging folder left behind."""
    start, _ = refined
    chosen = tmp_path / "selected"
    chosen.mkdir()
    (chosen / "policy.pt").write_bytes(b"the previous choice")
    (tmp_path / "broken.pt").write_bytes(b"not a checkpoint")
    argv = ["--out", str(chosen), "--candidates", f"start={start / 'policy.pt'}",
            str(tmp_path / "broken.pt"), "--episodes", str(sim_episodes), "--tracks", "200",
            "--seconds", "2", "--jobs", "1"]  # fmt: skip
    assert sel.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "broken.pt" in err, err
    assert (chosen / "policy.pt").read_bytes() == b"the previous choice"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.pt", "selected"]


def aggregate(completion: float, collisions: float) -> dict:
    return {"completion_ratio": {"mean": completion}, "collisions_per_min": {"mean": collisions}}


def test_the_score_trades_completion_against_collisions_and_ties_keep_fewer_steps():
    driven = [
        {"name": "start", "order": 0, "aggregate": aggregate(0.70, 2.0)},  # 0.60
        {"name": "refine100", "order": 1, "aggregate": aggregate(0.80, 6.0)},  # 0.50
        {"name": "refine200", "order": 2, "aggregate": aggregate(0.65, 0.0)},  # 0.65
        {"name": "refine300", "order": 3, "aggregate": aggregate(0.75, 2.0)},  # 0.65, later
    ]
    assert sel.choose(driven)["name"] == "refine200"
    assert sel.choose(driven, collision_cost=0.0)["name"] == "refine100"
    assert sel.choose(driven[:2])["name"] == "start"  # refinement that drives worse is rejected


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--candidates", "nowhere.pt"], "no such checkpoint: nowhere.pt"),
        (["--candidates", "a=x.pt", "a=x.pt"], "given twice"),
        (["--candidates", "x.pt", "--tracks", "100-104"], "held out for evaluation"),
        (["--candidates", "x.pt", "--seconds", "nan"], "--seconds must be > 0"),
        (["--candidates", "x.pt", "--keep", "gone.pt"], "--keep: no such file: gone.pt"),
        (["--candidates", "x.pt", "--reuse", "gone.json"], "--reuse: cannot read gone.json"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(extra, message, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "x.pt").write_bytes(b"")
    assert sel.main(["--out", "sel", "--episodes", "eps", *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and message in err
    assert not (tmp_path / "sel").exists()
