"""Does the ONNX file compute what the PyTorch policy computes, on frames the car really sees?

Random tensors are the wrong test input: a uint8 cast, a normalisation constant or a channel
order that is wrong shows up on real camera frames (and real speeds) and can hide in noise.
So every comparison here runs on frames read from recorded episodes with carrt's own reader,
the same bytes the car feeds the model.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from carrt import model_contract as mc
from carrt.episodes.reader import list_episodes, read_episode
from carrt.errors import UserError

CPU = "CPUExecutionProvider"


@dataclass
class Frames:
    """A sample of recorded observations: what the policy is fed, and where each came from."""

    images: np.ndarray  # (N, 96, 96, 3) uint8
    speeds: np.ndarray  # (N, 1) float32, m/s
    episode: np.ndarray  # (N,) index into `episodes`
    episodes: list[str]  # episode names

    def __len__(self) -> int:
        return len(self.images)

    def subset(self, mask: np.ndarray) -> Frames:
        return Frames(self.images[mask], self.speeds[mask], self.episode[mask], self.episodes)

    def split_held_out(self) -> tuple[Frames, Frames]:
        """(calibration, held_out), split by episode so no held-out frame has a neighbour
        (a near-duplicate at 10 Hz) in the calibration set; by frame when only one episode."""
        present = np.unique(self.episode)
        if len(present) >= 2:
            calibration = np.isin(self.episode, present[::2])
        else:
            calibration = np.arange(len(self)) % 2 == 0
        return self.subset(calibration), self.subset(~calibration)


def sample_frames(
    episode_dirs: Sequence[str | os.PathLike[str]],
    *,
    max_frames: int = 256,
    seed: int = 0,
    avoid: Iterable[str] = (),
) -> Frames:
    """Up to max_frames (frame, speed) pairs spread over the given episodes.

    `avoid`: episode names (or paths) the policy was trained on; they are left out while other
    episodes remain, so the comparison is on held-out-style data. Raises UserError when there
    are no episodes or no frames: parity without real frames would prove nothing.
    """
    if not episode_dirs:
        raise UserError(
            "export needs recorded episodes (--episodes DIR): parity and calibration run on "
            "real frames, not random tensors"
        )
    paths = list_episodes([Path(p) for p in episode_dirs])
    avoid_names = {Path(a).name for a in avoid}
    unseen = [p for p in paths if p.name not in avoid_names]
    episodes = [read_episode(p) for p in (unseen or paths)]
    episodes = [ep for ep in episodes if ep.n > 0]
    if not episodes:
        raise UserError(f"no frames in the episodes given ({', '.join(map(str, episode_dirs))})")
    index = np.concatenate(
        [np.stack([np.full(ep.n, i), np.arange(ep.n)], 1) for i, ep in enumerate(episodes)]
    )
    if len(index) > max_frames:
        rng = np.random.default_rng(seed)
        index = index[np.sort(rng.choice(len(index), max_frames, replace=False))]
    images = np.stack([episodes[e].frames[t] for e, t in index]).astype(np.uint8, copy=False)
    speeds = np.array([[episodes[e].steps["speed_mps"][t]] for e, t in index], np.float32)
    return Frames(images, speeds, index[:, 0].copy(), [ep.name for ep in episodes])


# ----------------------------------------------------------------------------- running models
def torch_outputs(policy, frames: Frames, batch: int = 64) -> tuple[np.ndarray, np.ndarray]:
    import torch

    mus, sigmas = [], []
    with torch.inference_mode():
        for i in range(0, len(frames), batch):
            image = torch.from_numpy(np.ascontiguousarray(frames.images[i : i + batch]))
            speed = torch.from_numpy(np.ascontiguousarray(frames.speeds[i : i + batch]))
            mu, sigma = policy(image, speed)
            mus.append(mu.float().cpu().numpy())
            sigmas.append(sigma.float().cpu().numpy())
    return np.concatenate(mus), np.concatenate(sigmas)


def ort_session(model: str | os.PathLike[str] | bytes, providers: Sequence[str] = (CPU,)):
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.log_severity_level = 3
    source = model if isinstance(model, bytes) else str(model)
    return ort.InferenceSession(source, options, providers=list(providers))


def ort_outputs(session, frames: Frames, batch: int = 64) -> tuple[np.ndarray, np.ndarray]:
    mus, sigmas = [], []
    for i in range(0, len(frames), batch):
        feeds = {
            mc.INPUT_IMAGE: np.ascontiguousarray(frames.images[i : i + batch]),
            mc.INPUT_SPEED: np.ascontiguousarray(frames.speeds[i : i + batch]),
        }
        mu, sigma = session.run([mc.OUTPUT_MU, mc.OUTPUT_SIGMA], feeds)
        mus.append(np.asarray(mu, np.float32))
        sigmas.append(np.asarray(sigma, np.float32))
    return np.concatenate(mus), np.concatenate(sigmas)


# ----------------------------------------------------------------------------- comparing
@dataclass(frozen=True)
class Parity:
    """Absolute differences between a reference (PyTorch) and a candidate (onnxruntime)."""

    frames: int
    max_abs_mu: float
    mean_abs_mu: float
    max_abs_sigma: float
    mean_abs_sigma: float
    tolerance: float

    @property
    def ok(self) -> bool:
        # NaN compares False: a model that answers NaN never passes.
        return bool(self.max_abs_mu <= self.tolerance and self.max_abs_sigma <= self.tolerance)

    def render(self) -> str:
        return (
            f"{self.frames} frames: mu max {self.max_abs_mu:.2e} mean {self.mean_abs_mu:.2e}, "
            f"sigma max {self.max_abs_sigma:.2e} mean {self.mean_abs_sigma:.2e} "
            f"(tolerance {self.tolerance:g})"
        )

    def as_dict(self) -> dict:
        return {**self.__dict__, "ok": self.ok}


def _abs_err(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    if a.shape != b.shape:
        raise ValueError(f"output shapes differ: {list(a.shape)} vs {list(b.shape)}")
    err = np.abs(a.astype(np.float64) - b.astype(np.float64))
    return np.where(np.isfinite(err), err, np.inf)


def compare(
    reference: tuple[np.ndarray, np.ndarray],
    candidate: tuple[np.ndarray, np.ndarray],
    tolerance: float,
) -> Parity:
    mu, sigma = _abs_err(reference[0], candidate[0]), _abs_err(reference[1], candidate[1])
    return Parity(
        frames=len(mu),
        max_abs_mu=float(mu.max()),
        mean_abs_mu=float(mu.mean()),
        max_abs_sigma=float(sigma.max()),
        mean_abs_sigma=float(sigma.mean()),
        tolerance=float(tolerance),
    )


def check_parity(
    policy, model: str | os.PathLike[str] | bytes, frames: Frames, tolerance: float
) -> Parity:
    """PyTorch against onnxruntime (CPU) on `frames`, worst case over two batch shapes.

    Batch 1 is how the car runs it; batched runs prove the batch axis is really dynamic
    (a traced reshape that baked in the export's batch size shows up here, not on the car).
    """
    reference = torch_outputs(policy, frames)
    session = ort_session(model)
    batched = ort_outputs(session, frames, batch=64)
    single = ort_outputs(session, frames, batch=1)
    a, b = compare(reference, batched, tolerance), compare(reference, single, tolerance)
    worst = Parity(
        frames=len(frames),
        max_abs_mu=max(a.max_abs_mu, b.max_abs_mu),
        mean_abs_mu=max(a.mean_abs_mu, b.mean_abs_mu),
        max_abs_sigma=max(a.max_abs_sigma, b.max_abs_sigma),
        mean_abs_sigma=max(a.mean_abs_sigma, b.mean_abs_sigma),
        tolerance=float(tolerance),
    )
    return worst
