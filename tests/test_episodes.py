"""Episodes on disk: round trip, format, collision labels, listing.

Every field written comes back, the files are readable with numpy and json alone, a crashed run
and an empty episode still read, collision labels are derived on read (never written) from
measured timestamps, and listing and reading errors name the path. The writer is in
test_episodes_writer.py, summaries, rendering and the CLI in test_episodes_inspect.py.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from episode_factory import assert_step_matches, make_step, metadata, mixed_steps, write_episode

from carrt.episodes import STEP_DTYPE, collision_labels, list_episodes, read_episode
from carrt.episodes import format as fmt
from carrt.episodes.summary import summarize
from carrt.episodes.video import render_video
from carrt.errors import UserError
from carrt.interfaces import Mode
from carrt.model_contract import HORIZON


# ----------------------------------------------------------------------------- round trip
def test_every_field_round_trips(tmp_path):
    steps = mixed_steps()
    meta_in = metadata(
        model_sha256="ab" * 32, model_metadata={"carrt.horizon": "10"}, model_path="p.onnx"
    )
    path = write_episode(tmp_path, steps, meta=meta_in, reason="stopped")
    ep = read_episode(path)
    assert ep.n == len(steps) and not ep.torn and ep.finished
    for record, frame, step in zip(ep.steps, ep.frames, steps, strict=True):
        assert_step_matches(record, frame, step)
    assert ep.duration_s == pytest.approx(2.9)
    np.testing.assert_array_equal(ep.timestamps, [s.frame_captured_at for s in steps])

    meta = ep.meta
    assert meta["schema"] == fmt.SCHEMA and meta["horizon"] == HORIZON
    assert fmt.dtype_from_json(meta["format"]["steps"]["dtype"]) == STEP_DTYPE
    assert meta["car_config"] == {"loop": {"rate_hz": 10.0}}
    assert meta["model"] == {
        "sha256": "ab" * 32,
        "path": "p.onnx",
        "metadata": meta_in["model"]["metadata"],
    }
    assert meta["end"]["reason"] == "stopped" and ep.end_reason == "stopped"
    assert meta["counts"] == {"steps": 30, "dropped": 0}
    for key in ("start", "end"):
        assert {"wall", "monotonic", "time"} <= set(meta[key])
    assert meta["end"]["monotonic"] >= meta["start"]["monotonic"]


def test_the_step_dtype_is_rebuilt_without_pythons_parser(monkeypatch):
    """numpy parses a sub-array format ("(10,)<f4") with ast.literal_eval, which CPython 3.11
    cannot run from two threads at once (gh-106905, a spurious SystemError that stopped a
    study whose chains read episodes side by side); the reader parses shapes itself."""
    import ast

    def refuse(*_a, **_k):
        raise AssertionError("dtype_from_json went through Python's parser")

    spec = fmt.dtype_to_json(STEP_DTYPE)
    assert any(f.startswith("(") for f in spec["formats"]), "the step has sub-arrays"
    monkeypatch.setattr(ast, "literal_eval", refuse)
    rebuilt = fmt.dtype_from_json(spec)
    assert rebuilt == STEP_DTYPE and rebuilt.itemsize == STEP_DTYPE.itemsize
    assert fmt.dtype_from_json(fmt.dtype_to_json(fmt.step_dtype(3))) == fmt.step_dtype(3)


# carrt.episode/1's record as every recorded episode has it: the Step's field table
# (carrt/interfaces.py STEP_FIELDS) must keep making it, byte for byte.
EPISODE_1_RECORD = {
    "names": ["magic", "seq", "index", "frame_captured_at", "command_sent_at", "wall_time",
              "encoder_ticks", "speed_mps", "human_action", "policy_action", "executed_action",
              "plan_mu", "plan_sigma", "mode", "override", "estop", "noise", "collision", "lap",
              "_reserved", "crc"],
    "formats": ["<u4", "<u4", "<i8", "<f8", "<f8", "<f8", "<i8", "<f4", "(2,)<f4", "(2,)<f4",
                "(2,)<f4", "(10, 2)<f4", "(10, 2)<f4", "|u1", "|b1", "|b1", "|b1", "|b1", "|b1",
                "(2,)|u1", "<u4"],
    "offsets": [0, 4, 8, 16, 24, 32, 40, 48, 52, 60, 68, 76, 156, 236, 237, 238, 239, 240, 241,
                242, 244],
    "itemsize": 248,
}  # fmt: skip


def test_the_step_table_makes_the_recorded_layout_and_bytes():
    """The dtype and the Step are both built from one table; what they make is pinned here to
    what carrt.episode/1 has always written (the CRCs of two records packed before the table)."""
    import dataclasses
    import zlib

    from carrt.interfaces import STEP_FIELDS, Step

    assert fmt.dtype_to_json(fmt.step_dtype(10)) == EPISODE_1_RECORD
    assert [f.name for f in dataclasses.fields(Step)] == [f.name for f in STEP_FIELDS]
    assert fmt.FLAGS == ("override", "estop", "noise", "collision", "lap")
    for mode, crc in ((Mode.AUTO, 0x88CC0DC8), (Mode.MANUAL, 0x34817FDE)):
        step = make_step(3, mode=mode, override=True, lap=True)
        assert zlib.crc32(fmt.pack_step(step, step.image.tobytes(), 3)) == crc


def test_frames_are_a_read_only_memmap(tmp_path):
    ep = read_episode(write_episode(tmp_path, mixed_steps(5)))
    assert isinstance(ep.frames, np.memmap)
    assert ep.frames.shape == (5, 96, 96, 3) and ep.frames.dtype == np.uint8
    with pytest.raises(ValueError):
        ep.frames[0, 0, 0, 0] = 1


def test_readable_with_numpy_and_json_alone(tmp_path):
    """What a user without carrt does: the dtype and shapes come from meta.json."""
    steps = mixed_steps(8)
    path = write_episode(tmp_path, steps)
    meta = json.loads((path / "meta.json").read_text())
    spec = meta["format"]["steps"]["dtype"]
    dtype = np.dtype({k: spec[k] for k in ("names", "formats", "offsets", "itemsize")})
    records = np.fromfile(path / meta["format"]["steps"]["file"], dtype=dtype)
    frames = np.memmap(path / meta["format"]["frames"]["file"], dtype=np.uint8, mode="r").reshape(
        -1, *meta["format"]["frames"]["shape"]
    )
    assert len(records) == len(frames) == 8
    for record, frame, step in zip(records, frames, steps, strict=True):
        assert_step_matches(record, frame, step)


def test_plan_is_nan_when_not_auto_and_sized_to_the_episode_horizon(tmp_path):
    plan = np.arange(2 * HORIZON, dtype=np.float32).reshape(HORIZON, 2)
    steps = [make_step(0, mode=Mode.AUTO, plan_mu=plan, plan_sigma=plan + 1), make_step(1)]
    path = write_episode(tmp_path, steps, meta=metadata(horizon=4))
    ep = read_episode(path)
    assert ep.meta["horizon"] == 4 and ep.steps["plan_mu"].shape == (2, 4, 2)
    np.testing.assert_array_equal(ep.steps["plan_mu"][0], plan[:4])
    assert np.isnan(ep.steps["plan_sigma"][1]).all()


def test_zero_step_episode(tmp_path):
    path = write_episode(tmp_path, [])
    ep = read_episode(path)
    assert ep.n == 0 and ep.frames.shape == (0, 96, 96, 3) and not ep.torn
    assert ep.duration_s == 0.0 and len(ep.collision) == 0
    assert summarize(ep)["frames"] == 0
    with pytest.raises(UserError, match="no frames"):
        render_video([ep], tmp_path / "x.mp4")


def test_crashed_run_without_end_metadata_is_readable(tmp_path):
    steps = mixed_steps(6)
    path = write_episode(tmp_path, steps)
    meta = json.loads((path / "meta.json").read_text())
    meta["end"] = meta["end_reason"] = meta["counts"] = None
    (path / "meta.json").write_text(json.dumps(meta))
    (path / "synced.json").unlink()
    ep = read_episode(path)
    assert ep.n == 6 and not ep.finished and ep.end_reason == fmt.END_CRASHED
    assert summarize(ep)["dropped"] is None


# ----------------------------------------------------------------------------- collision labels
def _steps(t, mode=Mode.MANUAL, estop=None, collision=None):
    arr = np.zeros(len(t), dtype=STEP_DTYPE)
    arr["frame_captured_at"] = t
    arr["mode"] = mode if np.isscalar(mode) else np.asarray(mode)
    if estop is not None:
        arr["estop"] = estop
    if collision is not None:
        arr["collision"] = collision
    return arr


def test_collision_flag_labels_the_previous_half_second():
    t = 100.0 + 0.1 * np.arange(30)
    c = np.zeros(30, bool)
    c[20] = True
    labels = collision_labels(_steps(t, collision=c))
    assert labels.dtype == np.uint8
    assert np.flatnonzero(labels).tolist() == [16, 17, 18, 19, 20]  # 5 frames at 10 Hz


def test_estop_edge_counts_only_while_driving():
    n = 30
    t = 100.0 + 0.1 * np.arange(n)
    mode = np.full(n, int(Mode.MANUAL))
    estop = np.zeros(n, bool)
    mode[10:15], estop[10:15] = int(Mode.ESTOP), True  # latched while driving: one event at 10
    mode[15:20] = int(Mode.DISARMED)
    estop[22:25] = True  # pressed while parked: no collision
    mode[20:25] = int(Mode.DISARMED)
    mode[22:25] = int(Mode.ESTOP)
    labels = collision_labels(_steps(t, mode=mode, estop=estop))
    assert np.flatnonzero(labels).tolist() == [6, 7, 8, 9, 10]


def test_end_reason_collision_or_estop_labels_the_last_steps():
    t = 100.0 + 0.1 * np.arange(12)
    steps = _steps(t)
    assert np.flatnonzero(collision_labels(steps, "collision")).tolist() == [7, 8, 9, 10, 11]
    assert np.flatnonzero(collision_labels(steps, "estop")).tolist() == [7, 8, 9, 10, 11]
    assert not collision_labels(steps, "stopped").any()
    assert not collision_labels(steps, None).any()


def test_window_is_by_measured_timestamps_not_by_step_count():
    t = np.array([10.0, 10.3, 10.45, 10.5, 10.55, 10.9, 11.0])  # irregular: dropped frames
    c = np.zeros(len(t), bool)
    c[-1] = True
    labels = collision_labels(_steps(t, collision=c))
    assert labels.tolist() == [0, 0, 0, 0, 1, 1, 1]  # (10.5, 11.0]: 10.5 itself is outside


def test_collision_labels_derived_on_read_never_written(tmp_path):
    steps = [make_step(i, collision=i == 9) for i in range(12)]
    path = write_episode(tmp_path, steps, reason="collision")
    before = (path / "steps.bin").read_bytes()
    ep = read_episode(path)
    assert np.flatnonzero(ep.collision).tolist() == [5, 6, 7, 8, 9, 10, 11]
    assert (path / "steps.bin").read_bytes() == before


# ----------------------------------------------------------------------------- listing
def test_list_episodes_accepts_dirs_episodes_and_several(tmp_path):
    a = write_episode(tmp_path / "day1", [make_step(0)])
    b = write_episode(tmp_path / "day2", [make_step(0)])
    (tmp_path / "day1" / "notes").mkdir()  # unrelated folders are ignored when listing a root
    assert list_episodes(tmp_path / "day1") == [a]
    assert list_episodes(a) == [a] and list_episodes(str(a / "meta.json")) == [a]
    assert set(list_episodes([tmp_path / "day1", b])) == {a, b}


def test_listing_and_reading_errors_name_the_path(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "x").mkdir()
    with pytest.raises(UserError, match=r"no episodes in .*empty"):
        list_episodes(tmp_path / "empty")
    with pytest.raises(UserError, match=r"other is not a carrt episode \(no meta.json\)"):
        read_episode(tmp_path / "other")
    with pytest.raises(UserError, match="does not exist"):
        list_episodes(tmp_path / "nope")
    with pytest.raises(UserError, match="does not exist"):
        read_episode(tmp_path / "nope")
