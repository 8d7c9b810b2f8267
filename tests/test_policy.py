"""The ONNX policy: a valid model drives with the right values, every broken export is refused
at load with one line naming the problem, providers are chosen in order with the CPU as the
fallback, and a late plan is used at most once."""

from __future__ import annotations

import argparse

import numpy as np
import onnxruntime as ort
import pytest
from onnx import TensorProto
from onnx_models import build_policy, reference_mu

from carrt import model_info
from carrt.errors import UserError
from carrt.interfaces import Plan, Policy
from carrt.model_contract import REQUIRED_KEYS, ContractError, TensorSpec, validate_io
from carrt.plan import PlanBuffer
from carrt.policy import CPU, OnnxPolicy, select_providers

CUDA, TRT = "CUDAExecutionProvider", "TensorrtExecutionProvider"


def image_with(left: int, right: int) -> np.ndarray:
    image = np.empty((96, 96, 3), np.uint8)
    image[:, :48], image[:, 48:] = left, right
    return image


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return build_policy(tmp_path_factory.mktemp("m") / "p.onnx", ramp=(0.05, 0.02))


@pytest.fixture(scope="module")
def policy(model):
    return OnnxPolicy(model)


# ----------------------------------------------------------------------------- a valid model
def test_valid_model_loads_with_metadata_and_hash(policy, model):
    import hashlib

    assert isinstance(policy, Policy)
    assert policy.horizon == 10
    assert set(REQUIRED_KEYS) <= set(policy.metadata)
    assert policy.sha256 == hashlib.sha256(model.read_bytes()).hexdigest()
    assert policy.size_bytes == model.stat().st_size
    assert policy.provider == CPU


def test_predict_returns_the_graphs_plan(policy):
    rng = np.random.default_rng(1)
    image = rng.integers(0, 256, (96, 96, 3), dtype=np.uint8)
    image[:, :48] //= 2  # darker on the left: steer right of zero
    plan = policy.predict(image, 1.5)
    assert isinstance(plan, Plan)
    assert plan.mu.shape == plan.sigma.shape == (10, 2)
    assert plan.mu.dtype == plan.sigma.dtype == np.float32
    expected = np.clip(reference_mu(image, 1.5, ramp=(0.05, 0.02)), (-1, 0), (1, 1))
    np.testing.assert_allclose(plan.mu, expected, atol=1e-5)
    np.testing.assert_allclose(plan.sigma, 0.1, atol=1e-7)
    # and it really depends on its inputs
    assert policy.predict(image, 0.0).mu[0, 1] > plan.mu[0, 1]
    assert (
        policy.predict(image_with(200, 50), 0).mu[0, 0]
        > 0
        > policy.predict(image_with(50, 200), 0).mu[0, 0]
    )


def test_predict_refuses_an_image_that_is_not_96x96_uint8(policy):
    with pytest.raises(ValueError):
        policy.predict(np.zeros((96, 96, 3), np.float32), 0.0)
    with pytest.raises(ValueError):
        policy.predict(np.zeros((120, 160, 3), np.uint8), 0.0)


def test_mu_is_clipped_to_the_metadata_bounds(tmp_path):
    # action_low "-1.0,0.0": a model exported before throttle could go negative still loads,
    # and its plan is clipped to its own bounds, so it never brakes.
    path = build_policy(
        tmp_path / "wild.onnx",
        steering=50.0,
        throttle=(-0.5, 0.0),
        throttle_clip=None,
        metadata_overrides={"carrt.action_high": "0.8,0.6", "carrt.action_low": "-1.0,0.0"},
    )
    policy = OnnxPolicy(path)
    assert policy.predict(image_with(255, 0), 0.0).mu[:, 0] == pytest.approx([0.8] * 10)
    assert policy.predict(image_with(0, 255), 0.0).mu[:, 0] == pytest.approx([-1.0] * 10)
    assert (policy.predict(image_with(0, 255), 0.0).mu[:, 1] == 0.0).all()
    fast = build_policy(tmp_path / "fast.onnx", throttle=(3.0, 0.0), throttle_clip=None)
    assert (OnnxPolicy(fast).predict(image_with(9, 9), 0.0).mu[:, 1] == 1.0).all()


def test_a_policy_can_brake_with_negative_throttle(tmp_path):
    path = build_policy(tmp_path / "brake.onnx", throttle=(-0.7, 0.0), throttle_clip=None)
    policy = OnnxPolicy(path)
    assert tuple(policy.action_low) == (-1.0, -1.0)
    assert policy.predict(image_with(9, 9), 0.0).mu[:, 1] == pytest.approx([-0.7] * 10)


def test_bounds_wider_than_the_contract_are_refused(tmp_path):
    path = build_policy(tmp_path / "wide.onnx", metadata_overrides={"carrt.action_low": "-1,-2"})
    with pytest.raises(UserError, match="exceed"):
        OnnxPolicy(path)


def test_warm_up_runs_and_returns_latencies(policy):
    latencies = policy.warm_up(3)
    assert len(latencies) == 3 and all(0 < t < 5 for t in latencies)
    assert policy.warmup_latencies == latencies


def test_a_model_that_answers_nan_is_refused_at_warm_up_and_neutral_in_predict(tmp_path):
    policy = OnnxPolicy(build_policy(tmp_path / "nan.onnx", steering=float("nan")))
    with pytest.raises(UserError, match="NaN"):
        policy.warm_up(1)
    plan = policy.predict(image_with(1, 2), 0.0)
    assert np.isfinite(plan.mu).all()
    assert (plan.mu[:, 0] == 0.0).all() and policy.nonfinite_outputs == 1


def test_dynamic_horizon_dim_is_accepted(tmp_path):
    path = build_policy(tmp_path / "dyn.onnx", declared_horizon=None)
    policy = OnnxPolicy(path)
    policy.warm_up(1)  # the run-time shapes are checked on every inference
    assert policy.predict(image_with(1, 2), 0.0).mu.shape == (10, 2)


# ----------------------------------------------------------------------------- broken models
BROKEN = {
    "corrupt bytes": ({"corrupt": True}, "not a valid ONNX model"),
    "image float": ({"image_dtype": TensorProto.FLOAT}, "input image is float32, expected uint8"),
    "image NCHW": ({"image_shape": (None, 3, 96, 96)}, r"input image has shape \[N, 3, 96, 96\]"),
    "image 64px": ({"image_shape": (None, 64, 64, 3)}, r"input image has shape \[N, 64, 64, 3\]"),
    "fixed batch": ({"image_shape": (4, 96, 96, 3)}, "fixed batch of 4"),
    "speed rank": ({"speed_shape": (None,)}, r"input speed has shape \[N\], expected \[N, 1\]"),
    "speed double": ({"speed_dtype": TensorProto.DOUBLE}, "input speed is float64"),
    "input name": ({"input_names": ("img", "speed")}, "input 'image' missing"),
    "extra input": ({"extra_input": "steer_prev"}, "unexpected input 'steer_prev'"),
    "output name": ({"output_names": ("mu", "std")}, "output 'sigma' missing"),
    "mu float16": ({"mu_dtype": TensorProto.FLOAT16}, "output mu is float16, expected float32"),
    "horizon vs metadata": (
        {"metadata_overrides": {"carrt.horizon": "8"}},
        r"output mu has shape \[N, 10, 2\], expected \[N, 8, 2\] \(metadata carrt.horizon is 8\)",
    ),
    "no metadata": ({"drop_metadata": list(REQUIRED_KEYS)}, "metadata missing carrt.schema"),
    "missing key": ({"drop_metadata": ["carrt.horizon"]}, "metadata missing carrt.horizon"),
    "wrong schema": (
        {"metadata_overrides": {"carrt.schema": "carrt.policy/0"}},
        "carrt.schema is 'carrt.policy/0'",
    ),
    "bad horizon": ({"metadata_overrides": {"carrt.horizon": "ten"}}, "not an integer"),
    "other period": (
        {"metadata_overrides": {"carrt.control_period_s": "0.05"}},
        "0.05 s control period",
    ),
    "speed units": ({"metadata_overrides": {"carrt.speed_units": "km/h"}}, "speed_units"),
}


@pytest.mark.parametrize("variant", list(BROKEN))
def test_broken_model_is_refused_with_one_line(tmp_path, variant):
    knobs, message = BROKEN[variant]
    path = build_policy(tmp_path / "bad.onnx", **knobs)
    with pytest.raises(UserError, match=message) as err:
        OnnxPolicy(path)
    text = str(err.value)
    assert text.startswith(f"model {path}: ") and "\n" not in text


def test_missing_and_non_onnx_files_are_refused(tmp_path):
    with pytest.raises(UserError, match="no such file"):
        OnnxPolicy(tmp_path / "absent.onnx")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"\x00\x01 definitely not protobuf " * 50)
    with pytest.raises(UserError, match="not a valid ONNX model") as err:
        OnnxPolicy(junk)
    assert "\n" not in str(err.value)


def test_validate_io_accepts_dynamic_dims_and_extra_outputs():
    inputs = [
        TensorSpec("image", "uint8", (None, 96, 96, 3)),
        TensorSpec("speed", "float32", (1, 1)),
    ]
    outputs = [
        TensorSpec("mu", "float32", ("batch", "h", 2)),
        TensorSpec("sigma", "float32", (None, 10, 2)),
        TensorSpec("features", "float32", (None, 512)),
    ]
    validate_io(inputs, outputs, 10)
    with pytest.raises(ContractError, match="horizon is 8"):
        validate_io(inputs, outputs, 8)


# ----------------------------------------------------------------------------- providers
def test_provider_order_is_kept_and_cpu_is_always_the_fallback():
    everything = [TRT, CUDA, CPU]
    assert select_providers([TRT, CUDA, CPU], [CUDA, CPU]) == [CUDA, CPU]
    assert select_providers([TRT, CUDA, CPU], [CPU]) == [CPU]
    assert select_providers([CUDA, TRT, CPU], everything) == [CUDA, TRT, CPU]
    assert select_providers([CUDA], everything) == [CUDA, CPU]
    assert select_providers([CPU, CUDA], everything) == [CUDA, CPU]
    assert select_providers([], everything) == [CPU]


def test_unknown_provider_name_is_a_config_error():
    with pytest.raises(UserError, match="unknown onnxruntime provider 'CUDAExecutionProvder'"):
        select_providers(["CUDAExecutionProvder", CPU], [CPU])


def test_cpu_selected_here_when_gpus_are_unavailable(model):
    available = ort.get_available_providers()
    policy = OnnxPolicy(model, providers=[TRT, CUDA, CPU], intra_op_threads=1)
    expected = select_providers([TRT, CUDA, CPU], available)
    assert policy.requested_providers == expected
    assert policy.provider == expected[0]
    if TRT not in available and CUDA not in available:
        assert policy.provider == CPU and policy.providers == [CPU]
    assert policy.fallback_note is None


# ----------------------------------------------------------------------------- plan buffer
def plan_with(first: float, horizon: int = 10) -> Plan:
    mu = np.array([[first + i, 0.1 * i] for i in range(horizon)], np.float32)
    return Plan(mu=mu, sigma=np.ones_like(mu))


def test_plan_buffer_uses_the_next_step_once_then_neutral():
    buffer = PlanBuffer()
    assert buffer.fallback() is None  # no plan yet: neutral
    assert buffer.fresh(plan_with(0.0)) == (0.0, 0.0)
    assert buffer.fallback() == pytest.approx((1.0, 0.1))
    assert buffer.fallback() is None
    assert buffer.fallback() is None
    assert buffer.fresh(plan_with(5.0)) == (5.0, 0.0)
    assert buffer.fallback() == pytest.approx((6.0, 0.1))
    assert buffer.fallback() is None
    assert buffer.plan is not None


def test_plan_buffer_clear_and_horizon_one():
    buffer = PlanBuffer()
    buffer.fresh(plan_with(0.0))
    buffer.clear()
    assert buffer.fallback() is None and buffer.plan is None
    buffer.fresh(plan_with(0.0, horizon=1))
    assert buffer.fallback() is None  # nothing after step 0


# ----------------------------------------------------------------------------- carrt model info
def info_args(path, **extra) -> argparse.Namespace:
    return argparse.Namespace(
        model=str(path), providers=f"{TRT},{CUDA},{CPU}", warmup=extra.get("warmup", 2)
    )


def test_model_info_prints_everything_a_bug_report_needs(model, policy, capsys):
    assert model_info.run(info_args(model)) == 0
    out = capsys.readouterr().out
    assert policy.sha256 in out
    assert f"{model.stat().st_size:,} bytes" in out
    for key in REQUIRED_KEYS:
        assert key in out
    assert "image  uint8    [N, 96, 96, 3]" in out
    assert "speed  float32  [N, 1]" in out
    assert "mu     float32  [N, 10, 2]" in out
    assert f"selected   {policy.provider}" in out
    assert "available  " + ", ".join(ort.get_available_providers()) in out
    assert "warm-up   2 runs" in out


def test_model_info_does_not_require_the_cars_control_period(tmp_path, capsys):
    path = build_policy(
        tmp_path / "p20.onnx", metadata_overrides={"carrt.control_period_s": "0.05"}
    )
    assert model_info.run(info_args(path, warmup=0)) == 0
    assert "carrt.control_period_s      0.05" in capsys.readouterr().out


def test_model_info_on_a_bad_model_is_one_line(tmp_path):
    path = build_policy(tmp_path / "bad.onnx", drop_metadata=["carrt.iteration"])
    with pytest.raises(UserError, match=r"metadata missing carrt\.iteration") as err:
        model_info.run(info_args(path))
    assert "\n" not in str(err.value)


def test_model_info_parser_registers_model_info():
    parser = argparse.ArgumentParser(prog="carrt")
    model_info.add_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["model", "info", "p.onnx", "--warmup", "0"])
    assert args.func is model_info.run and args.model == "p.onnx" and args.warmup == 0


def test_carrt_model_info_through_the_cli(tmp_path, capsys):
    from carrt import cli

    path = build_policy(tmp_path / "bad.onnx", image_dtype=TensorProto.FLOAT)
    assert cli.main(["model", "info", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "input image is float32" in err


def test_the_placements_a_model_was_trained_on_are_read_from_its_metadata():
    import json

    from carrt import model_contract as mc

    metas = [{"sim": {"layout": "hard", "track_seed": 3}}, {"sim": {"layout": "hard",
             "track_seed": 1}}, {"sim": {"layout": "easy", "track_seed": 1}}, {}]  # fmt: skip
    placed = mc.sim_placements(metas)
    assert placed == {"easy": [1], "hard": [1, 3]}
    meta = {mc.SIM_PLACEMENTS: json.dumps(placed)}
    assert mc.trained_on(meta, "hard", range(0, 5)) == [1, 3]
    assert mc.trained_on(meta, "easy", [2]) == [] and mc.trained_on({}, "hard", [1]) == []
    assert mc.trained_on({mc.SIM_PLACEMENTS: "not json"}, "hard", [1]) == []


def test_a_list_of_placements_is_said_in_the_form_it_is_typed():
    from carrt.arg_types import format_int_list, parse_int_list

    for text in ("100-104,120", "5", "1,3,5-7", "200-259"):
        assert format_int_list(parse_int_list(text, "tracks")) == text
