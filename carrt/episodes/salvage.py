"""Salvage: the intact steps of a damaged episode, into a new episode beside the old.

`carrt episodes show --verify` reports damage inside the durable steps (a flipped bit on the
card, a bad copy) and training reads such an episode only up to the damage. Every record
carries its own CRC over itself and its frame, so the steps after the damage that still pass
theirs are whole too: `carrt episodes salvage EP -o DIR` writes the prefix and those steps, in
order, as a new episode (records renumbered, CRCs recomputed, the gap said in its metadata).
The damaged episode is left as it is.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from carrt.episodes import format as fmt
from carrt.episodes.reader import Episode, intact_records, read_episode
from carrt.errors import UserError


def intact_steps(path: Path, ep: Episode) -> tuple[np.ndarray, np.ndarray, int]:
    """(records, frames, total) of the steps before the damage and of every later record that
    passes its own checks, by the reader's rule (`intact_records`, which Damage counts too)."""
    dtype = ep.steps.dtype
    steps_size = (path / fmt.STEPS).stat().st_size
    frames_size = (path / fmt.FRAMES).stat().st_size
    total = min(steps_size // dtype.itemsize, frames_size // fmt.FRAME_BYTES)
    if total == 0:
        raise UserError(f"{path}: no whole record to salvage")
    raw = np.fromfile(path / fmt.STEPS, dtype=dtype, count=total)
    frames = np.memmap(path / fmt.FRAMES, dtype=np.uint8, mode="r", shape=(total, fmt.FRAME_BYTES))
    cut = ep.damage.step  # read up to here; that record fails its checks
    keep = [*range(cut), *intact_records(raw, frames, cut + 1, total, dtype)]
    return raw[keep], np.asarray(frames[keep]), total


def salvage(path: str | Path, out_dir: str | Path) -> tuple[Path, int, int]:
    """The new episode's path, the steps kept and the steps the old one had."""
    path = Path(path)
    ep = read_episode(path, verify_all=True)
    if ep.damage is None:
        raise UserError(f"{path}: no damage inside its durable steps: nothing to salvage")
    records, frames, total = intact_steps(path, ep)
    out = Path(out_dir) / f"{path.name}-salvaged"
    if out.exists():
        raise UserError(f"{out} exists: salvage into another -o")
    out.mkdir(parents=True)
    meta = dict(ep.meta)
    meta["counts"] = {**(meta.get("counts") or {}), "steps": len(records)}
    meta["salvaged"] = {"from": str(path), "steps_kept": len(records), "steps_in": total,
                        "damaged_from_step": ep.damage.step}  # fmt: skip
    fmt.write_records(out, records, frames, meta)
    if (path / "marks.json").is_file():  # marks are in seconds: they still mean the same steps
        shutil.copy2(path / "marks.json", out / "marks.json")
    return out, len(records), total
