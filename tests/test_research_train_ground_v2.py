"""research/ground_v2.py and research/plan_distil.py (issue 67): the start state from the
recorded commands, the board's rise limit, the speed law's fit, the fused map's unseen floor,
the plan set and the gated target. Small and fast: no simulator, no trained nets."""

import numpy as np
import pytest
import torch

from research import ground_v2, plan_distil
from research.ground_model import CarGeometry, MapGrid

GEO = CarGeometry()
LAW = ground_v2.SpeedLaw(tau=0.25, coef=(5.0, 7.0, 1.88, 0.3))


def imagined(state, actions, v0=1.0):
    acts = torch.tensor(actions, dtype=torch.float32)[None]
    return ground_v2.drive(
        GEO, LAW, torch.tensor([v0]), acts, torch.tensor(np.array([state])).float()
    )


def test_start_state_from_recorded_commands_changes_the_first_steps():
    # a second of full left and full throttle, as a car records it, against the same car at rest
    past = np.tile([[-1.0, 1.0]], (10, 1))
    state = ground_v2.start_states(np.vstack([past, [[0.0, 0.0]]]), LAW, GEO)[-1]
    assert state[0] == pytest.approx(GEO.max_steer, rel=1e-3)  # the servo reached full left
    assert state[1] == pytest.approx(1.0)  # the board's throttle has risen to the command
    plan = [[0.0, 1.0]] * 3
    v_rec, p_rec = imagined(state, plan)
    v_rest, p_rest = imagined([0.0, 0.0, 0.0], plan)
    assert v_rec[0, 0] > v_rest[0, 0] + 0.1  # the motor was already spun up
    assert p_rec[0, 0, 2] > p_rest[0, 0, 2] + 0.05  # the wheels were still turned left


def test_the_board_rise_limit_holds():
    board, motor = ground_v2.board_motor(np.array([1.0, 1.0, -0.5]), tau=0.25)
    assert board[1] == pytest.approx(0.2)  # 2 /s × 0.1 s
    assert board[2] == pytest.approx(0.4)
    assert board[3] == pytest.approx(-0.5)  # a fall is immediate
    assert motor[0].max() <= 0.2 + 1e-9
    fast = ground_v2.SpeedLaw(LAW.tau, LAW.coef, rise_per_s=1e9)
    acts = torch.tensor([[[0.0, 1.0]] * 5])
    v_limited, _ = ground_v2.drive(GEO, LAW, torch.tensor([0.5]), acts, torch.zeros(1, 3))
    v_free, _ = ground_v2.drive(GEO, fast, torch.tensor([0.5]), acts, torch.zeros(1, 3))
    assert (v_limited < v_free - 1e-3).all()


def test_speed_law_fit_recovers_the_law_and_skips_impacts():
    rng = np.random.default_rng(0)
    throttle = np.clip(np.repeat(rng.uniform(0.2, 1.0, 30), 5), 0, 1)
    executed = np.stack([np.zeros_like(throttle), throttle], 1)
    speeds, _ = ground_v2.drive(
        GEO, LAW, torch.tensor([0.5]), torch.from_numpy(executed).float()[None], torch.zeros(1, 3)
    )
    v = np.concatenate([[0.5], speeds[0].numpy()[:-1]])
    corrupt = v.copy()
    corrupt[60:63] = 0.06  # an impact: the car stops dead for a few steps
    seg = {"speed": corrupt, "executed": executed, "events": [59]}
    law, _ = ground_v2.SpeedLaw.fit([seg], 0.1, GEO)
    assert law.tau == pytest.approx(0.25)
    assert law.coef[0] == pytest.approx(5.0, rel=0.05)
    assert law.coef[2] == pytest.approx(1.88, rel=0.05)


def test_unseen_floor_gets_the_base_rate_never_free():
    grid = MapGrid()
    nx, ny = grid.shape
    now = torch.stack([torch.full((nx, ny), 0.9), torch.full((nx, ny), 0.1)])
    visible = torch.zeros(nx, ny)
    visible[nx // 2 :] = 1.0  # the far half seen now
    fused, seen = ground_v2.fuse(grid, [now], visible, [], base=0.03)
    assert torch.all(fused[0][: nx // 2] == 0.03)  # unseen: the base rate, not 0
    assert torch.all(fused[1][: nx // 2] == 1.0)  # and the evidential u is total
    assert torch.all(fused[0][nx // 2 :] == 0.9)
    # a frame 1.5 m back saw the near floor: after dead reckoning its value fills it
    past = torch.stack([torch.full((nx, ny), 0.4), torch.full((nx, ny), 0.2)])
    fused2, seen2 = ground_v2.fuse(grid, [now, past], visible, [np.array([1.5, 0.0, 0.0])], 0.03)
    near = round((0.2 - grid.x_min) / grid.cell)  # 0.2 m ahead now was 1.7 m ahead then
    assert fused2[0][near, ny // 2] == pytest.approx(0.4)
    assert seen2.sum() > seen.sum()


def test_plan_set_keeps_mu_first_and_pairs_the_noise():
    mu = np.zeros((10, 2), np.float32)
    mu[:, 1] = 0.3
    plans = plan_distil.plan_set(mu, [-1, -1], [1, 1], np.random.default_rng(0))
    assert plans.shape == (13 + 4 + 1 + 2 * plan_distil.NOISE_PAIRS, 10, 2)
    assert np.array_equal(plans[0], mu)
    swerve = plans[13]
    assert np.allclose(swerve[:3, 0], -0.6) and np.allclose(swerve[3:], mu[3:])
    a, b = plans[-2], plans[-1]
    assert np.allclose(a + b, 2 * mu, atol=1e-5)  # antithetic (no clipping this close to 0)


def test_gated_target_stays_mu_unless_a_plan_beats_it_by_the_margin_and_members_agree():
    plans = np.stack([np.full((10, 2), v, np.float32) for v in (0.0, 0.5, -0.5)])
    cost = np.array([1.0, 0.9, 1.2])  # the best beats μ by 0.1
    target, moved = plan_distil.gated_target(plans, cost, True, margin=0.2, lam=0.3)
    assert not moved and np.array_equal(target, plans[0])
    target, moved = plan_distil.gated_target(plans, cost, False, margin=0.05, lam=0.3)
    assert not moved and np.array_equal(target, plans[0])
    target, moved = plan_distil.gated_target(plans, cost, True, margin=0.05, lam=0.3)
    assert moved and 0.0 < target[0, 0] < 0.5  # weighted between μ and the better plan
    sharp = plan_distil.weighted_target(plans, cost, lam=1e-4)
    assert np.allclose(sharp, plans[1])  # λ → 0: the best plan


def test_auroc_orders_and_ties():
    assert plan_distil.auroc(np.array([3.0, 2.0, 1.0]), np.array([True, False, False])) == 1.0
    assert plan_distil.auroc(np.array([1.0, 1.0]), np.array([True, False])) == 0.5
