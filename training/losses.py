"""Evidential losses (the DIRL paper): regression for images and speed, classification for
collisions.

The reference implementations of these losses are known for NaNs. Everything here computes in
float32 whatever the inputs' dtype (autocast, half precision), and the NIG negative log
likelihood is rearranged so that no term can overflow or cancel for finite inputs:

    NLL = ½log(π/ν) − α·log Ω + (α+½)·log(ν r² + Ω) + lgamma(α) − lgamma(α+½),  Ω = 2β(1+ν)
        = ½log(π/ν) + ½log Ω + (α+½)·log1p(ν r² / Ω) + lgamma(α) − lgamma(α+½)

The second form never subtracts two large α·log Ω terms, takes log Ω as a sum of logs (no
β·ν product to overflow), and bounds the ratio inside log1p, so residuals of 1e6 with β of 1e-6
or evidence of 1e9 stay finite in value and gradient.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

NU_MIN = 1e-5  # ν floor (evidential pitfalls: ν → 0 makes the NLL blow up)
ALPHA_MARGIN = 1e-3  # α ≥ 1 + margin, so the uncertainty β/(α − 1) stays finite
BETA_MIN = 1e-6


@dataclass
class NIG:
    """Normal-Inverse-Gamma parameters; the prediction is γ. ν > 0, α > 1, β > 0."""

    gamma: Tensor
    nu: Tensor
    alpha: Tensor
    beta: Tensor

    def map(self, fn: Callable[[Tensor], Tensor]) -> NIG:
        """The same op on all four (index, detach, reshape, .to(device))."""
        return NIG(fn(self.gamma), fn(self.nu), fn(self.alpha), fn(self.beta))

    @classmethod
    def from_raw(cls, raw: Tensor, dim: int) -> NIG:
        """Split four raw channels along `dim` and constrain them (σ, evidence positive)."""
        gamma, nu, alpha, beta = raw.unbind(dim)
        return cls(
            gamma=gamma,
            nu=F.softplus(nu).clamp(min=NU_MIN),
            alpha=F.softplus(alpha) + 1.0 + ALPHA_MARGIN,
            beta=F.softplus(beta) + BETA_MIN,
        )


_LOG_PI = math.log(math.pi)
_LOG_2 = math.log(2.0)
_RATIO_MAX = 1e30  # log1p(1e30) ≈ 69: beyond this the loss is flat, not inf
_RESIDUAL_MAX = 1e12  # in normalised units; r² must stay finite or the β gradient is 0·inf


def _f32(*tensors: Tensor) -> list[Tensor]:
    return [t.float() for t in tensors]


def nig_nll(y: Tensor, nig: NIG) -> Tensor:
    """Elementwise negative log likelihood of y under the Student-t that the NIG implies."""
    y, gamma, nu, alpha, beta = _f32(y, nig.gamma, nig.nu, nig.alpha, nig.beta)
    r2 = (y - gamma).clamp(-_RESIDUAL_MAX, _RESIDUAL_MAX).square()
    ratio = (r2 * (nu / (1.0 + nu)) / (2.0 * beta)).clamp(max=_RATIO_MAX)
    log_omega = _LOG_2 + torch.log(beta) + torch.log1p(nu)
    return (
        0.5 * (_LOG_PI - torch.log(nu))
        + 0.5 * log_omega
        + (alpha + 0.5) * torch.log1p(ratio)
        + torch.lgamma(alpha)
        - torch.lgamma(alpha + 0.5)
    )


def nig_regulariser(y: Tensor, nig: NIG) -> Tensor:
    """Elementwise |y − γ|·(2ν + α): evidence is penalised where the prediction is wrong."""
    y, gamma, nu, alpha = _f32(y, nig.gamma, nig.nu, nig.alpha)
    return (y - gamma).abs() * (2.0 * nu + alpha)


def _masked_mean(loss: Tensor, mask: Tensor | None) -> Tensor:
    """Mean over the elements where mask is set; mask's dims align with loss's leading dims
    ((N, H) for a loss of (N, H, 3, P, P)). An all-zero mask gives 0, not NaN."""
    if mask is None:
        return loss.mean()
    mask = mask.float()
    mask = mask.reshape(*mask.shape, *([1] * (loss.dim() - mask.dim()))).expand_as(loss)
    valid = mask > 0
    # where(), not loss * mask: padded elements may hold inf, and inf * 0 is NaN.
    total = torch.where(valid, loss * mask, torch.zeros_like(loss)).sum()
    return total / mask.sum().clamp(min=1.0)


def evidential_regression_loss(
    y: Tensor, nig: NIG, lam: float = 0.01, mask: Tensor | None = None
) -> Tensor:
    """NLL + λ·R, averaged over the valid elements."""
    return _masked_mean(nig_nll(y, nig) + lam * nig_regulariser(y, nig), mask)


def nig_uncertainty(nig: NIG) -> Tensor:
    """Elementwise (1 + 1/ν)·β/(α − 1): the model's uncertainty in its own prediction γ.

    It grows without bound as α → 1; clip it before it enters a policy loss.
    """
    nu, alpha, beta = _f32(nig.nu, nig.alpha, nig.beta)
    return (1.0 + 1.0 / nu) * beta / (alpha - 1.0)


def dirichlet_probability(evidence: Tensor) -> Tensor:
    """Expected class probabilities p = (e + 1)/S of the Dirichlet the evidence implies."""
    alpha = evidence.float() + 1.0
    return alpha / alpha.sum(dim=-1, keepdim=True)


def evidential_classification_loss(
    y_onehot: Tensor,
    evidence: Tensor,
    class_weights: Tensor | None = None,
    mask: Tensor | None = None,
) -> Tensor:
    """Σ_j (y_j − p_j)² + p_j(1 − p_j)/(S + 1), averaged over the valid samples.

    class_weights (K,) weights each sample by its true class (the collision class is rare);
    the mean still divides by the number of valid samples, so a weight of w counts such a
    sample w times. mask has the samples' shape (evidence's without the class dim).
    """
    y, evidence = _f32(y_onehot, evidence)
    alpha = evidence + 1.0
    strength = alpha.sum(dim=-1, keepdim=True)
    p = alpha / strength
    loss = ((y - p).square() + p * (1.0 - p) / (strength + 1.0)).sum(dim=-1)
    if class_weights is not None:
        loss = loss * (y * class_weights.to(loss.device, torch.float32)).sum(dim=-1)
    return _masked_mean(loss, mask)


def dirichlet_uncertainty(evidence: Tensor) -> Tensor:
    """K/S: 1 with no evidence at all, → 0 as evidence accumulates. Shape: evidence's minus
    the class dim."""
    evidence = evidence.float()
    return evidence.shape[-1] / (evidence + 1.0).sum(dim=-1)
