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


def mirror_batch(batch: dict, generator: torch.Generator, share: float = 0.5) -> dict:
    """Mirror a random `share` of the samples left↔right: every image (the frame and, for the
    world model, its future frames) flipped across its vertical axis and every steering negated
    (−1 is full left), throttle, speed and collision labels unchanged.

    Why: the car, camera and physics are left-right symmetric, so a mirrored window is a window
    the car could have recorded. On one track driven one way round the policy's steering is
    tied to the place (mostly one way on the bends), and a world model can learn "steering
    this way is safe" from where the car was instead of from what it saw; in the mirrored
    copy the same steering meets the opposite scene, so only what the image shows can explain
    the outcome. Deterministic in `generator`.
    """
    b = batch["image"].shape[0]
    flip = torch.rand(b, generator=generator) < share
    if not bool(flip.any()):
        return batch
    out = dict(batch)
    sign = torch.where(flip, -1.0, 1.0)

    def images(x: torch.Tensor, width_dim: int) -> torch.Tensor:
        picked = flip.view(b, *([1] * (x.dim() - 1))).to(x.device)
        return torch.where(picked, x.flip(width_dim), x)

    def steering(a: torch.Tensor) -> torch.Tensor:
        s = sign.to(a.device, a.dtype).view(b, *([1] * (a.dim() - 2)))
        return torch.stack((a[..., 0] * s, a[..., 1]), dim=-1)

    out["image"] = images(batch["image"], 2)  # (B, h, w, 3)
    if "future_images" in batch:
        out["future_images"] = images(batch["future_images"], 3)  # (B, H, P, P, 3)
    for key in ("actions", "expert_actions"):
        if key in batch:
            out[key] = steering(batch[key])
    return out
