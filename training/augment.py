"""Image augmentation for imitation, on the uint8 batch, in torch.

Why: obstacle colours are drawn at random per placement, and a policy trained on a few hundred
placements can latch on to "the red box" instead of "a box". Per sample, a hue rotation (a
rotation of RGB about the grey axis, so a colour turns into another colour of the same
brightness), a saturation and a brightness/contrast jitter. Geometry is never touched: a flipped
or shifted frame would need a changed steering label. One 3×3 colour matrix and an offset per
sample: a single batched matmul, well under a millisecond per batch of 64 on a CPU.
"""

from __future__ import annotations

import math

import torch

_GREY = torch.full((3,), 1.0 / math.sqrt(3.0))


def _hue_rotation(angle: torch.Tensor) -> torch.Tensor:
    """(B,) radians → (B, 3, 3) rotations of RGB about the grey axis (Rodrigues' formula)."""
    k = _GREY
    kx = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    kk = torch.outer(k, k)
    c, s = torch.cos(angle)[:, None, None], torch.sin(angle)[:, None, None]
    eye = torch.eye(3)
    return c * eye + s * kx + (1 - c) * kk


def augment_images(
    images: torch.Tensor,
    generator: torch.Generator,
    *,
    hue: float = 0.5,
    saturation: float = 0.3,
    brightness: float = 0.2,
    contrast: float = 0.2,
) -> torch.Tensor:
    """uint8 (B, h, w, 3) → uint8 (B, h, w, 3) with per-sample colour jitter.

    hue: max rotation as a fraction of a half turn (1.0 = ±180°); saturation, brightness and
    contrast: max relative change (brightness as a share of 255). Deterministic in `generator`.
    """
    b = images.shape[0]

    def uniform(scale: float) -> torch.Tensor:
        return (torch.rand(b, generator=generator) * 2 - 1) * scale

    m = _hue_rotation(uniform(hue * math.pi))
    sat = 1.0 + uniform(saturation)
    grey = torch.outer(_GREY, _GREY)  # projection onto the grey axis
    # saturation: keep the grey component, scale the chroma
    m = m @ (grey + sat[:, None, None] * (torch.eye(3) - grey))
    gain = 1.0 + uniform(contrast)
    offset = uniform(brightness) * 255.0 + (1.0 - gain) * 127.5
    m = m * gain[:, None, None]
    x = images.reshape(b, -1, 3).to(torch.float32)
    y = torch.baddbmm(offset[:, None, None].expand(b, 1, 3), x, m.transpose(1, 2))
    return y.clamp_(0, 255).round_().to(torch.uint8).reshape(images.shape)
