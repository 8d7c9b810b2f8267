"""The one held-out evaluation loop every stage uses during training.

Why one: the three stages each measured their validation windows with their own loop (eval
mode, fixed windows, batches, restoring the mode afterwards), and the copies drifted. Here a
stage only says what it measures on one batch; the loop does the rest the same way for all.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import nn

from training.data import take


@torch.no_grad()
def held_out(
    modules: Sequence[nn.Module],
    dataset,
    device,
    measure: Callable[[dict], dict[str, tuple[float, float]]],
    *,
    batch_size: int = 32,
    limit: int = 256,
) -> dict[str, float]:
    """Σ numerator / Σ denominator per name over the first `limit` windows of `dataset`, with
    `modules` in eval mode (their previous modes restored). `measure(batch)` returns, per name,
    (numerator, denominator) for one batch already on `device`: (mean, 1) gives the mean over
    batches, (sum of errors, count) an exact mean over items."""
    modes = [m.training for m in modules]
    for m in modules:
        m.eval()
    sums: dict[str, list[float]] = {}
    try:
        n = min(len(dataset), limit)
        for start in range(0, n, batch_size):
            items = range(start, min(n, start + batch_size))
            batch = {k: v.to(device) for k, v in take(dataset, items).items()}
            for name, (num, den) in measure(batch).items():
                acc = sums.setdefault(name, [0.0, 0.0])
                acc[0] += float(num)
                acc[1] += float(den)
    finally:
        for m, mode in zip(modules, modes, strict=True):
            m.train(mode)
    return {k: (num / den if den else float("nan")) for k, (num, den) in sums.items()}
