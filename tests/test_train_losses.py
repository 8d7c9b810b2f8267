"""The evidential losses against values worked out by hand from the paper's formulas."""

import math

import pytest
import torch

from training.losses import (
    dirichlet_probability,
    dirichlet_uncertainty,
    evidential_classification_loss,
    evidential_regression_loss,
    nig_nll,
    nig_regulariser,
    nig_uncertainty,
)
from training.models import NIG

# (y, γ, ν, α, β)
CASES = [
    (1.0, 0.5, 2.0, 3.0, 0.5),
    (-0.3, 0.2, 0.1, 1.5, 2.0),
    (0.0, 0.0, 10.0, 1.01, 0.01),
    (4.0, -1.0, 0.5, 20.0, 3.0),
]


def paper_nll(y, gamma, nu, alpha, beta):
    """DESIGN §2 literally: ½log(π/ν) − α·log Ω + (α+½)·log(ν r² + Ω) + lgamma(α) − lgamma(α+½)."""
    omega = 2 * beta * (1 + nu)
    r = y - gamma
    return (
        0.5 * math.log(math.pi / nu)
        - alpha * math.log(omega)
        + (alpha + 0.5) * math.log(nu * r * r + omega)
        + math.lgamma(alpha)
        - math.lgamma(alpha + 0.5)
    )


def nig(gamma, nu, alpha, beta, grad=False):
    t = [torch.tensor(v, dtype=torch.float32, requires_grad=grad) for v in (gamma, nu, alpha, beta)]
    return NIG(*t)


@pytest.mark.parametrize("case", CASES)
def test_nig_nll_regulariser_uncertainty_by_hand(case):
    y, gamma, nu, alpha, beta = case
    p = nig(gamma, nu, alpha, beta)
    yt = torch.tensor(y)
    assert nig_nll(yt, p).item() == pytest.approx(paper_nll(*case), rel=1e-5, abs=1e-5)
    assert nig_regulariser(yt, p).item() == pytest.approx(abs(y - gamma) * (2 * nu + alpha))
    assert nig_uncertainty(p).item() == pytest.approx((1 + 1 / nu) * beta / (alpha - 1), rel=1e-5)


def test_nig_nll_is_the_student_t_marginal():
    # The NIG's predictive distribution is St(γ, β(1+ν)/(να), 2α): an independent check.
    y, gamma, nu, alpha, beta = CASES[0]
    scale = math.sqrt(beta * (1 + nu) / (nu * alpha))
    st = torch.distributions.StudentT(torch.tensor(2 * alpha), torch.tensor(gamma), scale)
    assert nig_nll(torch.tensor(y), nig(gamma, nu, alpha, beta)).item() == pytest.approx(
        -st.log_prob(torch.tensor(y)).item(), rel=1e-5
    )


def test_regression_loss_is_nll_plus_lambda_r():
    y, gamma, nu, alpha, beta = CASES[0]
    expected = paper_nll(*CASES[0]) + 0.1 * abs(y - gamma) * (2 * nu + alpha)
    loss = evidential_regression_loss(torch.tensor(y), nig(gamma, nu, alpha, beta), lam=0.1)
    assert loss.item() == pytest.approx(expected, rel=1e-5)


def test_classification_loss_and_uncertainty_by_hand():
    # e = (3, 1), y = collision: S = 6, p = (2/3, 1/3)
    e = torch.tensor([[3.0, 1.0]])
    y = torch.tensor([[0.0, 1.0]])
    expected = (2 / 3) ** 2 + (2 / 3) ** 2 + 2 * (2 / 3 * 1 / 3) / 7
    assert evidential_classification_loss(y, e).item() == pytest.approx(expected, rel=1e-6)
    assert dirichlet_uncertainty(e).item() == pytest.approx(2 / 6)
    assert dirichlet_probability(e)[0, 1].item() == pytest.approx(1 / 3)
    # no evidence: p = ½, S = 2, u = 1; loss = 2·¼ + 2·¼/3
    zero = torch.zeros(1, 2)
    assert evidential_classification_loss(y, zero).item() == pytest.approx(0.5 + 0.5 / 3)
    assert dirichlet_uncertainty(zero).item() == pytest.approx(1.0)


def test_class_weights_scale_each_sample_by_its_true_class():
    e = torch.tensor([[3.0, 1.0], [3.0, 1.0]])
    y = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    per = [
        (1 / 3) ** 2 * 2 + 2 * (2 / 9) / 7,  # true class 0: p0 = 2/3
        (2 / 3) ** 2 * 2 + 2 * (2 / 9) / 7,
    ]
    w = torch.tensor([1.0, 10.0])
    loss = evidential_classification_loss(y, e, class_weights=w)
    assert loss.item() == pytest.approx((per[0] + 10 * per[1]) / 2, rel=1e-6)


def _finite(*tensors):
    return all(bool(torch.isfinite(t).all()) for t in tensors)


def test_regression_extremes_stay_finite_in_value_and_gradient():
    vals = {
        "gamma": [0.0, 1e6, -1e6, 0.5],
        "nu": [1e-5, 1e9, 1.0, 1e-5],
        "alpha": [1.0 + 1e-3, 1e6, 1.0 + 1e-6, 1e9],
        "beta": [1e-6, 1e6, 1e-6, 1e9],
    }
    grid = torch.meshgrid(*(torch.tensor(v) for v in vals.values()), indexing="ij")
    leaves = [g.reshape(-1).clone().requires_grad_(True) for g in grid]
    p = NIG(*leaves)
    for y in (torch.zeros_like(leaves[0]), torch.full_like(leaves[0], 1e6)):
        loss = evidential_regression_loss(y, p, lam=0.01)
        u = nig_uncertainty(p)
        assert _finite(nig_nll(y, p), nig_regulariser(y, p), loss, u)
        grads = torch.autograd.grad(loss + u.mean(), leaves)
        assert _finite(*grads)


def test_regression_handles_half_precision_inputs_in_float32():
    p = NIG(*(torch.tensor([v], dtype=torch.float16) for v in (0.0, 1e-5, 1.001, 1e-6)))
    out = nig_nll(torch.tensor([300.0], dtype=torch.float16), p)
    assert out.dtype == torch.float32
    assert _finite(out)


def test_classification_extremes_stay_finite():
    e = torch.tensor([[0.0, 0.0], [1e9, 0.0], [0.0, 1e9], [1e9, 1e9]], requires_grad=True)
    y = torch.tensor([[1.0, 0.0], [0.0, 1.0], [0.0, 1.0], [1.0, 0.0]])
    loss = evidential_classification_loss(y, e, class_weights=torch.tensor([1.0, 20.0]))
    (grad,) = torch.autograd.grad(loss, e)
    assert _finite(loss, grad, dirichlet_uncertainty(e))
    assert dirichlet_uncertainty(e)[0].item() == pytest.approx(1.0)
    assert dirichlet_uncertainty(e)[3].item() < 1e-8


def test_mask_averages_only_the_valid_steps():
    torch.manual_seed(0)
    n, h, p = 2, 4, 3
    y = torch.randn(n, h, 3, p, p)
    gamma = torch.randn(n, h, 3, p, p, requires_grad=True)
    params = NIG(gamma, torch.ones(n, h, 3, p, p), torch.full((n, h, 3, p, p), 2.0),
                 torch.ones(n, h, 3, p, p))  # fmt: skip
    mask = torch.tensor([[1.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]])
    y_bad = y.clone()
    y_bad[mask == 0] = 1e6  # padding may hold anything
    loss = evidential_regression_loss(y_bad, params, mask=mask)
    valid = mask.bool()
    expected = evidential_regression_loss(
        y[valid], NIG(gamma[valid], *(t[valid] for t in (params.nu, params.alpha, params.beta)))
    )
    assert loss.item() == pytest.approx(expected.item(), rel=1e-6)
    (grad,) = torch.autograd.grad(loss, gamma)
    assert torch.all(grad[~valid] == 0)
    assert torch.any(grad[valid] != 0)
    nothing = evidential_regression_loss(y, params, mask=torch.zeros(n, h))
    assert nothing.item() == 0.0


def test_classification_mask():
    e = torch.tensor([[[3.0, 1.0], [0.0, 5.0]]])
    y = torch.tensor([[[0.0, 1.0], [1.0, 0.0]]])
    full = evidential_classification_loss(y, e)
    first = evidential_classification_loss(y[:, :1], e[:, :1])
    masked = evidential_classification_loss(y, e, mask=torch.tensor([[1.0, 0.0]]))
    assert masked.item() == pytest.approx(first.item())
    assert masked.item() != pytest.approx(full.item())
