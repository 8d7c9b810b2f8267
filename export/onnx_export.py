"""The trained policy as one ONNX file that carrt will accept and that computes what PyTorch did.

Only the policy leaves training: the world model stays behind (docs/training.md#export). The file is
written under a temporary name and renamed into place only after it has passed, in this order: the
ONNX checker, a no-external-data check, parity with PyTorch on recorded frames, and carrt's own
loader (model_contract + OnnxPolicy + a warm-up). A file at out_path therefore always is a model the
car accepts; a refused export leaves whatever was there before untouched.
"""

from __future__ import annotations

import io
import json
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import onnx

import carrt
from carrt import model_contract as mc
from carrt.errors import UserError
from carrt.policy import file_sha256
from carrt.version import code_version
from export.graph import (
    OPSET,
    ExportRefused,
    carrt_accepts,
    check_structure,
    declare_outputs,
    positive_perms,
    set_metadata,
    write_checked,
)
from export.parity import Frames, Parity, check_parity, sample_frames
from firmware_bridge.timing import CONTROL_PERIOD_S

DEFAULT_TOLERANCE = 1e-4  # fp32 PyTorch vs onnxruntime, absolute, on mu and sigma
DEFAULT_MAX_FRAMES = 256


@dataclass
class ExportReport:
    path: Path
    size_bytes: int
    sha256: str
    metadata: dict[str, str]
    parity: Parity
    exporter: str
    variants: dict[str, Any] = field(default_factory=dict)  # name -> quantize.VariantReport
    notes: list[str] = field(default_factory=list)

    def render(self) -> list[str]:
        lines = [
            f"wrote {self.path} ({self.size_bytes:,} bytes, sha256 {self.sha256[:16]}…)",
            f"  horizon {self.metadata['carrt.horizon']}, iteration "
            f"{self.metadata['carrt.iteration']}, exporter {self.exporter}",
            f"  parity (PyTorch vs onnxruntime CPU): {self.parity.render()}",
        ]
        lines += [f"  {v.render()}" for v in self.variants.values()]
        lines += [f"  note: {n}" for n in self.notes]
        return lines

    def as_dict(self) -> dict:
        return {
            "path": str(self.path),
            "size_bytes": self.size_bytes,
            "sha256": self.sha256,
            "metadata": self.metadata,
            "parity": self.parity.as_dict(),
            "exporter": self.exporter,
            "variants": {k: v.as_dict() for k, v in self.variants.items()},
            "notes": self.notes,
        }


# ----------------------------------------------------------------------------- checkpoint
def load_checkpoint_policy(path: str | os.PathLike[str]):
    """(PolicyNet in eval mode on the CPU, checkpoint dict). UserError when it cannot be read."""
    path = Path(path)
    if not path.is_file():  # before importing torch: a typo should answer at once
        raise UserError(f"checkpoint {path}: no such file")
    try:
        from training.checkpoint import CheckpointError, load_policy
    except ImportError as exc:
        raise UserError(
            f"export needs the training package ({exc}); install with pip install -e '.[train]'"
        ) from exc
    try:
        policy, ckpt = load_policy(path)
    except CheckpointError as exc:  # its message already names the file and the problem
        raise UserError(str(exc)) from exc
    except (KeyError, TypeError, ValueError, RuntimeError, OSError, EOFError) as exc:
        text = " ".join(str(exc).split())[:200]
        raise UserError(
            f"checkpoint {path}: cannot load a policy ({type(exc).__name__}: {text})"
        ) from exc
    if not isinstance(ckpt, dict):
        raise UserError(f"checkpoint {path}: not a carrt checkpoint (a {type(ckpt).__name__})")
    return policy.cpu().float().eval(), ckpt


# ----------------------------------------------------------------------------- metadata
def build_metadata(ckpt: dict, horizon: int, exporter: str) -> dict[str, str]:
    digest = str(ckpt.get("data_digest") or "")
    if not digest:
        raise ExportRefused(
            "checkpoint has no data_digest: the car records which data a policy was trained "
            "on, and this one cannot say"
        )
    meta = {
        "carrt.schema": mc.SCHEMA,
        "carrt.horizon": str(horizon),
        "carrt.control_period_s": str(CONTROL_PERIOD_S),
        "carrt.image_shape": ",".join(str(d) for d in mc.IMAGE_SHAPE),
        "carrt.action_names": ",".join(mc.ACTION_NAMES),
        "carrt.action_low": ",".join(str(x) for x in mc.ACTION_LOW),
        "carrt.action_high": ",".join(str(x) for x in mc.ACTION_HIGH),
        "carrt.speed_units": "m/s",
        "carrt.training_data_digest": digest,
        "carrt.iteration": str(int(ckpt.get("iteration", 0))),
        "carrt.code_version": code_version(),
        # Not required by the contract; what a bug report about this file needs.
        "carrt.variant": "fp32",
        "carrt.profile": str(ckpt.get("profile", "")),
        "carrt.stage": str(ckpt.get("stage", "")),
        "carrt.step": str(ckpt.get("step", "")),
        "carrt.training_code_version": str(ckpt.get("code_version", "")),
        "carrt.exporter": exporter,
    }
    if ckpt.get("sim_placements"):  # the simulator's placements it trained on: carrt eval warns
        meta[mc.SIM_PLACEMENTS] = json.dumps(ckpt["sim_placements"], separators=(",", ":"))
    mc.validate_metadata(meta, CONTROL_PERIOD_S)
    return meta


# ----------------------------------------------------------------------------- graph
def torch_to_onnx(policy, example: Frames) -> tuple[onnx.ModelProto, str]:
    """Trace the policy with a real (uint8 frame, speed) batch; dynamic batch axis, opset 17.

    The TorchScript-based exporter is used when this torch still has it: it writes one
    protobuf with the weights inside and needs nothing beyond torch. The torch.export-based
    one (needs onnxscript) is the fallback.
    """
    import torch

    args = (torch.from_numpy(example.images[:2].copy()), torch.from_numpy(example.speeds[:2]))
    names = {"input_names": [mc.INPUT_IMAGE, mc.INPUT_SPEED]}
    names["output_names"] = [mc.OUTPUT_MU, mc.OUTPUT_SIGMA]
    axes = {n: {0: "N"} for n in (*names["input_names"], *names["output_names"])}
    buffer = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the legacy exporter's deprecation notice
        try:
            torch.onnx.export(
                policy, args, buffer, dynamo=False, opset_version=OPSET,
                dynamic_axes=axes, do_constant_folding=True, **names,
            )  # fmt: skip
            exporter = f"torch {torch.__version__} torchscript"
        except TypeError:  # a torch without the legacy switch, or without the legacy exporter
            buffer = io.BytesIO()
            try:
                program = torch.onnx.export(
                    policy, args, None, dynamo=True, opset_version=OPSET,
                    dynamic_axes=axes, external_data=False, **names,
                )  # fmt: skip
            except ImportError as exc:
                raise ExportRefused(f"torch.onnx needs {exc.name or 'onnxscript'}") from exc
            buffer.write(program.model_proto.SerializeToString())
            exporter = f"torch {torch.__version__} dynamo"
    model = onnx.load_from_string(buffer.getvalue())
    positive_perms(model.graph)
    model.producer_name = "carrt.export"
    model.producer_version = carrt.__version__
    return model, exporter


def variant_path(out: Path, variant: str) -> Path:
    """policy.onnx -> policy.int8.onnx (what `carrt drive --model` gets on a weak board)."""
    stem = out.name[: -len(".onnx")] if out.name.endswith(".onnx") else out.name
    return out.with_name(f"{stem}.{variant}.onnx")


# ----------------------------------------------------------------------------- the whole export
def export_policy(
    checkpoint_path: str | os.PathLike[str],
    out_path: str | os.PathLike[str],
    episodes: list[str],
    *,
    int8: bool = False,
    fp16: bool = False,
    tolerance: float = DEFAULT_TOLERANCE,
    max_frames: int = DEFAULT_MAX_FRAMES,
    max_mean_mu_error: float = 0.05,
    max_abs_mu_error: float = 0.2,
    int8_symmetric: bool = False,
    seed: int = 0,
) -> ExportReport:
    """Export the checkpoint's policy to out_path (and optional weak-board variants beside it).

    Raises UserError for unusable inputs (no checkpoint, no episodes) and ExportRefused (a
    UserError) when the model fails a check; in both cases nothing is written at out_path.
    A refused int8/fp16 variant does not fail the export: it is reported and not written.
    int8_symmetric: zero-point-0 activations, for TensorRT's explicit quantisation (the
    default suits onnxruntime's CPU kernels).
    """
    from export import quantize

    if not (np.isfinite(tolerance) and tolerance >= 0):
        raise UserError(f"tolerance must be a finite number >= 0, got {tolerance}")
    out = Path(out_path)
    policy, ckpt = load_checkpoint_policy(checkpoint_path)
    frames = sample_frames(
        episodes, max_frames=max_frames, seed=seed, avoid=ckpt.get("episodes") or ()
    )

    model, exporter = torch_to_onnx(policy, frames)
    horizon = _horizon(policy, frames)
    declare_outputs(model, horizon)
    meta = build_metadata(ckpt, horizon, exporter)
    meta["carrt.checkpoint_sha256"] = file_sha256(Path(checkpoint_path))
    set_metadata(model, meta)
    check_structure(model, horizon)

    parity = check_parity(policy, model.SerializeToString(), frames, tolerance)
    if not parity.ok:
        raise ExportRefused(
            f"ONNX output differs from PyTorch beyond tolerance on {parity.render()}; "
            f"nothing written to {out}"
        )
    meta["carrt.parity_max_abs_mu"] = f"{parity.max_abs_mu:.3g}"
    meta["carrt.parity_max_abs_sigma"] = f"{parity.max_abs_sigma:.3g}"
    set_metadata(model, meta)
    size = write_checked(model, out, carrt_accepts)
    report = ExportReport(out, size, file_sha256(out), meta, parity, exporter)

    bounds = quantize.Bounds(max_mean_mu_error, max_abs_mu_error)
    makers = {
        "int8": lambda path: quantize.int8_variant(
            model, frames, path, bounds, horizon, symmetric=int8_symmetric
        ),
        "fp16": lambda path: quantize.fp16_variant(model, frames, path, bounds, horizon),
    }
    wanted = {"int8": int8, "fp16": fp16}
    for name, make in makers.items():
        path = variant_path(out, name)
        if wanted[name]:
            try:
                report.variants[name] = make(path)
            except Exception as exc:  # the fp32 file is in place and valid: report, go on
                why = f"failed: {type(exc).__name__}: {' '.join(str(exc).split())[:200]}"
                report.variants[name] = quantize.VariantReport(name, path, False, why)
        if not (wanted[name] and report.variants[name].written) and path.exists():
            # A variant left from an earlier export would be a different policy under a
            # name that says it is this one.
            path.unlink()
            report.notes.append(f"removed {path.name} from an earlier export (not rewritten)")
    return report


def _horizon(policy, frames: Frames) -> int:
    import torch

    with torch.inference_mode():
        mu, sigma = policy(torch.from_numpy(frames.images[:1].copy()),
                           torch.from_numpy(frames.speeds[:1]))  # fmt: skip
    if mu.ndim != 3 or mu.shape[2] != 2 or tuple(sigma.shape) != tuple(mu.shape):
        raise ExportRefused(
            f"policy outputs mu {list(mu.shape)} and sigma {list(sigma.shape)}, expected [N, H, 2]"
        )
    return int(mu.shape[1])
