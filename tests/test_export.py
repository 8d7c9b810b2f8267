"""export/: the ONNX file computes what PyTorch computes on recorded frames, carries carrt's
metadata, is one self-contained file that carrt loads, and every failed check leaves no file."""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

import carrt
from carrt import model_contract as mc
from carrt import model_info
from carrt.errors import UserError
from carrt.policy import OnnxPolicy
from export import ExportRefused, export_policy, graph
from export import onnx_export as ox
from export.parity import sample_frames, torch_outputs
from export.quantize import Bounds, fp16_providers, fp16_variant
from training.data import compute_normalisation, data_digest, load_episodes
from training.models import PolicyNet
from training.profiles import get_profile

ROOT = Path(__file__).resolve().parent.parent


def tiny_policy() -> PolicyNet:
    torch.manual_seed(0)
    policy = PolicyNet(get_profile("tiny"))
    with torch.no_grad():  # undo the head's small init, so the plan depends on the frame
        policy.head[-1].weight.mul_(20.0)
    return policy.eval()


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory, sim_episodes) -> Path:
    """A checkpoint dict per the training contract, written with torch.save."""
    episodes = load_episodes([sim_episodes])
    policy = tiny_policy()
    norm = compute_normalisation(episodes, max_frames=256)
    policy.set_normalisation(norm)
    path = tmp_path_factory.mktemp("ckpt") / "policy.pt"
    torch.save(
        {
            "format": "carrt.checkpoint/2", "config": {}, "profile": "tiny",
            "stage": "imitation", "step": 7, "policy": policy.state_dict(),
            "world_model": None, "optimizer": None, "normalisation": norm.to_dict(),
            "data_digest": data_digest(episodes), "iteration": 2, "code_version": "test",
            "episodes": [],
        },
        path,
    )  # fmt: skip
    return path


@pytest.fixture(scope="module")
def exported(tmp_path_factory, checkpoint, sim_episodes):
    out = tmp_path_factory.mktemp("export") / "policy.onnx"
    report = export_policy(checkpoint, out, [str(sim_episodes)], max_frames=128)
    return out, report


def _policy_from(checkpoint: Path) -> PolicyNet:
    from training.checkpoint import load_policy

    return load_policy(checkpoint)[0]


# ----------------------------------------------------------------------------- the fp32 file
def test_metadata_round_trip_through_carrt_loader_and_model_info(exported, checkpoint, capsys):
    out, report = exported
    ckpt = torch.load(checkpoint, weights_only=True)
    policy = OnnxPolicy(out, providers=["CPUExecutionProvider"])  # the car's own checks
    meta = policy.metadata
    assert set(mc.REQUIRED_KEYS) <= set(meta)
    assert meta["carrt.schema"] == mc.SCHEMA and policy.horizon == 10
    assert meta["carrt.control_period_s"] == "0.1" and meta["carrt.speed_units"] == "m/s"
    assert meta["carrt.training_data_digest"] == ckpt["data_digest"]
    assert meta["carrt.iteration"] == "2" and meta["carrt.profile"] == "tiny"
    assert meta["carrt.code_version"].startswith(carrt.__version__)
    assert meta == report.metadata
    assert [t.render() for t in policy.inputs] == [
        "image uint8 [N, 96, 96, 3]", "speed float32 [N, 1]"]  # fmt: skip
    assert [t.render() for t in policy.outputs] == [
        "mu float32 [N, 10, 2]", "sigma float32 [N, 10, 2]"]  # fmt: skip

    args = argparse.Namespace(model=str(out), providers="CPUExecutionProvider", warmup=1)
    assert model_info.run(args) == 0
    printed = capsys.readouterr().out
    assert ckpt["data_digest"] in printed and "carrt.code_version" in printed


def test_fp32_parity_on_simulator_frames(exported, checkpoint, sim_episodes):
    out, report = exported
    assert report.parity.ok and report.parity.frames == 128
    assert report.parity.max_abs_mu <= 1e-4 and report.parity.max_abs_sigma <= 1e-4
    # Independently of export's own check: the car's predict() against PyTorch.
    frames = sample_frames([sim_episodes], max_frames=48, seed=1)
    mu_torch = torch_outputs(_policy_from(checkpoint), frames)[0]
    assert np.ptp(mu_torch[:, 0, 0]) > 1e-3, "the plan should depend on the frame"
    policy = OnnxPolicy(out, providers=["CPUExecutionProvider"])
    mu_onnx = np.stack([policy.predict(im, float(s[0])).mu for im, s in zip(
        frames.images, frames.speeds, strict=True)])  # fmt: skip
    np.testing.assert_allclose(mu_onnx, mu_torch, atol=1e-4, rtol=0)


def test_one_self_contained_file_at_opset_17(exported):
    out, _ = exported
    assert sorted(p.name for p in out.parent.iterdir()) == ["policy.onnx"]
    model = onnx.load(out, load_external_data=False)
    assert graph.external_tensors(model) == []
    assert all(not onnx.external_data_helper.uses_external_data(t) for t in model.graph.initializer)
    assert {o.domain or "ai.onnx": o.version for o in model.opset_import} == {"ai.onnx": 17}
    onnx.checker.check_model(model, full_check=True)


def test_missing_or_wrong_metadata_is_refused_by_carrt(exported, tmp_path):
    out, _ = exported
    model = onnx.load(out)
    kept = [p for p in model.metadata_props if p.key != "carrt.horizon"]
    del model.metadata_props[:]
    model.metadata_props.extend(kept)
    onnx.save(model, tmp_path / "no_horizon.onnx")
    with pytest.raises(UserError, match=r"metadata missing carrt\.horizon"):
        OnnxPolicy(tmp_path / "no_horizon.onnx", providers=["CPUExecutionProvider"])

    graph.set_metadata(
        model, {**graph.get_metadata(onnx.load(out)), "carrt.schema": "carrt.policy/0"}
    )
    onnx.save(model, tmp_path / "old_schema.onnx")
    with pytest.raises(UserError, match=r"carrt\.schema is 'carrt\.policy/0'"):
        OnnxPolicy(tmp_path / "old_schema.onnx", providers=["CPUExecutionProvider"])


# ----------------------------------------------------------------------------- refusals
def test_a_broken_export_is_refused_and_leaves_no_file(
    checkpoint, sim_episodes, tmp_path, monkeypatch
):
    """The classic: the graph normalises with other statistics than training did."""
    real = ox.torch_to_onnx

    def forgets_normalisation(policy, example):
        broken = _policy_from(checkpoint)
        with torch.no_grad():
            broken.image_mean.zero_()
            broken.image_std.fill_(1.0)
        return real(broken, example)

    monkeypatch.setattr(ox, "torch_to_onnx", forgets_normalisation)
    out = tmp_path / "policy.onnx"
    with pytest.raises(ExportRefused, match="differs from PyTorch beyond tolerance"):
        export_policy(checkpoint, out, [str(sim_episodes)], max_frames=32)
    assert list(tmp_path.iterdir()) == []


def test_a_file_carrt_would_refuse_is_not_written(checkpoint, sim_episodes, tmp_path, monkeypatch):
    def trained_at_20_hz(ckpt, horizon, exporter):
        meta = real(ckpt, horizon, exporter)
        return {**meta, "carrt.control_period_s": "0.05"}

    real = ox.build_metadata
    monkeypatch.setattr(ox, "build_metadata", trained_at_20_hz)
    with pytest.raises(ExportRefused, match=r"control period"):
        export_policy(checkpoint, tmp_path / "policy.onnx", [str(sim_episodes)], max_frames=8)
    assert list(tmp_path.iterdir()) == []


def test_bad_inputs_are_user_errors(checkpoint, sim_episodes, tmp_path):
    with pytest.raises(UserError, match="needs recorded episodes"):
        export_policy(checkpoint, tmp_path / "p.onnx", [])
    with pytest.raises(UserError, match="no such file"):
        export_policy(tmp_path / "nope.pt", tmp_path / "p.onnx", [str(sim_episodes)])
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(UserError, match=r"junk\.pt: unreadable"):
        export_policy(tmp_path / "junk.pt", tmp_path / "p.onnx", [str(sim_episodes)])
    (tmp_path / "junk.pt").unlink()
    with pytest.raises(UserError, match="tolerance"):
        export_policy(checkpoint, tmp_path / "p.onnx", [str(sim_episodes)], tolerance=-1)
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- variants
def test_int8_error_is_reported_bounded_and_enforced(checkpoint, sim_episodes, tmp_path):
    out = tmp_path / "policy.onnx"
    report = export_policy(checkpoint, out, [str(sim_episodes)], int8=True, max_frames=96)
    int8 = report.variants["int8"]
    assert int8.written, int8.reason
    assert int8.path == tmp_path / "policy.int8.onnx" and int8.path.is_file()
    assert int8.held_out_frames > 0 and int8.calibration_frames > 0
    assert 0 < int8.mean_abs_mu <= 0.05 and int8.max_abs_mu <= 0.2
    assert int8.size_bytes < report.size_bytes
    loaded = OnnxPolicy(int8.path, providers=["CPUExecutionProvider"])
    assert loaded.metadata["carrt.variant"] == "int8"
    assert loaded.metadata["carrt.training_data_digest"] == report.metadata[
        "carrt.training_data_digest"]  # fmt: skip
    assert [t.dtype for t in loaded.inputs] == ["uint8", "float32"]
    model = onnx.load(int8.path)
    assert "QuantizeLinear" in {n.op_type for n in model.graph.node}
    assert graph.external_tensors(model) == []

    # A bound of 0 refuses it, and the int8 file of the previous export does not survive
    # beside a new policy.onnx it no longer matches.
    again = export_policy(checkpoint, out, [str(sim_episodes)], int8=True, max_frames=96,
                          max_mean_mu_error=0.0)  # fmt: skip
    refused = again.variants["int8"]
    assert not refused.written and not refused.skipped and "bound" in refused.reason
    assert math.isfinite(refused.mean_abs_mu)
    assert not int8.path.exists() and out.is_file()


def test_fp16_converts_where_a_provider_runs_it(exported, sim_episodes, tmp_path):
    out, _ = exported
    frames = sample_frames([sim_episodes], max_frames=32)
    # Forced onto the CPU here only to check the conversion and its bookkeeping.
    path = tmp_path / "policy.fp16.onnx"
    report = fp16_variant(
        onnx.load(out), frames, path, Bounds(), 10, providers=["CPUExecutionProvider"]
    )
    assert report.written, report.reason
    assert report.max_abs_mu < 1e-2
    loaded = OnnxPolicy(path, providers=["CPUExecutionProvider"])
    assert loaded.metadata["carrt.variant"] == "fp16"
    assert [t.dtype for t in [*loaded.inputs, *loaded.outputs]] == ["uint8", *["float32"] * 3]

    if not fp16_providers():  # a CPU-only onnxruntime: skipped with a reason, nothing written
        skipped = fp16_variant(onnx.load(out), frames, tmp_path / "x.fp16.onnx", Bounds(), 10)
        assert skipped.skipped and "no fp16-capable execution provider" in skipped.reason
        assert not (tmp_path / "x.fp16.onnx").exists()


# ----------------------------------------------------------------------------- CLI
def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "export", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)  # fmt: skip


def test_cli_exports_and_refuses_a_missing_checkpoint(checkpoint, sim_episodes, tmp_path):
    out = tmp_path / "cli.onnx"
    done = _cli(str(checkpoint), "-o", str(out), "--episodes", str(sim_episodes),
                "--max-frames", "16")  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert f"wrote {out}" in done.stdout and out.is_file()

    missing = _cli(str(tmp_path / "nope.pt"), "-o", str(tmp_path / "x.onnx"),
                   "--episodes", str(sim_episodes))  # fmt: skip
    assert missing.returncode == 2
    lines = missing.stderr.strip().splitlines()
    assert len(lines) == 1 and "nope.pt" in lines[0] and "no such file" in lines[0]
    assert not (tmp_path / "x.onnx").exists()


# ----------------------------------------------------------------------------- throttle ceiling
def test_a_throttle_ceiling_caps_every_plan_and_keeps_the_network(exported, sim_episodes, tmp_path):
    from export.throttle_ceiling import apply_throttle_ceiling

    src, _ = exported
    capped = tmp_path / "capped.onnx"
    apply_throttle_ceiling(src, capped, 0.3)
    before, after = OnnxPolicy(src), OnnxPolicy(capped)
    assert float(after.action_high[1]) == pytest.approx(0.3)
    assert float(after.action_high[0]) == float(before.action_high[0])
    assert after.metadata["carrt.throttle_ceiling"] == "0.3"
    frames = sample_frames([str(sim_episodes)], max_frames=64, seed=0)
    raw_above = 0
    for image, speed in zip(frames.images, frames.speeds[:, 0], strict=True):
        plan_before, plan_after = before.predict(image, speed), after.predict(image, speed)
        raw_above += int((plan_before.mu[:, 1] > 0.3).sum())
        assert (plan_after.mu[:, 1] <= np.float32(0.3)).all()
        np.testing.assert_array_equal(plan_after.mu[:, 0], plan_before.mu[:, 0])
        np.testing.assert_array_equal(plan_after.sigma, plan_before.sigma)
    assert raw_above > 0, "the uncapped plans never exceeded the ceiling: nothing was tested"
    assert onnx.load(str(capped)).graph == onnx.load(str(src)).graph


@pytest.mark.parametrize("ceiling", ["nan", "inf", "0", "1.5", "-0.2"])
def test_a_bad_throttle_ceiling_is_one_line_and_exit_2(exported, tmp_path, ceiling):
    src, _ = exported
    out = tmp_path / "x.onnx"
    done = subprocess.run(
        [sys.executable, "-m", "export.throttle_ceiling", str(src), "-o", str(out),
         "--max-throttle", ceiling],
        capture_output=True, text=True, cwd=ROOT,
    )  # fmt: skip
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "--max-throttle" in lines[0], done.stderr
    assert not out.exists()


def test_a_throttle_ceiling_on_a_file_that_is_no_policy_is_refused(tmp_path):
    from export.throttle_ceiling import apply_throttle_ceiling

    bogus = tmp_path / "bogus.onnx"
    bogus.write_bytes(b"not a model")
    with pytest.raises(UserError, match=r"bogus\.onnx"):
        apply_throttle_ceiling(bogus, tmp_path / "out.onnx", 0.8)
    with pytest.raises(UserError, match="no such file"):
        apply_throttle_ceiling(tmp_path / "missing.onnx", tmp_path / "out.onnx", 0.8)
    assert not (tmp_path / "out.onnx").exists()


def test_a_checkpoint_given_as_the_model_is_named_with_the_command_that_exports_it(checkpoint):
    result = subprocess.run(
        [sys.executable, "-m", "carrt", "drive", "--model", str(checkpoint), "--sim"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert "a PyTorch training checkpoint, not an ONNX model" in result.stderr
    assert f"carrt-export {checkpoint} -o {checkpoint.with_suffix('.onnx')}" in result.stderr
    assert "protobuf" not in result.stderr.lower()
