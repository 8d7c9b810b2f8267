"""The statistics LeRobot keeps of every feature (meta/stats.json and each episode's row).

LeRobot normalises a policy's inputs and outputs with them, so a dataset without them does not
train there. Per feature: min, max, mean, std, count and the 1/10/50/90/99 % quantiles, over
the frames (axis 0); images per channel, scaled to [0, 1] and shaped (3, 1, 1) as LeRobot's
are. Images are counted with one 256-bin histogram per channel, which gives every statistic
exactly without a float copy of the frames (20,000 frames would be 4 GB as float64). NaN
(no policy, no plan) is left out of a feature's statistics; a feature with no number at all
has NaN statistics.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)


def _names(q: float) -> str:
    return f"q{round(q * 100):02d}"


def feature_stats(values: np.ndarray) -> dict[str, np.ndarray]:
    """Statistics over axis 0 of (N,) or (N, ...) values; (N,) is treated as (N, 1)."""
    if values.ndim == 1:
        values = values[:, None]
    numbers = values.astype(np.float64)
    with warnings.catch_warnings():  # all-NaN columns: NaN statistics, said by their value
        warnings.simplefilter("ignore", RuntimeWarning)
        out = {
            "min": np.nanmin(numbers, axis=0),
            "max": np.nanmax(numbers, axis=0),
            "mean": np.nanmean(numbers, axis=0),
            "std": np.nanstd(numbers, axis=0),
            "count": np.array([len(values)]),
        }
        for q in QUANTILES:
            out[_names(q)] = np.nanquantile(numbers, q, axis=0)
    if values.dtype.kind in "biu":  # min and max in the feature's own type, as LeRobot's
        out["min"], out["max"] = values.min(axis=0), values.max(axis=0)
    return out


class ImageStats:
    """Per-channel histograms of uint8 RGB frames, added to batch by batch."""

    def __init__(self) -> None:
        self.counts = np.zeros((3, 256), dtype=np.int64)
        self.frames = 0

    def add(self, frames: np.ndarray) -> None:
        for c in range(3):
            self.counts[c] += np.bincount(frames[..., c].ravel(), minlength=256)
        self.frames += len(frames)

    def stats(self) -> dict[str, np.ndarray]:
        levels = np.arange(256) / 255.0
        rows: dict[str, list[float]] = {k: [] for k in ("min", "max", "mean", "std")}
        quantiles: dict[str, list[float]] = {_names(q): [] for q in QUANTILES}
        for hist in self.counts:
            total = hist.sum()
            seen = np.flatnonzero(hist)
            mean = float((hist * levels).sum() / total)
            rows["min"].append(levels[seen[0]])
            rows["max"].append(levels[seen[-1]])
            rows["mean"].append(mean)
            rows["std"].append(float(np.sqrt((hist * (levels - mean) ** 2).sum() / total)))
            cumulative = np.cumsum(hist) / total
            for q in QUANTILES:
                quantiles[_names(q)].append(levels[int(np.searchsorted(cumulative, q))])
        out = {k: np.asarray(v).reshape(3, 1, 1) for k, v in {**rows, **quantiles}.items()}
        out["count"] = np.array([self.frames])
        return out


def to_json(stats: dict[str, dict[str, np.ndarray]]) -> dict[str, Any]:
    """numpy → lists (NaN stays NaN, as Python's json reads it back)."""
    return {k: {name: np.asarray(v).tolist() for name, v in s.items()} for k, s in stats.items()}
