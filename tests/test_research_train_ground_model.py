"""The ground world model (research/ground_model.py, issue 59 3b): its motion is the car's, its
floor projection is the camera's, its labels come from what an episode records, the gradient of
its objective in steering points away from a hazard, and it trains and is scored end to end."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from carrt.sim.car import CarParams, step_car  # noqa: E402
from carrt.sim.render import Renderer  # noqa: E402
from carrt.sim.track import build_track  # noqa: E402
from carrt.sim.types import CarState  # noqa: E402
from research import ground_model as gm  # noqa: E402


@pytest.mark.parametrize("steering, throttle", [(0.0, 0.5), (0.3, 0.6), (-0.8, 0.8), (1.0, 1.0)])
def test_the_paths_follow_the_simulated_car_within_5_cm_over_a_second(steering, throttle):
    """The simulator's car (carrt/sim/car.py) is the truth; the model gets only its speeds (as the
    wheel odometry records them) and the steering commands, and integrates its own constants."""
    state = CarState(x=0.0, y=0.0, yaw=0.0, v=1.5, yaw_rate=0.0, steer=0.0, motor=0.6,
                     sliding=False, odometer=0.0, encoder_ticks=0)  # fmt: skip
    speeds, truth = [state.v], []
    for _ in range(10):
        state = step_car(state, CarParams(), 0.1, steering, throttle)
        speeds.append(state.v)
        truth.append((state.x, state.y, state.yaw))
    poses = gm.rollout(gm.CarGeometry(), torch.tensor([speeds], dtype=torch.float64),
                       torch.full((1, 10), steering, dtype=torch.float64),
                       torch.zeros(1, dtype=torch.float64))[0].numpy()  # fmt: skip
    diff = poses - np.array(truth)
    diff[:, 2] = (diff[:, 2] + math.pi) % (2 * math.pi) - math.pi
    assert np.abs(diff[:, :2]).max() < 0.05 and np.abs(diff[:, 2]).max() < 0.1
    if steering:  # the protocol's sign: +1 is right, a clockwise turn (y falls)
        assert np.sign(poses[-1, 1]) == -np.sign(steering)


def test_a_floor_point_lands_on_the_pixel_whose_ray_the_renderer_casts_to_it():
    """The renderer keeps each pixel's floor hit (relative to the camera); projecting that point
    back through the camera's mounting must give the same pixel."""
    renderer = Renderer(build_track("hard", 200))
    geo = gm.CarGeometry()
    size = renderer.camera.width
    sorted_of_pixel = renderer._out_bytes[::3] // 4  # image pixel q is sorted ray inv[q]
    gx, gy = renderer._gx[sorted_of_pixel], renderer._gy[sorted_of_pixel]
    down = ~renderer._sky[sorted_of_pixel] & (np.hypot(gx, gy) < 5.0)
    q = np.flatnonzero(down)
    u, v, ahead = gm.floor_to_pixel(geo, torch.tensor(gx[q] + geo.cam_forward),
                                    torch.tensor(gy[q]))  # fmt: skip
    assert bool(ahead.all()) and len(q) > 1000
    assert np.abs(u.numpy() - (q % size + 0.5)).max() < 1e-6
    assert np.abs(v.numpy() - (q // size + 0.5)).max() < 1e-6


def test_labels_free_where_the_car_drove_and_hazard_at_the_front_where_it_hit():
    """Straight ahead at 1 m/s for 10 steps, the episode ending in a collision: from frame 0 the
    path's points are free up to the contact, where the front points (0.1 m per step ahead) are
    hazard; nothing past the contact; frame 9's only label is the contact."""
    geo = gm.CarGeometry()
    n = 10
    points, labels = gm.hazard_labels(geo, np.ones(n), np.zeros(n), np.array([n - 1]), 15)
    p = len(gm.body_points(geo))
    hazard = np.flatnonzero(labels[0] == 1)
    assert list(hazard) == [9 * p, 9 * p + 1, 9 * p + 2]  # step 10 = the contact: front points
    assert points[0, hazard, 0] == pytest.approx(1.0 + geo.front, abs=1e-6)
    assert (labels[0, : 9 * p] == 0).all() and (labels[0, 10 * p :] == -1).all()
    assert np.flatnonzero(labels[9] >= 0).tolist() == [0, 1, 2]
    # without an event the path is free to the episode's end
    _, free = gm.hazard_labels(geo, np.ones(n), np.zeros(n), np.array([], dtype=int), 15)
    assert (free[0, : 10 * p] == 0).all() and (free[0, 10 * p :] == -1).all()


def fixed_hazard_model(side: float) -> gm.GroundWorldModel:
    """A ground model whose hazard map rises toward one side (side +1: the left, y > 0) from
    0.6 m ahead on, to a wall beyond 0.15 m off the centreline: the map the net would predict."""
    geo, grid = gm.CarGeometry(), gm.MapGrid()
    model = gm.GroundWorldModel(geo, grid, gm.SpeedResponse())
    nx, ny = grid.shape
    xs = grid.x_min + (torch.arange(nx) + 0.5) * grid.cell
    ys = grid.y_half - (torch.arange(ny) + 0.5) * grid.cell
    x, y = torch.meshgrid(xs, ys, indexing="ij")
    logits = torch.where(x > 0.6, (-2.0 + 40.0 * side * y).clamp(-8, 8), -8.0)
    model.hazard.forward = lambda image: logits.expand(len(image), -1, -1)
    return model


@pytest.mark.parametrize("side, safer", [(1.0, 1.0), (-1.0, -1.0)])
def test_the_objective_gradient_steers_away_from_a_hazard_on_one_side(side, safer):
    """A wall on the left (y > 0): steering right (+) is safer, so the objective (lower is
    better) must fall with steering, and imagined risk must be higher steering into the wall."""
    model = fixed_hazard_model(side)
    image = torch.zeros(1, 96, 96, 3, dtype=torch.uint8)
    plan = torch.tensor([[[0.0, 0.5]] * 10], requires_grad=True)
    out = model.imagine(image, torch.tensor([[1.5]]), plan)
    objective = (-out["speed"] + 10.0 * out["p_collision"]).sum()
    (grad,) = torch.autograd.grad(objective, plan)
    assert np.sign(float(grad[0, :, 0].sum())) == -safer
    away, into = (torch.tensor([[[s * safer, 0.5]] * 10]) for s in (0.5, -0.5))
    with torch.no_grad():
        risk_away = model.imagine(image, torch.tensor([[1.5]]), away)["p_crash"]
        risk_into = model.imagine(image, torch.tensor([[1.5]]), into)["p_crash"]
    assert float(risk_into) > 0.9 and float(risk_away) < float(risk_into)


def test_the_speed_response_is_learnt_from_odometry():
    """Speeds made by the law itself with known constants, from standstill as an episode starts,
    come back from the fit."""
    truth = gm.SpeedResponse(tau=0.2, coef=(4.0, 6.0, 1.5, 0.2))
    rng = np.random.default_rng(0)
    runs = []
    for _ in range(20):
        throttle = np.repeat(rng.uniform(-0.5, 1.0, 8), 5)
        speeds, _ = gm.drive(gm.CarGeometry(substeps=1), truth, torch.tensor([0.0]),
                             torch.tensor(np.stack([np.zeros(40), throttle], 1)[None]),
                             torch.zeros(1))  # fmt: skip
        runs.append((np.concatenate([[0.0], speeds[0].numpy()[:-1]]), throttle))
    fitted = gm.SpeedResponse.fit(runs, 0.1)
    assert fitted.tau == pytest.approx(0.2)
    assert np.allclose(fitted.coef, truth.coef, atol=0.3)
    assert min(fitted.coef) >= 0


def test_it_trains_on_episodes_and_the_check_scores_it(tmp_path, capsys):
    """Recorded sim episodes (the scripted expert as a sloppy person, with crashes) → a ground
    model → the counterfactual check's numbers; a missing run is one line and exit 2."""
    import subprocess
    import sys

    episodes, data = tmp_path / "demos", tmp_path / "cf.npz"
    policy = "carrt/assets/demo_policy.onnx"
    for argv in (["-m", "training.sim_data", "demos", "--out", str(episodes), "--tracks", "1000",
                  "--layouts", "hard", "--episodes", "2", "--noise", "0.5"],
                 ["-m", "carrt.sim.counterfactual", "--model", policy, "--layout", "hard",
                  "--tracks", "200", "--starts", "4", "--out", str(data)]):  # fmt: skip
        subprocess.run([sys.executable, *argv], check=True, capture_output=True)
    run = tmp_path / "run"
    assert gm.main(["train", "--episodes", str(episodes), "--out", str(run), "--steps", "3"]) == 0
    assert (run / "ground_model.pt").is_file() and (run / ".done").is_file()
    assert "speed response tau" in capsys.readouterr().out
    assert gm.main(["check", "--run", str(run), "--data", str(data)]) == 0
    printed = capsys.readouterr().out
    assert '"collision_auroc"' in printed and '"passes"' in printed
    # the same motion with the placement's true obstacles and fence: a crash it cannot miss
    from research.variants.counterfactual import load

    cf = load(data)
    simulated = gm.SpeedResponse(tau=0.25, coef=(5.0, 7.0, 1.88, 0.3))  # carrt/sim/car.py's
    perfect = gm.PerfectMapModel(simulated, cf)
    hit = cf["true_collision"].max(axis=2) > 0
    risk = np.stack([perfect.imagine(torch.from_numpy(cf["image"][i : i + 1]),
                                     torch.tensor([[float(cf["speed"][i])]]),
                                     torch.from_numpy(cf["actions"][i]))["p_crash"].detach().numpy()
                     for i in range(len(hit))])  # fmt: skip
    assert hit.any() and risk[hit].mean() > 0.7 and risk[~hit].mean() < 0.1
    assert gm.main(["check", "--run", str(run), "--data", str(data), "--perfect-map"]) == 0
    assert '"collision_auroc"' in capsys.readouterr().out
    assert gm.main(["check", "--run", str(tmp_path / "nothing"), "--data", str(data)]) == 2
    err = capsys.readouterr().err.strip()
    missing = tmp_path / "nothing" / "ground_model.pt"
    assert err == f"ground_model: error: {missing}: no such ground model file"
    assert gm.main(["train", "--episodes", str(tmp_path / "none"), "--out", str(run)]) == 2
    assert capsys.readouterr().err.startswith("ground_model: error: ")


def test_the_ceiling_plans_in_a_learnt_model_and_steers_away_from_its_hazard():
    """research.ceiling's choice with imagined outcomes: a wall on the left, μ straight ahead at
    half throttle at 2 m/s: steering left scores below μ, right above, and the plan it picks
    does not steer into the wall."""
    from research import ceiling

    model = fixed_hazard_model(1.0)
    mu = np.tile([[0.0, 0.5]], (10, 1)).astype(np.float32)
    plans = ceiling.candidates(mu, 10, (-1.0, -1.0), (1.0, 1.0))
    image = np.zeros((96, 96, 3), np.uint8)
    best, scores = ceiling.choose_imagined(
        (model, None), image, 2.0, plans, "speed", ceiling.Weights()
    )
    names = [name for name, _, _ in ceiling.CANDIDATES]
    assert plans[best, 0, 0] >= 0.0  # right (+) or straight, never towards the left wall
    assert scores[names.index("steer-0.3")] < scores[0] < scores[names.index("steer+0.3")]


def test_the_ceiling_drives_with_learnt_world_models(tmp_path, capsys):
    """`--world-model A,B` scores the plans in each ground model in turn: their runs are labelled
    with it and kept apart from the simulator's, plain drives once; a form it cannot score and
    a missing file are one line."""
    from research import ceiling

    paths = []
    for name, seed in (("wm", 0), ("other", 1)):
        torch.manual_seed(seed)
        model = gm.GroundWorldModel(gm.CarGeometry(), gm.MapGrid(), gm.SpeedResponse())
        gm.save(model, tmp_path / name, gm.TrainConfig())
        paths.append(str(tmp_path / name / "ground_model.pt"))
    args = ["--models", "demo", "--tracks", "200", "--seeds", "0", "--seconds", "2",
            "--out", str(tmp_path / "runs")]  # fmt: skip
    wm = paths[0]
    assert ceiling.main([*args, "--forms", "plain,speed", "--world-model", ",".join(paths)]) == 0
    results = json.loads((tmp_path / "runs" / "results.json").read_text())
    assert sorted(r["world_model"][:3] for r in results["rows"] if r["form"] == "speed") == [
        "oth",
        "wm-",
    ]
    assert [r["form"] for r in results["rows"]].count("plain") == 1
    printed = capsys.readouterr().out
    assert "| demo | speed in wm-" in printed and "| demo | speed in other-" in printed
    assert ceiling.main([*args, "--forms", "survival", "--world-model", wm]) == 2
    err = capsys.readouterr().err
    assert "the forms plain, speed, survival-true-progress only (survival needs the person" in err
    assert ceiling.main([*args, "--forms", "speed", "--world-model", str(tmp_path / "x.pt")]) == 2
    assert capsys.readouterr().err.strip().endswith("x.pt: no such file")
