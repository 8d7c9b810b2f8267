"""Which episodes training reads, and which of them train and which validate.

Reading checks every record's CRC (a flipped byte must not reach a batch). Validation holds out
whole placements (the obstacle layout a recording session drove), because episodes of one
placement are near-duplicates and would measure memorisation; the digest names the exact
episode set a policy was trained on (it goes into the checkpoint and the ONNX metadata).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Iterable, Sequence

from carrt.episodes.marks import apply_marks
from carrt.episodes.reader import Episode, list_episodes, read_episode

log = logging.getLogger("training.data")  # the name users and tests already filter on


def load_episodes(paths: str | os.PathLike | Iterable[str | os.PathLike]) -> list[Episode]:
    """Every episode under the given episode directories or directories of them, by name.
    Episodes with no steps (a run that died before its first frame) are left out.

    Every record's CRC is checked, not only the unsynced tail the car's reader checks: a byte
    flipped on disk or in a copy would otherwise reach training unnoticed. An episode is cut
    before its first damaged record, and the cut is logged."""
    episodes, excluded, marked = [], 0, 0
    for path in list_episodes(paths):
        ep = read_episode(path, verify_all=True)
        recorded = int((ep.meta.get("counts") or {}).get("steps", ep.n))
        if ep.n < recorded:
            log.warning(
                "%s: record %d fails its CRC: training uses the %d records before it of %d",
                ep.name, ep.n, ep.n, recorded,
            )  # fmt: skip
        if ep.n == 0:
            continue
        kept = apply_marks(ep)
        cut = ep.n - sum(part.n for part in kept)
        excluded, marked = excluded + cut, marked + (cut > 0)
        episodes.extend(kept)
    if excluded:
        log.info("marks: %d steps of %d episodes left out of training", excluded, marked)
    return episodes


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


def placement_key(ep: Episode) -> str:
    """The obstacle placement an episode was driven on; episodes sharing it are near-duplicates.

    An explicit meta["placement"] wins; a simulator recording names its layout and track seed
    (meta["sim"], written by `carrt teleop/drive --sim`); on a real car one recording session
    is one placement of the obstacles (meta["session_id"], when the session writes one).
    Without any of these the episode is its own placement, the old per-episode split.
    """
    meta = ep.meta or {}
    if meta.get("placement") is not None:
        return f"placement:{meta['placement']}"
    sim = meta.get("sim")
    if isinstance(sim, dict) and sim.get("track_seed") is not None:
        return f"sim:{sim.get('layout')}:{sim['track_seed']}"
    if meta.get("session_id") is not None:
        return f"session:{meta['session_id']}"
    return f"episode:{ep.name}"


def split_by_placement(
    episodes: Sequence[Episode], val_fraction: float, seed: int
) -> tuple[list[Episode], list[Episode]]:
    """(train, val) with whole placements held out (placement_key), so the held-out loss
    measures driving past obstacles the policy has never seen, not frames next to ones it
    trained on: episodes of one placement are near-duplicates of each other.

    val_fraction is a share of the placements, ranked by a seeded hash of their key (stable as
    data is added). With a single placement there is nothing to hold out by placement, and the
    split falls back to whole episodes (split_by_episode).
    """
    keys = [placement_key(ep) for ep in episodes]
    groups = sorted(set(keys))
    if len(groups) < 2:
        return split_by_episode(episodes, val_fraction, seed)
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    n_val = round(len(groups) * val_fraction)
    if val_fraction > 0:
        n_val = min(max(n_val, 1), len(groups) - 1)
    held = set(sorted(groups, key=lambda k: _rank_key(seed, k))[:n_val])
    train = [ep for ep, k in zip(episodes, keys, strict=True) if k not in held]
    val = [ep for ep, k in zip(episodes, keys, strict=True) if k in held]
    return train, val


def data_digest(episodes: Sequence[Episode]) -> str:
    """sha256 over the episodes' names, step counts and metadata, independent of their order:
    it names a training set (in checkpoints and exported models) without hashing gigabytes."""
    h = hashlib.sha256(b"carrt.data/1\n")
    for ep in sorted(episodes, key=lambda e: e.name):
        h.update(json.dumps([ep.name, int(ep.n), ep.meta], sort_keys=True, default=str).encode())
        h.update(b"\n")
    return h.hexdigest()
