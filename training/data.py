"""Training data over carrt episodes: windows of H steps, splits, digest, normalisation.

Episodes are read only with carrt's reader (one implementation of the format). Frames stay in
the reader's memory maps and are copied one window at a time, so a dataset of any size costs
only its small per-step arrays in RAM; DataLoader workers reopen the maps instead of being
sent a pickled copy of every frame.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import Dataset

from carrt.episodes.reader import Episode, list_episodes, read_episode

IMAGE_STD_MIN = 1e-2  # in 0..1 pixel units: a constant channel must not divide by ~0
SPEED_STD_MIN = 0.1  # m/s: data recorded standing still must not blow the speed input up


@dataclass
class Normalisation:
    """Inputs are normalised as (pixel/255 − image_mean)/image_std per RGB channel and
    (speed − speed_mean)/speed_std. Image statistics are in 0..1 pixel units, the convention
    of torchvision's ImageNet statistics, so pretrained backbones can keep theirs."""

    image_mean: tuple[float, float, float] = (0.5, 0.5, 0.5)
    image_std: tuple[float, float, float] = (0.25, 0.25, 0.25)
    speed_mean: float = 0.0
    speed_std: float = 1.0

    def to_dict(self) -> dict[str, Any]:
        """Plain lists and floats: loads under torch.load(weights_only=True) and into JSON."""
        return {
            "image_mean": [float(x) for x in self.image_mean],
            "image_std": [float(x) for x in self.image_std],
            "speed_mean": float(self.speed_mean),
            "speed_std": float(self.speed_std),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Normalisation:
        return cls(
            image_mean=tuple(float(x) for x in d["image_mean"]),
            image_std=tuple(float(x) for x in d["image_std"]),
            speed_mean=float(d["speed_mean"]),
            speed_std=float(d["speed_std"]),
        )


def load_episodes(paths: str | os.PathLike | Iterable[str | os.PathLike]) -> list[Episode]:
    """Every episode under the given episode directories or directories of them, by name.
    Episodes with no steps (a run that died before its first frame) are left out."""
    episodes = [read_episode(p) for p in list_episodes(paths)]
    return [ep for ep in episodes if ep.n > 0]


def _rank_key(seed: int, name: str) -> bytes:
    return hashlib.sha256(f"{seed}:{name}".encode()).digest()


def split_by_episode(
    episodes: Sequence[Episode], val_fraction: float, seed: int
) -> tuple[list[Episode], list[Episode]]:
    """(train, val), whole episodes only: frames of one episode are near-duplicates, so a
    frame-level split would measure memorisation.

    Episodes are ranked by a seeded hash of their name, not by a shuffle of the list, so the
    split does not depend on the order the episodes came in, and an episode stays on its side
    when later iterations add episodes (unless the val set's size changes). With at least two
    episodes and val_fraction > 0 both sides get at least one.
    """
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    n = len(episodes)
    n_val = round(n * val_fraction)
    if val_fraction > 0 and n >= 2:
        n_val = min(max(n_val, 1), n - 1)
    ranked = sorted(range(n), key=lambda i: _rank_key(seed, episodes[i].name))
    val_idx = set(ranked[:n_val])
    train = [ep for i, ep in enumerate(episodes) if i not in val_idx]
    val = [ep for i, ep in enumerate(episodes) if i in val_idx]
    return train, val


def data_digest(episodes: Sequence[Episode]) -> str:
    """sha256 over the episodes' names, step counts and metadata, independent of their order:
    it names a training set (in checkpoints and exported models) without hashing gigabytes."""
    h = hashlib.sha256(b"carrt.data/1\n")
    for ep in sorted(episodes, key=lambda e: e.name):
        h.update(json.dumps([ep.name, int(ep.n), ep.meta], sort_keys=True, default=str).encode())
        h.update(b"\n")
    return h.hexdigest()


def compute_normalisation(episodes: Sequence[Episode], max_frames: int = 4096) -> Normalisation:
    """Per-channel image statistics from at most max_frames frames spread evenly over all the
    episodes; speed statistics from every step (the speeds are already in RAM)."""
    counts = [ep.n for ep in episodes]
    total = sum(counts)
    if total == 0:
        raise ValueError("no steps to compute a normalisation from")
    picks = np.unique(np.linspace(0, total - 1, min(max_frames, total)).round().astype(np.int64))
    starts = np.cumsum([0, *counts])
    s1 = np.zeros(3)
    s2 = np.zeros(3)
    pixels = 0
    for i, ep in enumerate(episodes):
        local = picks[(picks >= starts[i]) & (picks < starts[i + 1])] - starts[i]
        if len(local) == 0:
            continue
        x = np.asarray(ep.frames[local], dtype=np.float64).reshape(-1, 3) / 255.0
        s1 += x.sum(0)
        s2 += np.square(x).sum(0)
        pixels += len(x)
    mean = s1 / pixels
    std = np.sqrt(np.maximum(s2 / pixels - np.square(mean), 0.0))
    speeds = np.concatenate([np.asarray(ep.steps["speed_mps"], np.float64) for ep in episodes])
    speeds = speeds[np.isfinite(speeds)]
    speed_mean = float(speeds.mean()) if len(speeds) else 0.0
    speed_std = float(speeds.std()) if len(speeds) else 1.0
    return Normalisation(
        image_mean=tuple(float(m) for m in mean),
        image_std=tuple(float(max(s, IMAGE_STD_MIN)) for s in std),
        speed_mean=speed_mean,
        speed_std=max(speed_std, SPEED_STD_MIN),
    )


@dataclass
class _Arrays:
    """The small per-step arrays of one episode, copied out of the reader once."""

    path: Path
    n: int
    speed: np.ndarray  # (n,) float32, non-finite → 0
    expert: np.ndarray  # (n, 2) float32: a*
    executed: np.ndarray  # (n, 2) float32: a
    collision: np.ndarray  # (n,) float32: c


def _arrays(ep: Episode) -> _Arrays:
    def clean(x: np.ndarray) -> np.ndarray:
        return np.nan_to_num(np.asarray(x, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)

    return _Arrays(
        path=Path(ep.path),
        n=ep.n,
        speed=clean(ep.steps["speed_mps"]),
        expert=clean(ep.steps["human_action"]),
        executed=clean(ep.steps["executed_action"]),
        collision=np.asarray(ep.collision, dtype=np.float32),
    )


def _edge_slice(a: np.ndarray, start: int, length: int) -> np.ndarray:
    """a[start:start+length], padded at the end by repeating the last row."""
    idx = np.minimum(np.arange(start, start + length), len(a) - 1)
    return a[idx]


class WindowDataset(Dataset):
    """One item per start step t with at least one future step (t + 1 < n).

    Fields (torch tensors): image uint8 (96,96,3) frame t; speed (1,) m/s at t;
    expert_actions (H,2) a*_t..a*_{t+H−1}; actions (H,2) executed a_t..a_{t+H−1};
    future_images uint8 (H,P,P,3) frames t+1..t+H (area-resized to P); future_speeds (H,1);
    collisions (H,) the labels c of t+1..t+H; mask (H,) 1 where step t+1+k exists;
    action_mask (H,) 1 where step t+k exists (one more than mask at an episode's end).
    Past an episode's end every field repeats its last real row; the masks say so.
    collision_free_only keeps the starts whose c_t and window labels are all 0 (the paper's
    imitation data).
    """

    def __init__(
        self,
        episodes: Sequence[Episode],
        horizon: int = 10,
        *,
        predict_size: int = 16,
        collision_free_only: bool = False,
    ) -> None:
        self.horizon = int(horizon)
        self.predict_size = int(predict_size)
        self.collision_free_only = collision_free_only
        self.names = [ep.name for ep in episodes]
        self._eps = [_arrays(ep) for ep in episodes]
        self._frames: dict[int, np.ndarray] = {i: ep.frames for i, ep in enumerate(episodes)}
        index: list[tuple[int, int]] = []
        for i, a in enumerate(self._eps):
            for t in range(a.n - 1):
                if collision_free_only and a.collision[t : t + 1 + self.horizon].any():
                    continue
                index.append((i, t))
        self.index = np.asarray(index, dtype=np.int64).reshape(-1, 2)

    def __len__(self) -> int:
        return len(self.index)

    @property
    def collision_fraction(self) -> float:
        """Share of the valid future labels that are collisions (for class weights)."""
        pos = cnt = 0
        for i, t in self.index:
            c = self._eps[i].collision[t + 1 : t + 1 + self.horizon]
            pos, cnt = pos + int(c.sum()), cnt + len(c)
        return pos / cnt if cnt else 0.0

    def __getstate__(self) -> dict[str, Any]:
        # The memory maps are not sent to DataLoader workers (pickling one copies every frame);
        # each worker reopens the episodes it touches.
        state = self.__dict__.copy()
        state["_frames"] = {}
        return state

    def _frames_of(self, i: int) -> np.ndarray:
        frames = self._frames.get(i)
        if frames is None:
            frames = read_episode(self._eps[i].path).frames[: self._eps[i].n]
            self._frames[i] = frames
        return frames

    def _resize(self, frames: np.ndarray) -> torch.Tensor:
        x = torch.from_numpy(frames)
        if frames.shape[1] == self.predict_size and frames.shape[2] == self.predict_size:
            return x
        size = (self.predict_size, self.predict_size)
        y = F.interpolate(x.permute(0, 3, 1, 2).float(), size=size, mode="area")
        return y.round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).contiguous()

    def __getitem__(self, item: int) -> dict[str, torch.Tensor]:
        i, t = (int(v) for v in self.index[item])
        a, h = self._eps[i], self.horizon
        frames = self._frames_of(i)
        ks = np.arange(h)
        future = np.minimum(t + 1 + ks, a.n - 1)
        # Fancy indexing copies the rows out of the memory map; the map itself stays shared.
        return {
            "image": torch.from_numpy(np.array(frames[t])),
            "speed": torch.tensor([a.speed[t]], dtype=torch.float32),
            "expert_actions": torch.from_numpy(_edge_slice(a.expert, t, h)),
            "actions": torch.from_numpy(_edge_slice(a.executed, t, h)),
            "future_images": self._resize(np.asarray(frames[future])),
            "future_speeds": torch.from_numpy(a.speed[future][:, None].copy()),
            "collisions": torch.from_numpy(a.collision[future].copy()),
            "mask": torch.from_numpy((t + 1 + ks < a.n).astype(np.float32)),
            "action_mask": torch.from_numpy((t + ks < a.n).astype(np.float32)),
        }
