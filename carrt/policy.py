"""The ONNX policy on the car, and the rule for what to do when it is late.

Everything that can be wrong with a model file (missing, corrupt, wrong inputs, wrong horizon,
no metadata, trained at another control period) is found here at load time and raised as one
UserError line, so `carrt drive` refuses before the car is armed instead of steering on
nonsense at the first tick (carrt/model_contract.py).
"""

from __future__ import annotations

import hashlib
import os
import time
import zipfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

from carrt import model_contract as mc
from carrt.config import LoopConfig
from carrt.errors import UserError
from carrt.interfaces import Plan
from carrt.model_contract import IMAGE_SHAPE
from carrt.shipped import resolve_model
from firmware_bridge.timing import CONTROL_PERIOD_S

CPU = "CPUExecutionProvider"
TENSORRT = "TensorrtExecutionProvider"
DEFAULT_PROVIDERS: tuple[str, ...] = tuple(LoopConfig().providers)

_ORT_DTYPES = {"float": "float32", "double": "float64"}


def select_providers(preferred: Sequence[str], available: Sequence[str]) -> list[str]:
    """The configured order, minus what this onnxruntime build lacks, with CPU always last.

    A name onnxruntime has never heard of is a config typo, and is refused rather than
    skipped: silently running on the CPU because of a misspelt "CUDA" would cost the 10 Hz
    budget with no explanation.
    """
    known = set(ort.get_all_providers())
    for name in preferred:
        if name not in known:
            raise UserError(
                f"loop.providers: unknown onnxruntime provider {name!r} "
                f"(known: {', '.join(sorted(known))})"
            )
    chosen = [p for p in dict.fromkeys(preferred) if p in available]
    if CPU in chosen:
        chosen.remove(CPU)
    return [*chosen, CPU]


def refuse_checkpoint(path: Path) -> None:
    """A training checkpoint handed where an ONNX model belongs is a common slip (`runs/iter1/
    policy.pt` beside `policy.onnx`): name it, and the command that turns it into a model,
    instead of onnxruntime's protobuf parse error, which reads like a corrupt file. torch.save
    writes a zip archive holding `data.pkl` (or, in its legacy format, a pickle)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4)
            is_zip = head == b"PK\x03\x04"
            checkpoint = (is_zip and zipfile.is_zipfile(path) and _holds_pickle(path)) or (
                head[:1] == b"\x80" and path.suffix in (".pt", ".pth", ".ckpt")
            )
    except OSError:
        return  # the loader's own error names an unreadable file
    if checkpoint:
        raise UserError(
            f"model {path}: a PyTorch training checkpoint, not an ONNX model: export it with "
            f"carrt-export {path} -o {path.with_suffix('.onnx')}"
        )


def _holds_pickle(path: Path) -> bool:
    with zipfile.ZipFile(path) as archive:
        return any(name.endswith("data.pkl") for name in archive.namelist())


def _provider_options(name: str) -> tuple[str, dict[str, Any]] | str:
    if name != TENSORRT:
        return name
    # Building a TensorRT engine takes minutes on a Jetson: cache it between runs.
    cache = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "carrt" / "trt"
    with_cache: dict[str, Any] = {
        "trt_engine_cache_enable": True,
        "trt_engine_cache_path": str(cache),
    }
    return name, with_cache


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def _spec(arg: Any) -> mc.TensorSpec:
    dtype = arg.type
    if dtype.startswith("tensor(") and dtype.endswith(")"):
        dtype = _ORT_DTYPES.get(dtype[7:-1], dtype[7:-1])
    shape = tuple(arg.shape) if arg.shape is not None else ()
    return mc.TensorSpec(arg.name, dtype, shape)


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text if len(text) <= 200 else text[:197] + "..."


class OnnxPolicy:
    """The Policy protocol over an onnxruntime session, validated against model_contract.

    control_period_s=None skips the control-period check (for `carrt model info`, which
    describes a model without a car in mind).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        providers: Sequence[str] = DEFAULT_PROVIDERS,
        intra_op_threads: int = 0,
        control_period_s: float | None = CONTROL_PERIOD_S,
    ) -> None:
        self.path = resolve_model(path)
        refuse_checkpoint(self.path)
        self.size_bytes = self.path.stat().st_size
        self.sha256 = file_sha256(self.path)
        self.available_providers = list(ort.get_available_providers())
        self.requested_providers = select_providers(providers, self.available_providers)
        self.fallback_note: str | None = None
        self._session = self._load(intra_op_threads)
        self.providers: list[str] = list(self._session.get_providers())
        self.provider: str = self.providers[0]
        if self.fallback_note is None and self.provider != self.requested_providers[0]:
            # onnxruntime drops a provider whose libraries fail to load with only a log line.
            self.fallback_note = (
                f"{self.requested_providers[0]} did not initialise; running on {self.provider}"
            )

        modelmeta = self._session.get_modelmeta()
        self.metadata: dict[str, str] = dict(modelmeta.custom_metadata_map)
        self.producer: str = modelmeta.producer_name
        self.inputs = [_spec(a) for a in self._session.get_inputs()]
        self.outputs = [_spec(a) for a in self._session.get_outputs()]
        try:
            self.horizon: int = mc.validate_metadata(self.metadata, control_period_s)
            mc.validate_io(self.inputs, self.outputs, self.horizon)
            low, high = mc.action_bounds(self.metadata)
        except mc.ContractError as exc:
            raise UserError(f"model {self.path}: {exc}") from exc
        self.action_low = np.asarray(low, dtype=np.float32)
        self.action_high = np.asarray(high, dtype=np.float32)
        # What the car does without a plan: no steering, no throttle, inside the bounds.
        self.neutral = np.clip(np.zeros(2, np.float32), self.action_low, self.action_high)
        self.nonfinite_outputs = 0
        self.warmup_latencies: list[float] = []

    def _load(self, intra_op_threads: int) -> ort.InferenceSession:
        options = ort.SessionOptions()
        options.log_severity_level = 3  # errors only: provider chatter is not the user's problem
        if intra_op_threads > 0:
            options.intra_op_num_threads = intra_op_threads
        # One inference per 100 ms: spinning worker threads would only burn the cores that
        # the camera, serial and writer threads need (measured: it doubled frame age here).
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        wanted = [_provider_options(p) for p in self.requested_providers]
        try:
            return ort.InferenceSession(str(self.path), options, providers=wanted)
        except Exception as exc:
            if self.requested_providers == [CPU]:
                raise UserError(
                    f"model {self.path}: not a valid ONNX model ({_one_line(exc)})"
                ) from exc
            gpu_error = _one_line(exc)
        # A GPU provider can be "available" and still fail (mismatched CUDA/TensorRT libs):
        # the CPU must still drive, and the user must be told why it is slow.
        try:
            session = ort.InferenceSession(str(self.path), options, providers=[CPU])
        except Exception as exc:
            raise UserError(
                f"model {self.path}: not a valid ONNX model ({_one_line(exc)})"
            ) from exc
        self.fallback_note = f"fell back to {CPU}: {gpu_error}"
        return session

    # ------------------------------------------------------------------ inference
    def _run(self, image: np.ndarray, speed_mps: float) -> tuple[np.ndarray, np.ndarray]:
        if image.shape != IMAGE_SHAPE or image.dtype != np.uint8:
            raise ValueError(f"policy input must be {IMAGE_SHAPE} uint8, got {image.shape}")
        feeds = {
            mc.INPUT_IMAGE: np.ascontiguousarray(image)[None],
            mc.INPUT_SPEED: np.array([[speed_mps]], dtype=np.float32),
        }
        mu, sigma = self._session.run([mc.OUTPUT_MU, mc.OUTPUT_SIGMA], feeds)
        want = (1, self.horizon, 2)
        if mu.shape != want or sigma.shape != want:
            raise UserError(
                f"model {self.path}: outputs have shapes {list(mu.shape)} and "
                f"{list(sigma.shape)} at run time, expected {list(want)}"
            )
        return mu[0].astype(np.float32, copy=False), sigma[0].astype(np.float32, copy=False)

    def predict(self, image: np.ndarray, speed_mps: float) -> Plan:
        """One frame in, the clipped plan out. Never hands the loop a NaN.

        A non-finite step is replaced by neutral and counted (nonfinite_outputs), because a
        NaN throttle must not reach the car; warm-up refuses a model that does this at once.
        """
        mu, sigma = self._run(image, speed_mps)
        if not np.isfinite(mu).all():
            self.nonfinite_outputs += 1
            mu = np.where(np.isfinite(mu), mu, self.neutral)
        mu = np.clip(mu, self.action_low, self.action_high)
        return Plan(mu=mu, sigma=sigma)

    def warm_up(self, n: int = 5) -> list[float]:
        """Run n inferences before arming: the first ones allocate and (TensorRT) build.

        Returns the latencies in seconds (wall time, not the loop's clock, which may be
        simulated). Raises UserError when the model answers with NaN/inf on a plain frame.
        """
        image = np.full(IMAGE_SHAPE, 128, dtype=np.uint8)
        latencies = []
        for _ in range(n):
            start = time.perf_counter()
            mu, sigma = self._run(image, 0.0)
            latencies.append(time.perf_counter() - start)
            if not (np.isfinite(mu).all() and np.isfinite(sigma).all()):
                raise UserError(f"model {self.path}: outputs NaN or inf on a grey frame")
        self.warmup_latencies = latencies
        return latencies
