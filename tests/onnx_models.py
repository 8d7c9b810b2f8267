"""Tiny contract-valid ONNX policies built with onnx.helper (no torch), and broken variants.

`build_policy(tmp_path / "p.onnx")` writes a valid default model. Its plan depends on the
inputs deterministically, so tests can check values, not just shapes:

    steering = steering_gain * (mean(left half) - mean(right half)) / 255   (+ ramp * step)
    throttle = clip(throttle_base - throttle_per_mps * speed, 0, 1)          (+ ramp * step)
    sigma    = sigma (constant)

`reference_mu` computes the same in numpy. Every knob that makes the model wrong names one
way a real export can go wrong (see tests/test_policy.py).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from carrt import model_contract as mc

OPSET = 17
IR_VERSION = 8  # what opset 17 needs; TensorRT 8.6's parser reads it


def default_metadata(horizon: int = 10, control_period_s: float = 0.1) -> dict[str, str]:
    return {
        "carrt.schema": mc.SCHEMA,
        "carrt.horizon": str(horizon),
        "carrt.control_period_s": str(control_period_s),
        "carrt.image_shape": "96,96,3",
        "carrt.action_names": "steering,throttle",
        "carrt.action_low": ",".join(str(x) for x in mc.ACTION_LOW),
        "carrt.action_high": ",".join(str(x) for x in mc.ACTION_HIGH),
        "carrt.speed_units": "m/s",
        "carrt.training_data_digest": "0" * 64,
        "carrt.iteration": "0",
        "carrt.code_version": "0.1.0",
    }


def _dims(shape: Sequence[int | str | None]) -> list[int | str]:
    return ["N" if d is None else d for d in shape]


def _const(name: str, value: np.ndarray) -> onnx.NodeProto:
    return helper.make_node("Constant", [], [name], value=numpy_helper.from_array(value, name))


def build_policy(
    path: str | Path,
    *,
    horizon: int = 10,
    steering: float = 2.0,
    throttle: tuple[float, float] = (0.6, 0.2),
    throttle_clip: tuple[float, float] | None = (0.0, 1.0),
    ramp: tuple[float, float] = (0.0, 0.0),
    sigma: float = 0.1,
    metadata_overrides: Mapping[str, str] | None = None,
    drop_metadata: Iterable[str] = (),
    image_dtype: int = TensorProto.UINT8,
    image_shape: Sequence[int | str | None] = (None, 96, 96, 3),
    speed_dtype: int = TensorProto.FLOAT,
    speed_shape: Sequence[int | str | None] = (None, 1),
    input_names: tuple[str, str] = ("image", "speed"),
    output_names: tuple[str, str] = ("mu", "sigma"),
    extra_input: str | None = None,
    mu_dtype: int = TensorProto.FLOAT,
    declared_horizon: int | str | None = "same",
    corrupt: bool = False,
) -> Path:
    """Write a policy to `path` and return the path.

    declared_horizon: the H written in the outputs' declared shapes ("same": the graph's H;
    None: a dynamic dim). corrupt: write the serialized bytes cut in half (not loadable).
    steering=float("nan") makes a model that answers NaN.
    """
    path = Path(path)
    img_name, spd_name = input_names
    mu_name, sigma_name = output_names
    b, c = throttle
    nodes = [
        helper.make_node("Cast", [img_name], ["x"], to=TensorProto.FLOAT),
        _const("half", np.array([48], np.int64)),
        _const("zero", np.array([0], np.int64)),
        _const("end", np.array([96], np.int64)),
        _const("axis_w", np.array([2], np.int64)),
        helper.make_node("Slice", ["x", "zero", "half", "axis_w"], ["left"]),
        helper.make_node("Slice", ["x", "half", "end", "axis_w"], ["right"]),
        helper.make_node("ReduceMean", ["left"], ["lm"], axes=[1, 2, 3], keepdims=0),
        helper.make_node("ReduceMean", ["right"], ["rm"], axes=[1, 2, 3], keepdims=0),
        helper.make_node("Sub", ["lm", "rm"], ["diff"]),
        _const("gain", np.array(steering / 255.0, np.float32)),
        helper.make_node("Mul", ["diff", "gain"], ["steer"]),  # [N]
        helper.make_node("Cast", [spd_name], ["spd_f"], to=TensorProto.FLOAT),
        _const("flat", np.array([-1], np.int64)),
        helper.make_node("Reshape", ["spd_f", "flat"], ["spd"]),  # [N]
        _const("per_mps", np.array(c, np.float32)),
        _const("base", np.array(b, np.float32)),
        helper.make_node("Mul", ["spd", "per_mps"], ["slow"]),
        helper.make_node("Sub", ["base", "slow"], ["thr_raw"]),
    ]
    if throttle_clip is None:
        nodes.append(helper.make_node("Identity", ["thr_raw"], ["thr"]))
    else:
        nodes += [
            _const("lo", np.array(throttle_clip[0], np.float32)),
            _const("hi", np.array(throttle_clip[1], np.float32)),
            helper.make_node("Clip", ["thr_raw", "lo", "hi"], ["thr"]),
        ]
    steps = np.arange(horizon, dtype=np.float32)[None, :, None]
    nodes += [
        _const("ax1", np.array([1], np.int64)),
        helper.make_node("Unsqueeze", ["steer", "ax1"], ["steer1"]),  # [N, 1]
        helper.make_node("Unsqueeze", ["thr", "ax1"], ["thr1"]),
        helper.make_node("Concat", ["steer1", "thr1"], ["act"], axis=1),  # [N, 2]
        helper.make_node("Unsqueeze", ["act", "ax1"], ["act1"]),  # [N, 1, 2]
        _const("reps", np.array([1, horizon, 1], np.int64)),
        helper.make_node("Tile", ["act1", "reps"], ["tiled"]),  # [N, H, 2]
        _const("ramp", (steps * np.array(ramp, np.float32)).astype(np.float32)),
        helper.make_node("Add", ["tiled", "ramp"], ["mu_f"]),
        helper.make_node("Cast", ["mu_f"], [mu_name], to=mu_dtype),
        _const("nil", np.array(0.0, np.float32)),
        _const("sig", np.array(sigma, np.float32)),
        helper.make_node("Mul", ["tiled", "nil"], ["zeros"]),
        helper.make_node("Add", ["zeros", "sig"], [sigma_name]),
    ]
    inputs = [
        helper.make_tensor_value_info(img_name, image_dtype, _dims(image_shape)),
        helper.make_tensor_value_info(spd_name, speed_dtype, _dims(speed_shape)),
    ]
    if extra_input is not None:
        inputs.append(helper.make_tensor_value_info(extra_input, TensorProto.FLOAT, ["N", 1]))
    h_dim = horizon if declared_horizon == "same" else declared_horizon
    out_shape = ["N", "H" if h_dim is None else h_dim, 2]
    outputs = [
        helper.make_tensor_value_info(mu_name, mu_dtype, out_shape),
        helper.make_tensor_value_info(sigma_name, TensorProto.FLOAT, out_shape),
    ]
    graph = helper.make_graph(nodes, "carrt_test_policy", inputs, outputs)
    model = helper.make_model(
        graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="carrt-tests"
    )
    model.ir_version = IR_VERSION
    meta = default_metadata(horizon)
    meta.update(metadata_overrides or {})
    for key in drop_metadata:
        meta.pop(key, None)
    helper.set_model_props(model, meta)
    onnx.checker.check_model(model)
    data = model.SerializeToString()
    if corrupt:
        data = data[: len(data) // 2]
    path.write_bytes(data)
    return path


def reference_mu(
    image: np.ndarray,
    speed: float,
    *,
    horizon: int = 10,
    steering: float = 2.0,
    throttle: tuple[float, float] = (0.6, 0.2),
    throttle_clip: tuple[float, float] | None = (0.0, 1.0),
    ramp: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """What build_policy's graph computes for one (96, 96, 3) image, before carrt's clipping."""
    x = image.astype(np.float32)
    steer = steering * (x[:, :48].mean() - x[:, 48:].mean()) / 255.0
    thr = throttle[0] - throttle[1] * speed
    if throttle_clip is not None:
        thr = float(np.clip(thr, *throttle_clip))
    steps = np.arange(horizon, dtype=np.float32)[:, None]
    return (np.array([steer, thr], np.float32)[None, :] + steps * np.array(ramp)).astype(np.float32)
