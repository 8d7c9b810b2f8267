"""Choosing how far to refine by driving: refinement keeps candidates, selection drives each one
on validation placements through `carrt eval` and keeps the incumbent unless another beats it by
more than the placements' noise (research/variants/select_by_driving.py).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from research.variants import select_by_driving as sel  # noqa: E402
from research.variants.train import main as train  # noqa: E402
from training import checkpoint as ck  # noqa: E402

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
    """With --margin-z 0 the rule is the plain best score."""
    start, out = refined
    chosen = tmp_path / "selected"
    argv = ["--out", str(chosen), "--candidates", f"start={start / 'policy.pt'}",
            str(out / "candidates" / "refine2.pt"), str(out / "candidates" / "refine4.pt"),
            "--episodes", str(sim_episodes), "--tracks", "200,201", "--seconds", "4",
            "--jobs", "1", "--margin-z", "0", "--keep", str(out / "world_model.pt")]  # fmt: skip
    assert sel.main(argv) == 0
    selection = json.loads((chosen / "selection.json").read_text())
    assert [c["name"] for c in selection["candidates"]] == ["start", "refine2", "refine4"]
    assert selection["incumbent"] == "start" and selection["margin_z"] == 0
    for c in selection["candidates"]:  # each one was driven: 4 simulated seconds at 10 Hz
        assert c["aggregate"]["completion_ratio"]["mean"] >= 0.0
        assert [(r["track"], r["seed"]) for r in c["placements"]] == [(200, 0), (201, 0)]
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
    text = (first / "selection.json").read_text()
    assert "Infinity" not in text, "one placement: no standard error, written as null"
    earlier = json.loads(text)
    assert earlier["candidates"][1]["standard_error"] is None
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


def candidate(name: str, order: int, completions: list[float], collisions: float = 0.0) -> dict:
    """A driven candidate: one completion per validation placement (tracks 200, 201, ...)."""
    placements = [
        {"track": 200 + i, "seed": 0, "completion_ratio": c, "collisions_per_min": collisions}
        for i, c in enumerate(completions)
    ]
    mean = sum(completions) / len(completions)
    aggregate = {"completion_ratio": {"mean": mean}, "collisions_per_min": {"mean": collisions}}
    return {"name": name, "order": order, "aggregate": aggregate, "placements": placements}


def test_the_plain_best_score_trades_completion_against_collisions_and_ties_keep_fewer_steps():
    driven = [
        candidate("start", 0, [0.70, 0.70], 2.0),  # 0.60
        candidate("refine100", 1, [0.80, 0.80], 6.0),  # 0.50
        candidate("refine200", 2, [0.65, 0.65], 0.0),  # 0.65
        candidate("refine300", 3, [0.75, 0.75], 2.0),  # 0.65, later
    ]
    assert sel.choose(driven, margin_z=0)["name"] == "refine200"
    assert sel.choose(driven, collision_cost=0.0, margin_z=0)["name"] == "refine100"
    assert sel.choose(driven[:2], margin_z=0)["name"] == "start"  # refinement that drives worse


def test_a_challenger_must_win_by_more_than_the_placements_noise():
    """Ahead by 0.05 on average but by +0.45/−0.35 on single placements: noise, the incumbent
    stays; ahead by 0.04 on every placement alike: a real gain, it wins."""
    imitated = candidate("imitated", 1, [0.5, 0.9, 0.5, 0.9])
    lucky = candidate("lucky", 2, [0.95, 0.55, 0.95, 0.55])
    steady = candidate("steady", 3, [0.54, 0.94, 0.54, 0.94])
    start = candidate("start", 0, [0.4, 0.8, 0.4, 0.8])
    assert sel.choose([start, imitated, lucky], incumbent="imitated")["name"] == "imitated"
    assert lucky["advantage"] == pytest.approx(0.05) and lucky["standard_error"] > 0.2
    assert start["advantage"] == pytest.approx(-0.1), "the incumbent is the yardstick"
    assert sel.choose([start, imitated, lucky], incumbent="imitated", margin_z=0)["name"] == "lucky"
    picked = sel.choose([start, imitated, lucky, steady], incumbent="imitated")
    assert picked["name"] == "steady" and steady["standard_error"] == pytest.approx(0.0)
    # Without --incumbent the first candidate is the one to beat: here every other one does.
    assert sel.choose([start, imitated, steady])["name"] == "steady"


def test_one_placement_is_no_evidence_and_keeps_the_incumbent():
    start, better = candidate("start", 0, [0.5]), candidate("refine100", 1, [0.9])
    assert sel.choose([start, better])["name"] == "start"
    assert better["standard_error"] is None, "JSON has no infinity"
    assert sel.choose([start, better], margin_z=0)["name"] == "refine100"


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--candidates", "nowhere.pt"], "no such checkpoint: nowhere.pt"),
        (["--candidates", "a=x.pt", "a=x.pt"], "given twice"),
        (["--candidates", "x.pt", "--tracks", "100-104"], "held out for evaluation"),
        (["--candidates", "x.pt", "--seconds", "nan"], "--seconds must be > 0"),
        (["--candidates", "x.pt", "--margin-z", "-1"], "--margin-z >= 0"),
        (["--candidates", "x.pt", "--margin-z", "inf"], "--margin-z >= 0"),
        (["--candidates", "x.pt", "--incumbent", "imitated"], "no candidate is named 'imitated'"),
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
