"""Training data over carrt episodes: normalisation, the frame store and windows of H steps.

Which episodes are read, and which of them train or validate, is training/episodes.py.

Episodes are read only with carrt's reader (one implementation of the format). Training on a
CPU is limited by compute, and every millisecond spent reading memory maps per window is a
millisecond the two cores do not train: so all frames are decoded once into one uint8 tensor
in RAM (FrameStore, 2.8 GB per 100K frames) and a batch is gathered by tensor indexing,
without DataLoader workers. Imitation reads only the current frame (ImitationDataset); the
world model's future frames come from a once-resized copy of the store.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import Dataset, default_collate

from carrt.episodes.reader import Episode, labels_before, read_episode
from carrt.interfaces import Mode
from carrt.model_contract import HORIZON, IMAGE_SHAPE
from training.episodes import (  # re-exported: the stages and tests import them from here
    data_digest,
    load_episodes,
    placement_key,
    split_by_episode,
    split_by_placement,
)

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
    label: np.ndarray  # (n,) float32: 1 where a* is the person's command (mode MANUAL)
    intervention: np.ndarray  # (n,) bool: MANUAL steps of a take-over from AUTO
    takeover: np.ndarray  # (n,) float32: 1 in the 0.5 s before each take-over (override edge)


def _intervention_steps(mode: np.ndarray, override: np.ndarray) -> np.ndarray:
    """True from each override edge (the person took over in AUTO) while the mode stays MANUAL."""
    out = np.zeros(len(mode), dtype=bool)
    on = False
    for t in range(len(mode)):
        on = bool(override[t]) or (on and mode[t] == int(Mode.MANUAL))
        out[t] = on and mode[t] == int(Mode.MANUAL)
    return out


def takeover_labels(ep: Episode) -> np.ndarray:
    """1 for the steps in the 0.5 s before each take-over (override edge), as a collision's:
    the person stopped the policy because it was about to crash (the paper's e-stop)."""
    override = np.asarray(ep.steps["override"], dtype=bool)
    edges = np.flatnonzero(override & ~np.concatenate(([False], override[:-1])))
    return labels_before(np.asarray(ep.steps["frame_captured_at"], dtype=np.float64), edges)


def _arrays(ep: Episode) -> _Arrays:
    def clean(x: np.ndarray) -> np.ndarray:
        return np.nan_to_num(np.asarray(x, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)

    mode = np.asarray(ep.steps["mode"], dtype=np.int64)
    override = np.asarray(ep.steps["override"], dtype=bool)
    return _Arrays(
        path=Path(ep.path),
        n=ep.n,
        speed=clean(ep.steps["speed_mps"]),
        expert=clean(ep.steps["human_action"]),
        executed=clean(ep.steps["executed_action"]),
        collision=np.asarray(ep.collision, dtype=np.float32),
        label=(mode == int(Mode.MANUAL)).astype(np.float32),
        intervention=_intervention_steps(mode, override),
        takeover=takeover_labels(ep).astype(np.float32),
    )


def _area_resize(frames: torch.Tensor, size: int) -> torch.Tensor:
    """uint8 (N, h, w, 3) → uint8 (N, size, size, 3), area mean, rounded."""
    if frames.shape[1] == size and frames.shape[2] == size:
        return frames
    y = F.interpolate(frames.permute(0, 3, 1, 2).float(), size=(size, size), mode="area")
    return y.round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).contiguous()


class FrameStore:
    """Every frame of a list of episodes, decoded once into one uint8 tensor in RAM.

    Why: a training step gathers its batch with one index_select instead of 64 memory-map
    reads and 640 per-window resizes (measured: 17 % of an imitation step went to loading),
    and the world model's future frames are resized once per frame, not once per window they
    appear in (H = 10 times). 100K frames cost 2.8 GB (+0.3 GB at predict_size 32). Global step
    g of episode i is offsets[i] + t; the per-step arrays are concatenated the same way.
    Pickling (DataLoader workers) sends the episode paths only; the frames are re-read there.
    """

    def __init__(self, episodes: Sequence[Episode]) -> None:
        self.paths = [Path(ep.path) for ep in episodes]
        self.starts = [int(getattr(ep, "start", 0)) for ep in episodes]  # a marked segment's
        self._eps = [_arrays(ep) for ep in episodes]
        self.offsets = np.cumsum([0, *(a.n for a in self._eps)]).astype(np.int64)
        self._load(episodes)

    def _load(self, episodes: Sequence[Episode] | None = None) -> None:
        starts = [0] * len(self.paths) if episodes is not None else self.starts
        if episodes is None:  # unpickled (a DataLoader worker): read again, segments included
            episodes = [read_episode(p) for p in self.paths]
        total = int(self.offsets[-1])
        self.frames = torch.empty((total, *IMAGE_SHAPE), dtype=torch.uint8)
        view = self.frames.numpy()
        for i, ep in enumerate(episodes):
            first = starts[i]
            view[self.offsets[i] : self.offsets[i + 1]] = ep.frames[first : first + self._eps[i].n]
        self._resized: dict[int, torch.Tensor] = {}

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state.pop("frames", None)
        state.pop("_resized", None)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._load()

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def arrays(self, i: int) -> _Arrays:
        return self._eps[i]

    def cat(self, field: str) -> np.ndarray:
        """One per-step field of every episode, concatenated in global step order."""
        return np.concatenate([getattr(a, field) for a in self._eps]) if self._eps else np.zeros(0)

    def resized(self, size: int) -> torch.Tensor:
        """All frames area-resized to size × size (computed once, in chunks, then cached)."""
        if size not in self._resized:
            if size == IMAGE_SHAPE[0]:
                self._resized[size] = self.frames
            else:
                out = torch.empty((len(self), size, size, 3), dtype=torch.uint8)
                for s in range(0, len(self), 1024):
                    out[s : s + 1024] = _area_resize(self.frames[s : s + 1024], size)
                self._resized[size] = out
        return self._resized[size]


class WindowDataset(Dataset):
    """One item per start step t with at least one future step (t + 1 < n).

    Fields (torch tensors): image uint8 (96,96,3) frame t; speed (1,) m/s at t;
    expert_actions (H,2) a*_t..a*_{t+H−1}; actions (H,2) executed a_t..a_{t+H−1};
    future_images uint8 (H,P,P,3) frames t+1..t+H (area-resized to P); future_speeds (H,1);
    collisions (H,) the labels c of t+1..t+H; mask (H,) 1 where step t+1+k exists;
    action_mask (H,) 1 where step t+k exists (one more than mask at an episode's end).
    Past an episode's end every field repeats its last real row; the masks say so.
    collision_free_only keeps the starts whose c_t and window labels are all 0.
    takeovers_as_collisions: `collisions` is also 1 in the 0.5 s before each take-over (the
    paper counts the person's e-stop as a collision; drives where the person always takes over
    in time hold their near-crashes only as take-overs). TrainingConfig says why it is off.

    get_batch(items) builds a whole batch by tensor indexing (the trainer's fast path, no
    DataLoader); dataset[i] is get_batch([i]) without the batch dimension. Datasets over the
    same episodes should share one FrameStore (store=), or each holds its own copy in RAM.
    """

    fields = (
        "image", "speed", "expert_actions", "actions", "future_images", "future_speeds",
        "collisions", "mask", "action_mask",
    )  # fmt: skip

    def __init__(
        self,
        episodes: Sequence[Episode],
        horizon: int = HORIZON,
        *,
        predict_size: int = 16,
        collision_free_only: bool = False,
        takeovers_as_collisions: bool = False,
        store: FrameStore | None = None,
    ) -> None:
        self.takeovers_as_collisions = takeovers_as_collisions
        self.horizon = int(horizon)
        self.predict_size = int(predict_size)
        self.collision_free_only = collision_free_only
        self.names = [ep.name for ep in episodes]
        self.store = store if store is not None else FrameStore(episodes)
        if len(self.store.paths) != len(episodes):
            raise ValueError("store= holds other episodes than the ones given")
        self._eps = self.store._eps
        self.index = self._build_index()
        self._globals()

    def _starts(self, a: _Arrays) -> range:
        return range(a.n - 1)

    def _keep(self, a: _Arrays, t: int) -> bool:
        return not (self.collision_free_only and a.collision[t : t + 1 + self.horizon].any())

    def _build_index(self) -> np.ndarray:
        index = [
            (i, t) for i, a in enumerate(self._eps) for t in self._starts(a) if self._keep(a, t)
        ]
        return np.asarray(index, dtype=np.int64).reshape(-1, 2)

    def _globals(self) -> None:
        s = self.store
        self._speed = torch.from_numpy(s.cat("speed").astype(np.float32))
        self._expert = torch.from_numpy(s.cat("expert").astype(np.float32).reshape(-1, 2))
        self._executed = torch.from_numpy(s.cat("executed").astype(np.float32).reshape(-1, 2))
        labels = s.cat("collision").astype(np.float32)
        if self.takeovers_as_collisions:
            labels = np.maximum(labels, s.cat("takeover").astype(np.float32))
        self._collision = torch.from_numpy(labels)
        self._start = torch.from_numpy(s.offsets[self.index[:, 0]] + self.index[:, 1])
        self._end = torch.from_numpy(s.offsets[self.index[:, 0] + 1] - 1)  # last step

    def __len__(self) -> int:
        return len(self.index)

    def step_labels(self) -> np.ndarray:
        """Every step's collision label as this dataset reads it (for class weights)."""
        return self._collision.numpy()

    def _steps(self, items) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(start (B,), end (B,), t+k (B,H) clamped at the episode's last step), global steps."""
        rows = torch.as_tensor(np.asarray(items, dtype=np.int64).reshape(-1))
        start, end = self._start[rows], self._end[rows]
        now = torch.minimum(start[:, None] + torch.arange(self.horizon), end[:, None])
        return start, end, now

    def get_batch(self, items: Sequence[int] | np.ndarray) -> dict[str, torch.Tensor]:
        """The batch of the given item numbers, built by tensor indexing."""
        start, end, now = self._steps(items)
        ks = torch.arange(self.horizon)
        future = torch.minimum(start[:, None] + 1 + ks, end[:, None])
        batch = {
            "image": self.store.frames[start],
            "speed": self._speed[start][:, None],
            "expert_actions": self._expert[now],
            "action_mask": (start[:, None] + ks <= end[:, None]).float(),
        }
        if "actions" in self.fields:
            small = self.store.resized(self.predict_size)
            batch.update(
                actions=self._executed[now],
                future_images=small[future],
                future_speeds=self._speed[future][..., None],
                collisions=self._collision[future],
                mask=(start[:, None] + 1 + ks <= end[:, None]).float(),
            )
        return batch

    def __getitem__(self, item: int) -> dict[str, torch.Tensor]:
        return {k: v[0] for k, v in self.get_batch([int(item)]).items()}


class ImitationDataset(WindowDataset):
    """Imitation's data: frame t, speed t and the person's next H commands, nothing else.

    Only a* that a person (or the scripted expert playing one) gave are targets: steps in mode
    MANUAL. In AUTO the sticks are untouched and a* would teach "do nothing"; after an e-stop
    the car is DISARMED. A take-over in AUTO (override) switches the mode to MANUAL, so the
    person's commands on states the policy itself reached are targets too, weighted by
    intervention_weight. Every start t with a* label counts, the episode's last step included;
    no future frames are read. `weight` (H,) is the per-step target weight, 0 where there is
    no label (past the end, not MANUAL).
    """

    fields = ("image", "speed", "expert_actions", "action_mask", "weight")

    def __init__(
        self,
        episodes: Sequence[Episode],
        horizon: int = HORIZON,
        *,
        collision_free_only: bool = True,
        intervention_weight: float = 1.0,
        store: FrameStore | None = None,
    ) -> None:
        self.intervention_weight = float(intervention_weight)
        super().__init__(
            episodes, horizon, predict_size=IMAGE_SHAPE[0],
            collision_free_only=collision_free_only, store=store,
        )  # fmt: skip
        w = self.store.cat("label").astype(np.float32)
        w[self.store.cat("intervention").astype(bool)] *= self.intervention_weight
        self._weight = torch.from_numpy(w)

    def _starts(self, a: _Arrays) -> range:
        return range(a.n)

    def _keep(self, a: _Arrays, t: int) -> bool:
        return bool(a.label[t]) and super()._keep(a, t)

    @property
    def interventions(self) -> int:
        """Start steps that are a person's take-over from the policy."""
        return int(sum(self._eps[i].intervention[t] for i, t in self.index))

    def get_batch(self, items) -> dict[str, torch.Tensor]:
        batch = super().get_batch(items)
        batch["weight"] = self._weight[self._steps(items)[2]] * batch["action_mask"]
        return batch


def take(dataset: Dataset, items: Iterable[int]) -> dict[str, torch.Tensor]:
    """A batch of the given items: the dataset's get_batch when it has one, else collated."""
    items = list(items)
    if hasattr(dataset, "get_batch"):
        return dataset.get_batch(items)
    return default_collate([dataset[i] for i in items])


__all__ = [
    "FrameStore", "ImitationDataset", "Normalisation", "WindowDataset", "compute_normalisation",
    "data_digest", "load_episodes", "placement_key", "split_by_episode", "split_by_placement",
    "take",
]  # fmt: skip
