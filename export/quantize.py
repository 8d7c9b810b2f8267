"""Smaller, faster variants of the exported policy for boards that cannot run fp32 in 100 ms.

A quantised policy is a different policy: it is only written when its actions stay close to
the fp32 model's on frames it was not calibrated on (held-out episodes), and the measured error
travels in its metadata. Inputs and outputs keep the contract's types (uint8 image, float32
speed/mu/sigma), so carrt loads a variant exactly like the fp32 file.
"""

from __future__ import annotations

import copy
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx

import carrt
from carrt import model_contract as mc
from export.graph import (
    ExportRefused,
    carrt_accepts,
    check_structure,
    declare_outputs,
    get_metadata,
    set_metadata,
    tidy_opsets,
    topological_sort,
    write_checked,
)
from export.parity import CPU, Frames, ort_outputs, ort_session

GPU_PROVIDERS = ("TensorrtExecutionProvider", "CUDAExecutionProvider")


@dataclass(frozen=True)
class Bounds:
    """Largest action error (|mu - mu_fp32|, steering and throttle units) a variant may have."""

    max_mean_mu: float = 0.05
    max_abs_mu: float = 0.2


@dataclass
class VariantReport:
    name: str
    path: Path
    written: bool
    reason: str = ""  # why it was skipped or refused; "" when written
    skipped: bool = False  # not attempted here (no provider/tool), as opposed to refused
    held_out_frames: int = 0
    calibration_frames: int = 0
    mean_abs_mu: float = math.nan
    max_abs_mu: float = math.nan
    size_bytes: int = 0
    detail: str = ""

    def render(self) -> str:
        error = ""
        if not math.isnan(self.mean_abs_mu):
            error = (
                f"mu error vs fp32 on {self.held_out_frames} held-out frames: mean "
                f"{self.mean_abs_mu:.2e} max {self.max_abs_mu:.2e}"
            )
        if self.written:
            size = f"{self.size_bytes:,} bytes"
            return f"{self.name}: wrote {self.path} ({size}, {self.detail}); {error}"
        return f"{self.name}: {'skipped' if self.skipped else 'refused'}: {self.reason}"

    def as_dict(self) -> dict:
        return {**self.__dict__, "path": str(self.path)}


def _metadata(model: onnx.ModelProto, variant: str, extra: dict[str, str]) -> dict[str, str]:
    meta = get_metadata(model)
    meta.update({"carrt.variant": variant, **extra})
    return meta


def _errors(reference: np.ndarray, mu: np.ndarray) -> tuple[float, float]:
    err = np.abs(reference.astype(np.float64) - mu.astype(np.float64))
    err = np.where(np.isfinite(err), err, np.inf)
    return float(err.mean()), float(err.max())


def _finish(
    report: VariantReport, model: onnx.ModelProto, bounds: Bounds, horizon: int
) -> VariantReport:
    """Enforce the bounds, the structural checks and carrt's loader; write or refuse."""
    tidy_opsets(model)
    declare_outputs(model, horizon)
    model.producer_name, model.producer_version = "carrt.export", carrt.__version__

    if not (report.mean_abs_mu <= bounds.max_mean_mu and report.max_abs_mu <= bounds.max_abs_mu):
        report.reason = (
            f"mu error vs fp32 on {report.held_out_frames} held-out frames is mean "
            f"{report.mean_abs_mu:.2e} / max {report.max_abs_mu:.2e}, bound "
            f"{bounds.max_mean_mu} / {bounds.max_abs_mu}"
        )
        return report
    try:
        check_structure(model, horizon)
        report.size_bytes = write_checked(model, report.path, carrt_accepts)
    except ExportRefused as exc:
        report.reason = str(exc)
        return report
    report.written = True
    return report


# ----------------------------------------------------------------------------- int8
def _reader(frames: Frames, batch: int = 16):
    from onnxruntime.quantization import CalibrationDataReader

    class FrameReader(CalibrationDataReader):
        """Recorded frames and speeds, in the graph's own input types (uint8 stays uint8)."""

        def __init__(self) -> None:
            self.start = 0

        def get_next(self) -> dict[str, np.ndarray] | None:
            if self.start >= len(frames):
                return None
            end = self.start + batch
            feeds = {
                mc.INPUT_IMAGE: np.ascontiguousarray(frames.images[self.start : end]),
                mc.INPUT_SPEED: np.ascontiguousarray(frames.speeds[self.start : end]),
            }
            self.start = end
            return feeds

        def rewind(self) -> None:
            self.start = 0

    return FrameReader()


def _quantize(
    source: Path, target: Path, calibration: Frames, per_channel: bool, symmetric: bool
) -> None:
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    quantize_static(
        str(source),
        str(target),
        _reader(calibration),
        quant_format=QuantFormat.QDQ,
        # Conv/Gemm/MatMul carry the compute; the uint8→float normalisation, the heads'
        # tanh/sigmoid/softplus and the speed path stay float (cheap, and most sensitive).
        op_types_to_quantize=["Conv", "Gemm", "MatMul"],
        per_channel=per_channel,
        # uint8 activations with a zero point + symmetric int8 weights (U8S8) is what
        # onnxruntime's CPU kernels run fastest, and measured 5-10x closer to fp32 than
        # symmetric int8 activations, which waste half their range after each ReLU.
        # TensorRT's explicit quantisation needs zero points of 0: symmetric=True.
        activation_type=QuantType.QInt8 if symmetric else QuantType.QUInt8,
        weight_type=QuantType.QInt8,
        calibrate_method=CalibrationMethod.MinMax,
        extra_options={"ActivationSymmetric": symmetric, "WeightSymmetric": True},
    )


def int8_variant(
    model: onnx.ModelProto,
    frames: Frames,
    path: Path,
    bounds: Bounds,
    horizon: int,
    *,
    symmetric: bool = False,
) -> VariantReport:
    """Static QDQ int8, calibrated on half the episodes, judged on the other half."""
    calibration, held_out = frames.split_held_out()
    report = VariantReport("int8", path, False, held_out_frames=len(held_out),
                           calibration_frames=len(calibration))  # fmt: skip
    if not len(calibration) or not len(held_out):
        report.reason = f"needs at least 2 frames to calibrate and to check, got {len(frames)}"
        return report
    reference = ort_outputs(ort_session(model.SerializeToString()), held_out)[0]
    best: tuple[float, float, bool, onnx.ModelProto] | None = None
    with tempfile.TemporaryDirectory(prefix="carrt-int8-") as tmp:
        source = Path(tmp) / "fp32.onnx"
        onnx.save(model, source)
        try:
            from onnxruntime.quantization.shape_inference import quant_pre_process

            # Shape inference + graph optimisations make the Q/DQ placement cleaner.
            quant_pre_process(str(source), str(Path(tmp) / "pre.onnx"), skip_symbolic_shape=True)
            source = Path(tmp) / "pre.onnx"
        except Exception:  # optional step: quantising the plain export also works
            pass
        # Per-channel weight scales usually help convolutions; measure instead of assuming.
        for per_channel in (True, False):
            target = Path(tmp) / f"int8-{per_channel}.onnx"
            _quantize(source, target, calibration, per_channel, symmetric)
            quantised = onnx.load(target)
            mu = ort_outputs(ort_session(target), held_out)[0]
            mean, worst = _errors(reference, mu)
            if best is None or mean < best[0]:
                best = (mean, worst, per_channel, quantised)
    assert best is not None
    report.mean_abs_mu, report.max_abs_mu, per_channel, quantised = best
    report.detail = (
        f"static QDQ int8, {'per-channel' if per_channel else 'per-tensor'} weights, "
        f"{'symmetric int8' if symmetric else 'uint8'} activations"
    )
    set_metadata(quantised, _metadata(model, "int8", {
        "carrt.quantization": f"{report.detail}, MinMax calibration on "
        f"{report.calibration_frames} frames",
        "carrt.variant_mean_abs_mu": f"{report.mean_abs_mu:.4g}",
        "carrt.variant_max_abs_mu": f"{report.max_abs_mu:.4g}",
    }))  # fmt: skip
    return _finish(report, quantised, bounds, horizon)


# ----------------------------------------------------------------------------- fp16
def fp16_providers(available: list[str] | None = None) -> list[str]:
    if available is None:
        import onnxruntime as ort

        available = list(ort.get_available_providers())
    return [p for p in GPU_PROVIDERS if p in available]


def fp16_variant(
    model: onnx.ModelProto,
    frames: Frames,
    path: Path,
    bounds: Bounds,
    horizon: int,
    *,
    providers: list[str] | None = None,
) -> VariantReport:
    """float16 weights and compute, float32/uint8 at the edges (keep_io_types).

    Only written where an execution provider runs fp16 natively (CUDA/TensorRT): on a CPU
    onnxruntime upcasts or lacks kernels, so the file would be slower, not faster.
    """
    _, held_out = frames.split_held_out()
    report = VariantReport("fp16", path, False, held_out_frames=len(held_out))
    providers = fp16_providers() if providers is None else providers
    if not providers:
        import onnxruntime as ort

        report.skipped = True
        report.reason = (
            "no fp16-capable execution provider (TensorRT/CUDA) in this onnxruntime "
            f"(available: {', '.join(ort.get_available_providers())}); export on the car"
        )
        return report
    try:
        from onnxruntime.transformers.float16 import convert_float_to_float16
    except ImportError as exc:
        report.skipped = True
        report.reason = f"onnxruntime.transformers.float16 is not available ({exc})"
        return report
    half = convert_float_to_float16(copy.deepcopy(model), keep_io_types=True)
    topological_sort(half.graph)  # keep_io_types appends its input Casts at the end
    reference = ort_outputs(ort_session(model.SerializeToString()), held_out)[0]
    session = ort_session(half.SerializeToString(), list(dict.fromkeys([*providers, CPU])))
    mu = ort_outputs(session, held_out)[0]
    report.mean_abs_mu, report.max_abs_mu = _errors(reference, mu)
    report.detail = f"float16, float32 inputs/outputs, checked on {providers[0]}"
    set_metadata(half, _metadata(model, "fp16", {
        "carrt.variant_mean_abs_mu": f"{report.mean_abs_mu:.4g}",
        "carrt.variant_max_abs_mu": f"{report.max_abs_mu:.4g}",
    }))  # fmt: skip
    return _finish(report, half, bounds, horizon)
