"""research.variants.counterfactual: a world model's imagination scored against the simulator's
replays
(collision AUROC within a start, speed error against the constant-speed baseline, Spearman's ρ
of the refinement objective)."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from research.variants import counterfactual as cf  # noqa: E402
from research.variants.refine_search import alternatives  # noqa: E402
from research.variants.train import main as iterate  # noqa: E402


def test_auroc_counts_only_pairs_from_the_same_start():
    labels = np.array([[1, 0, 0], [1, 1, 0], [0, 0, 0]])
    perfect = np.array([[0.9, 0.1, 0.2], [0.1, 0.1, 0.0], [0.99, 0.99, 0.99]])
    assert cf.within_start_auroc(perfect, labels) == (1.0, 4)
    # High risk everywhere at the second start: ranking across starts would look good; it is not.
    across = np.array([[0.2, 0.3, 0.1], [0.9, 0.9, 0.95], [0.0, 0.0, 0.0]])
    assert cf.within_start_auroc(across, labels)[0] == pytest.approx(0.25)
    assert cf.within_start_auroc(np.full((3, 3), 0.5), labels)[0] == 0.5
    assert np.isnan(cf.within_start_auroc(perfect, np.zeros((3, 3)))[0])


def test_true_objective_counts_no_speed_after_a_collision():
    data = {
        "true_speed": np.array([[[2.0, 2.0, 0.0]]]),
        "true_collision": np.array([[[0.0, 1.0, 0.0]]]),
        "mask": np.array([[[1.0, 1.0, 0.0]]]),
    }
    assert cf.true_objective(data, 1.0, 10.0)[0, 0] == pytest.approx(-4.0 + 10.0)


def test_ordering_against_the_plan_counts_starts_where_imagination_agrees_with_truth():
    """Sequence 1 against the plan (sequence 0): truth says better, worse, worse, tie; the
    imagination says better, better, worse, worse; the tie is left out: 2 of 3 agree."""
    truth = np.array([[0.0, -1.0], [0.0, 2.0], [1.0, 3.0], [5.0, 5.0]])
    imagined = np.array([[0.0, -0.5], [1.0, 0.0], [0.0, 0.1], [0.0, 1.0]])
    assert cf.orders_like_truth(imagined, truth, 1) == pytest.approx(2 / 3)
    assert np.isnan(cf.orders_like_truth(imagined, truth, 0))  # the plan against itself


class _LinearWorld:
    """A stand-in whose imagined speed is scale·(sign·steering + throttle), scale read from the
    start's frame: the objective's gradient at the plan is known per start."""

    def __init__(self, sign: float) -> None:
        self.sign = sign

    def imagine(self, image, speed, actions, clip, correct):
        scale = image.float().mean()
        v = scale * (self.sign * actions[..., 0] + actions[..., 1])
        zero = torch.zeros_like(v)
        return {"speed": v, "p_collision": zero, "u_image": zero, "u_speed": zero,
                "u_collision": zero}  # fmt: skip


def test_gradient_agreement_scores_the_direction_refinement_follows():
    """Truth: at start i steering +0.3 and full throttle drive (i+1) m/s faster per step than
    steering −0.3 and no throttle. A world model whose speed rises with steering agrees on every
    start, raw and centred; one whose speed falls with it on none; throttle agrees in both."""
    names = ["plan", "steer-0.3", "steer+0.3", "lift", "full"]
    n, h = 4, 3
    true_speed = np.ones((n, len(names), h))
    for i in range(n):
        true_speed[i, names.index("steer+0.3")] += i + 1
        true_speed[i, names.index("full")] += i + 1
    data = {
        "actions": np.zeros((n, len(names), h, 2), np.float32),
        "image": np.stack([np.full((4, 4, 3), i + 1, np.uint8) for i in range(n)]),
        "speed": np.ones(n, np.float32),
        "true_speed": true_speed, "true_collision": np.zeros_like(true_speed),
        "mask": np.ones_like(true_speed), "meta": {"sequences": names},
    }  # fmt: skip
    cfg = SimpleNamespace(uncertainty_clip=10.0)
    truth = cf.true_objective(data, 1.0, 10.0)
    right = cf.gradient_agreement(_LinearWorld(1.0), data, cfg, (1.0, 10.0, 1.0), truth)
    assert right == {"steering": 1.0, "steering_centred": 1.0,
                     "throttle": 1.0, "throttle_centred": 1.0}  # fmt: skip
    wrong = cf.gradient_agreement(_LinearWorld(-1.0), data, cfg, (1.0, 10.0, 1.0), truth)
    assert wrong["steering"] == wrong["steering_centred"] == 0.0 and wrong["throttle"] == 1.0
    data["meta"] = {"sequences": names[:3]}  # a set without lift and full: nothing to score
    assert cf.gradient_agreement(_LinearWorld(1.0), data, cfg, (1.0, 10.0, 1.0), truth) == {}


def test_the_search_check_scores_the_move_refine_search_would_make():
    """Three starts over the search's eight sequences (plan first). Start 0: the imagination
    prefers lift (column 5) by 2, and truly lift is 1 better: a right move. Start 1: it prefers
    brake by 0.4, truly 3 worse: a wrong move, gone at margin 0.5. Start 2: it prefers the plan.
    """
    names = ["plan", "steer-0.6", "steer-0.3", "steer+0.3", "steer+0.6", "lift", "brake", "full",
             "random"]  # fmt: skip
    imagined, truth = np.zeros((3, 9)), np.zeros((3, 9))
    imagined[0, 5], truth[0, 5] = -2.0, -1.0
    imagined[1, 6], truth[1, 6] = -0.4, 3.0
    imagined[2, 1:] = 1.0
    truth[2, 7] = -4.0  # a better choice the imagination did not see: the oracle's
    imagined[:, 8], truth[:, 8] = -9.0, 9.0  # "random" is not among the search's choices
    out = cf.search_check(imagined, truth, names)
    assert out["margin_0"] == {"moves": pytest.approx(2 / 3), "right": 0.5,
                               "true_gain": pytest.approx((1.0 - 3.0 + 0.0) / 3)}  # fmt: skip
    assert out["margin_0.5"] == {"moves": pytest.approx(1 / 3), "right": 1.0,
                                 "true_gain": pytest.approx(1 / 3)}  # fmt: skip
    assert out["margin_2"]["moves"] == 0.0 and out["margin_2"]["right"] is None
    assert out["oracle_true_gain"] == pytest.approx((1.0 + 0.0 + 4.0) / 3)
    # what it picks at margin 0, and what truly was best (start 1: nothing beats the plan)
    third = pytest.approx(1 / 3)
    assert out["chosen"] == {"plan": third, "lift": third, "brake": third}
    assert out["truly_best"] == {"plan": third, "lift": third, "full": third}
    assert cf.search_check(imagined[:, :5], truth[:, :5], names[:5]) == {}


class _UnsureOfFullThrottle:
    """A stand-in that imagines speed = throttle with no collisions, and is unsure (u_image 5
    per step) only where the throttle is full: the speed term prefers full throttle, the
    uncertainty term the plan."""

    horizon = 3

    def eval(self):
        return self

    def imagine(self, image, speed, actions, clip, correct):
        v = actions[..., 1].clone()
        zero = torch.zeros_like(v)
        unsure = 5.0 * (actions[..., 1] > 0.99).float()
        return {"speed": v, "p_collision": zero, "u_image": unsure, "u_speed": zero,
                "u_collision": zero}  # fmt: skip


def test_the_check_scores_the_search_with_and_without_the_uncertainty_term():
    """Truly, full throttle beats the plan (half throttle) from both starts. The paper's
    objective stays on the plan (the uncertainty term outweighs the speed); without the term the
    search moves to full throttle, and the move is right."""
    names = ["plan", "steer-0.6", "steer-0.3", "steer+0.3", "steer+0.6", "lift", "brake", "full",
             "random"]  # fmt: skip
    n, h = 2, 3
    plan = torch.zeros(n, h, 2)
    plan[..., 1] = 0.5
    actions = torch.cat([alternatives(plan), plan[:, None]], dim=1).numpy()  # "random": the plan
    true_speed = np.clip(actions[..., 1], 0.0, None).astype(np.float64)
    data = {"actions": actions, "image": np.zeros((n, 4, 4, 3), np.uint8),
            "speed": np.full(n, 0.5, np.float32), "true_speed": true_speed,
            "true_collision": np.zeros_like(true_speed), "mask": np.ones_like(true_speed),
            "meta": {"sequences": names}}  # fmt: skip
    cfg = SimpleNamespace(refine_w_speed=1.0, refine_w_collision=10.0, refine_w_uncertainty=1.0,
                          no_uncertainty=False, uncertainty_clip=10.0)  # fmt: skip
    result = cf.score(_UnsureOfFullThrottle(), data, cfg)
    assert result["search"]["margin_0"]["moves"] == 0.0
    without = result["search_without_uncertainty"]["margin_0"]
    assert without["moves"] == 1.0 and without["right"] == 1.0
    assert without["true_gain"] == pytest.approx(h * 0.5)
    assert result["search"]["chosen"] == {"plan": 1.0}
    assert result["search_without_uncertainty"]["chosen"] == {"full": 1.0}
    assert result["search"]["truly_best"] == {"full": 1.0}
    # Against the plan, full throttle gains 0.5 × 3 steps of speed in imagination and in truth,
    # and loses 5 × 3 steps of uncertainty: the term the paper's objective stays on the plan for.
    full = result["by_sequence"]["full"]["vs_plan"]
    assert full == pytest.approx({"speed": -1.5, "collision": 0.0, "uncertainty": 15.0,
                                  "true": -1.5})  # fmt: skip
    assert result["by_sequence"]["lift"]["vs_plan"]["uncertainty"] == 0.0
    lines = "\n".join(cf.by_sequence_table(result))
    assert "| full |" in lines and "-1.50 / +0.00 / +15.00 | -1.50 |" in lines
    assert "refine_search without the uncertainty term" in lines
    assert "At margin 0 it picks full 100%; truly best: full 100%." in lines


@pytest.mark.timeout(300)  # an iteration and a simulator set: minutes on a loaded machine
def test_an_iteration_reports_its_world_model_counterfactual_check(sim_episodes, tmp_path):
    run = tmp_path / "iter1"
    small = ["--profile", "tiny", "--set", "threads=1", "--set", "progress=false",
             "--set", "figures=false", "--set", "imitation_steps=4",
             "--set", "world_model_steps=4", "--set", "refine_steps=2",
             "--set", "world_model_batch_size=4", "--set", "refine_batch_size=4",
             "--set", "counterfactual_starts=2", "--set", "counterfactual_tracks=200",
             "--set", "refine_search=true"]  # fmt: skip
    before = torch.get_num_threads()
    assert iterate(["--episodes", str(sim_episodes), "--out", str(run), *small]) == 0
    torch.set_num_threads(before)
    reported = json.loads((run / "metrics.json").read_text())["counterfactual"]
    assert "## Counterfactual check" in (run / "report.md").read_text()
    made = (run / "counterfactual.npz").stat().st_mtime_ns
    # The command scores the same run on the same set (made from the same policy: not remade).
    out = tmp_path / "cf.json"
    assert cf.main(["--run", str(run), "--json", str(out)]) == 0
    assert (run / "counterfactual.npz").stat().st_mtime_ns == made
    result = json.loads(out.read_text())
    assert result["starts"] == reported["starts"] == 2 and result["sequences_per_start"] == 9
    assert result["speed_mae"] == pytest.approx(reported["speed_mae"])
    assert 0 <= result["collision_rate"] <= 1
    assert result["speed_mae"] >= 0 and result["speed_mae_constant"] >= 0
    for key in ("collision_auroc", "rank_correlation"):
        assert np.isnan(result[key]) or -1 <= result[key] <= 1
    # The breakdown per kind of sequence agrees with the set it was computed from (its names
    # from the set's meta: this process never imports the simulator).
    data = cf.load(run / "counterfactual.npz")
    names = data["meta"]["sequences"]
    rows = result["by_sequence"]
    assert len(names) == 9 and list(rows) == names
    collided = data["true_collision"].max(axis=2).mean(axis=0)
    assert [rows[n]["true_collision"] for n in names] == pytest.approx(list(collided))
    assert all(0 <= rows[n]["imagined_risk"] <= 1 for n in names)
    assert rows["plan"]["orders_like_truth"] is None  # JSON null, not NaN
    assert all(rows[n]["orders_like_truth"] is None or 0 <= rows[n]["orders_like_truth"] <= 1
               for n in names)  # fmt: skip
    assert "NaN" not in json.dumps(rows)
    assert set(result["gradient_agreement"]) == {
        "steering", "steering_centred", "throttle", "throttle_centred"}  # fmt: skip
    assert "| brake |" in (run / "report.md").read_text()
    assert {"oracle_true_gain", "margin_0", "margin_2"} <= set(result["search"])
    assert "Search among the alternatives" in (run / "report.md").read_text()
    assert set(result["search_without_uncertainty"]) == set(result["search"])
