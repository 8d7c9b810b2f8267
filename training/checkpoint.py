"""Checkpoints: one torch.save'd dict that holds everything needed to resume or export a run.

A checkpoint is the unit of trust between the stages, iteration.py's resume, and export/: the
config that produced it, the weights, the optimiser state, the step, and the data it was
trained on (digest + episode list), so a later iteration or an exported ONNX file can say where
it came from. Writes are atomic (tmp file + os.replace): a run killed mid-write leaves the
previous checkpoint intact, never a torn file that the resume would choke on.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from carrt.errors import UserError
from carrt.version import code_version  # noqa: F401 - checkpoints carry it

# /2: the policy's throttle head is tanh over [-1, 1] (it can brake) and the cpu profile's
# backbone is 16 wide. A /1 policy would load into /2 code and silently drive differently
# (sigmoid weights read through tanh), so /1 files are refused with a line saying why.
FORMAT = "carrt.checkpoint/2"
STAGES = ("imitation", "world_model", "refine")
REQUIRED = (
    "config",
    "profile",
    "stage",
    "step",
    "policy",
    "world_model",
    "optimizer",
    "normalisation",
    "data_digest",
    "iteration",
    "code_version",
    "episodes",
)


class CheckpointError(UserError, ValueError):
    """The file is not a carrt checkpoint, or lacks a field; the message says which (a
    UserError like every bad input: one line, exit 2)."""


def save_checkpoint(path: str | os.PathLike, **fields: Any) -> None:
    """Write the checkpoint atomically. Extra fields (e.g. a loss history) are kept as given."""
    missing = [k for k in REQUIRED if k not in fields]
    if missing:
        raise CheckpointError(f"checkpoint {path}: missing fields {', '.join(missing)}")
    if fields["stage"] not in STAGES:
        raise CheckpointError(f"checkpoint {path}: unknown stage {fields['stage']!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        torch.save({"format": FORMAT, **fields}, tmp)
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def load_checkpoint(path: str | os.PathLike) -> dict:
    """Read a checkpoint onto the CPU; raise CheckpointError naming what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path}: no such file")
    try:
        # weights_only: a checkpoint is data; it must never run code when loaded.
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise CheckpointError(f"checkpoint {path}: unreadable ({exc})") from exc
    if isinstance(ckpt, dict) and ckpt.get("format") == "carrt.checkpoint/1":
        raise CheckpointError(
            f"checkpoint {path}: carrt.checkpoint/1, from before the policy could brake "
            "(throttle head and cpu profile changed): train it again"
        )
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise CheckpointError(f"checkpoint {path}: not a {FORMAT} file")
    missing = [k for k in REQUIRED if k not in ckpt]
    if missing:
        raise CheckpointError(f"checkpoint {path}: missing fields {', '.join(missing)}")
    return ckpt


def resumable(ckpt_dir: Path, targets: dict[str, int], *, profile: str, digest: str) -> dict:
    """The stage checkpoints a rerun of the same command resumes from, by stage.

    targets maps the run's stages, in order, to their configured steps. Checkpoints count up
    to the first unfinished stage: a later stage's checkpoint was trained on top of an earlier
    stage's end (before its steps were raised with --set, say), so it is stale, ignored, and
    overwritten when that stage runs. A run over another profile or other data is refused.
    """
    found: dict[str, dict] = {}
    for stage, steps in targets.items():
        path = Path(ckpt_dir) / f"{stage}.pt"
        if not path.is_file():
            if steps == 0:  # a skipped stage writes no checkpoint
                continue
            break
        ckpt = load_checkpoint(path)
        if ckpt["profile"] != profile or ckpt["data_digest"] != digest:
            what = f"profile {ckpt['profile']}" if ckpt["profile"] != profile else "other episodes"
            raise CheckpointError(
                f"{Path(ckpt_dir).parent} holds a run with {what}; use a new --out to start over"
            )
        found[stage] = ckpt
        if ckpt["step"] < steps:
            break
    return found


def profile_of(ckpt: dict):
    """The model sizes a checkpoint was trained with: its own copy of the profile's fields
    (`profile_fields`, written since the profiles could change under old files), else the
    profile of that name (older checkpoints)."""
    from training.profiles import Profile, get_profile

    fields = ckpt.get("profile_fields")
    if fields:
        return Profile(**fields)
    return get_profile(ckpt["profile"])


def load_policy(path: str | os.PathLike):
    """The checkpoint's PolicyNet (with its normalisation) in eval mode, and the checkpoint."""
    from training.data import Normalisation
    from training.models import PolicyNet

    ckpt = load_checkpoint(path)
    policy = PolicyNet(profile_of(ckpt))
    policy.set_normalisation(Normalisation.from_dict(ckpt["normalisation"]))
    policy.load_state_dict(ckpt["policy"])
    policy.eval()
    return policy, ckpt


def load_world_model(path: str | os.PathLike):
    """The checkpoint's WorldModel in eval mode, and the checkpoint (for evaluation, figures)."""
    from training.data import Normalisation
    from training.models import WorldModel

    ckpt = load_checkpoint(path)
    if ckpt["world_model"] is None:
        raise CheckpointError(f"checkpoint {path}: holds no world model")
    model = WorldModel(profile_of(ckpt))
    model.set_normalisation(Normalisation.from_dict(ckpt["normalisation"]))
    model.load_state_dict(ckpt["world_model"])
    model.eval()
    return model, ckpt
