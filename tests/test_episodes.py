"""Episodes: round trip, format, collision labels, listing, summaries, rendering, never blocking."""

from __future__ import annotations

import argparse
import json
import threading
import time

import cv2
import numpy as np
import pytest
from episode_factory import assert_step_matches, make_step, metadata, write_episode

from carrt.episodes import (
    STEP_DTYPE,
    EpisodeWriter,
    collision_labels,
    list_episodes,
    read_episode,
    video,
)
from carrt.episodes import cli as episodes_cli
from carrt.episodes import format as fmt
from carrt.episodes import writer as writer_mod
from carrt.episodes.contact_sheet import render_contact_sheet
from carrt.episodes.summary import summarize
from carrt.episodes.video import render_video
from carrt.errors import UserError
from carrt.interfaces import HORIZON, EpisodeSink, Mode


def mixed_steps(n: int = 30, seed: int = 0) -> list:
    """Every mode and flag appears; AUTO steps carry a plan."""
    modes = [Mode.DISARMED, Mode.MANUAL, Mode.AUTO, Mode.AUTO, Mode.MANUAL, Mode.ESTOP]
    steps = []
    for i in range(n):
        mode = modes[i % len(modes)]
        steps.append(
            make_step(
                i,
                seed=seed,
                mode=mode,
                override=i % 7 == 3,
                estop=mode == Mode.ESTOP,
                collision=i == 17,
                lap=i % 10 == 5,
            )
        )
    return steps


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


def test_one_writer_many_episodes_sorted_and_untouched(tmp_path):
    with EpisodeWriter(tmp_path, queue_steps=64) as writer:
        assert isinstance(writer, EpisodeSink)
        paths, digests = [], []
        for e in range(3):
            writer.begin(metadata())
            for i in range(5 + e):
                assert writer.write(make_step(i, seed=e))
            writer.end("stopped")
            assert writer.flush()
            paths.append(writer.last_episode_path)
            digests.append({f.name: f.read_bytes() for f in paths[-1].iterdir()})
        assert writer.written == 5 + 6 + 7 and writer.dropped == 0 and writer.episodes == 3
    assert list_episodes(tmp_path) == sorted(paths) == paths
    for path, files in zip(paths, digests, strict=True):
        assert {f.name: f.read_bytes() for f in path.iterdir()} == files
    assert [read_episode(p).n for p in paths] == [5, 6, 7]


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


def test_synced_file_follows_fsyncs_while_recording(tmp_path):
    with EpisodeWriter(tmp_path, sync_every_s=0.1) as writer:
        writer.begin(metadata())
        for i in range(5):
            writer.write(make_step(i))
        deadline = time.monotonic() + 2.0
        while writer.synced < 5 and time.monotonic() < deadline:
            time.sleep(0.01)
        synced = json.loads((writer.last_episode_path / "synced.json").read_text())
        assert writer.synced == 5 and synced == {"steps": 5}
        assert read_episode(writer.last_episode_path).n == 5


# ----------------------------------------------------------------------------- writer contract
def test_write_outside_an_episode_and_bad_images(tmp_path):
    with EpisodeWriter(tmp_path) as writer:
        assert writer.write(make_step(0)) is False
        assert writer.dropped == 0
        writer.begin(metadata())
        with pytest.raises(ValueError, match="uint8"):
            writer.write(make_step(0, image=np.zeros((96, 96), np.uint8)))
        with pytest.raises(ValueError, match="may not set"):
            writer.begin({"schema": "x"})


def test_caller_may_reuse_its_image_buffer(tmp_path):
    buffer = np.zeros((96, 96, 3), np.uint8)
    with EpisodeWriter(tmp_path) as writer:
        writer.begin(metadata())
        for value in (10, 20, 30):
            buffer[:] = value
            writer.write(make_step(value, image=buffer))
        buffer[:] = 0
    ep = read_episode(writer.last_episode_path)
    assert [int(f[0, 0, 0]) for f in ep.frames] == [10, 20, 30]


def test_cannot_create_episode_reports_error_without_raising(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with EpisodeWriter(blocker / "episodes") as writer:
        writer.begin(metadata())
        assert writer.flush()
        assert writer.write(make_step(0)) is False
        assert "cannot start an episode" in writer.error
        assert writer.dropped == 1 and not writer.recording


@pytest.fixture
def stalled_disk(monkeypatch) -> threading.Event:
    """Every write to the episode files waits (up to 10 s) until the returned event is set."""
    release = threading.Event()
    real_write = writer_mod.write_all

    def stalled_write(fd, data):
        release.wait(10)
        real_write(fd, data)

    monkeypatch.setattr(writer_mod, "write_all", stalled_write)
    return release


def test_stalled_disk_drops_and_counts_instead_of_blocking(tmp_path, stalled_disk):
    release = stalled_disk
    queue = 8
    writer = EpisodeWriter(tmp_path, queue_steps=queue)
    writer.begin(metadata())
    steps = [make_step(i) for i in range(200)]
    accepted, durations = [], []
    for step in steps:
        start = time.perf_counter()
        accepted.append(writer.write(step))
        durations.append(time.perf_counter() - start)
    # The thread holds at most one step; the queue holds `queue`; everything else is dropped.
    assert queue <= sum(accepted) <= queue + 1
    assert writer.dropped == len(steps) - sum(accepted)
    assert np.median(durations) < 100e-6, f"median write() {np.median(durations) * 1e6:.0f} us"
    # The disk is stalled for 10 s: any write() that waited for it would take seconds.
    assert max(durations) < 0.05, f"slowest write() {max(durations) * 1e3:.1f} ms"
    release.set()
    writer.end("stopped")
    writer.close()
    ep = read_episode(writer.last_episode_path)
    kept = [s for s, ok in zip(steps, accepted, strict=True) if ok]
    assert ep.n == len(kept) and ep.meta["counts"]["dropped"] == writer.dropped
    for record, frame, step in zip(ep.steps, ep.frames, kept, strict=True):
        assert_step_matches(record, frame, step)


def test_writer_on_simulated_time_waits_for_a_stalled_disk_and_keeps_every_step(
    tmp_path, stalled_disk
):
    """Faster than real time a dropped step is training data lost (and lost differently from run
    to run): the simulator's writer waits for room instead."""
    threading.Timer(0.3, stalled_disk.set).start()  # the disk comes back after 0.3 s
    writer = EpisodeWriter(tmp_path, queue_steps=8, wait_when_full=True)
    writer.begin(metadata())
    steps = [make_step(i) for i in range(200)]
    start = time.perf_counter()
    accepted = [writer.write(step) for step in steps]
    waited = time.perf_counter() - start
    writer.end("stopped")
    writer.close()
    assert all(accepted) and writer.dropped == 0
    assert waited >= 0.2, f"write() returned in {waited:.2f} s while the disk was stalled"
    ep = read_episode(writer.last_episode_path)
    assert ep.n == len(steps) and ep.meta["counts"]["dropped"] == 0
    for record, frame, step in zip(ep.steps, ep.frames, steps, strict=True):
        assert_step_matches(record, frame, step)


def test_waiting_writer_whose_thread_died_drops_instead_of_hanging(tmp_path):
    writer = EpisodeWriter(tmp_path, queue_steps=2, wait_when_full=True)
    writer.begin(metadata())
    writer._put(("stop",))  # the thread ends, as if it had died
    writer._thread.join(5)
    start = time.perf_counter()
    accepted = [writer.write(make_step(i)) for i in range(5)]
    assert accepted == [True, True, False, False, False] and writer.dropped == 3
    assert time.perf_counter() - start < 5


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


# ----------------------------------------------------------------------------- inspection
def test_summary_counts(tmp_path):
    steps = []
    for i in range(20):
        mode = Mode.MANUAL if i < 16 else Mode.ESTOP
        steps.append(
            make_step(
                i,
                mode=mode,
                speed_mps=1.0 if i % 2 else 2.0,
                override=i in (3, 8),
                estop=i >= 16,
                noise=i < 5,
            )
        )
    steps[17].speed_mps = 9.0  # while in ESTOP: not part of the driving speed
    ep = read_episode(
        write_episode(tmp_path, steps, reason="estop", meta=metadata(model_sha256="f" * 64))
    )
    s = summarize(ep)
    assert s["frames"] == 20 and s["duration_s"] == pytest.approx(1.9)
    assert s["avg_speed_mps"] == pytest.approx(1.5) and s["top_speed_mps"] == pytest.approx(2.0)
    assert s["interventions"] == 2 and s["estops"] == 1 and s["noise_share"] == 0.25
    assert s["collisions"] == 2  # the e-stop edge at 16, and the end reason at 19
    assert s["collision_frames"] == 8  # 12..16 for the edge, 15..19 for the end
    assert s["end_reason"] == "estop"
    assert s["model_sha256"] == "f" * 64 and s["dropped"] == 0


@pytest.mark.parametrize("suffix", [".mp4", ".avi"])
def test_video_holds_every_episode_and_decodes(tmp_path, suffix):
    first = read_episode(write_episode(tmp_path / "a", mixed_steps(12)))
    second = read_episode(write_episode(tmp_path / "b", mixed_steps(5)))
    out = render_video([first, second], tmp_path / f"ep{suffix}", fps=10, scale=2)
    cap = cv2.VideoCapture(str(out))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame)
    cap.release()
    assert len(frames) == 17, "both episodes, every frame"
    assert frames[0].shape == (192, 192 + video.PANEL_W, 3)


def test_mp4_is_h264_a_browser_plays(tmp_path):
    """H.264 High, yuv420p, the moov atom before the media (playback starts while loading)."""
    import av

    ep = read_episode(write_episode(tmp_path, mixed_steps(12)))
    out = render_video([ep], tmp_path / "ep.mp4")
    with av.open(str(out)) as container:
        (stream,) = container.streams.video
        assert stream.codec_context.name == "h264"
        assert stream.codec_context.pix_fmt == "yuv420p"
        assert stream.codec_context.profile == "High"
        assert (stream.width, stream.height) == (384 + video.PANEL_W, 384)
        assert sum(1 for _ in container.decode(stream)) == 12
    head = out.read_bytes()[:4096]
    assert head.find(b"moov") != -1 and head.find(b"moov") < out.read_bytes().find(b"mdat")


def test_the_overlay_draws_the_actions_and_the_plan(tmp_path):
    ep = read_episode(write_episode(tmp_path, mixed_steps(12)))
    panel = video.compose(ep, 3)[:, 384:]
    other = video.compose(ep, 7)[:, 384:]
    assert panel.shape == (384, video.PANEL_W, 3)
    assert (panel != other).any(), "the panel follows the step"
    assert panel[250:, :].std() > 5, "the plan's lines are drawn"


def test_a_wrong_video_suffix_is_refused(tmp_path):
    ep = read_episode(write_episode(tmp_path, mixed_steps(3)))
    with pytest.raises(UserError, match=r"\.mp4 \(H\.264\)"):
        render_video([ep], tmp_path / "ep.mov")


def test_contact_sheet_decodes(tmp_path):
    ep = read_episode(write_episode(tmp_path, mixed_steps(25)))
    out = render_contact_sheet(ep, tmp_path / "sheet.png", every=2)
    sheet = cv2.imread(str(out))
    assert sheet.shape == (2 * (96 + 12), 10 * 96, 3)  # 13 tiles in rows of 10
    # tile 0 is frame 0 (RGB on disk, BGR in the PNG)
    np.testing.assert_array_equal(sheet[:96, :96, ::-1], ep.frames[0])


# ----------------------------------------------------------------------------- CLI
def _cli(argv):
    parser = argparse.ArgumentParser(prog="carrt")
    episodes_cli.add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_ls_show_video(tmp_path, capsys):
    path = write_episode(tmp_path, mixed_steps(10))
    assert _cli(["episodes", "ls", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert path.name in out and "stopped" in out and "1 episodes" in out
    assert _cli(["episodes", "show", str(path)]) == 0
    out = capsys.readouterr().out
    assert "interventions" in out and '"car_config"' not in out and len(out.splitlines()) < 30
    assert _cli(["episodes", "show", str(path), "--meta"]) == 0
    assert '"car_config"' in capsys.readouterr().out
    assert _cli(["episodes", "show", str(path), "--json", "--verify"]) == 0
    assert json.loads(capsys.readouterr().out)["frames"] == 10
    assert _cli(["episodes", "video", str(path), "--sheet", str(tmp_path / "s.png")]) == 0
    assert (tmp_path / "s.png").is_file()
    assert _cli(["episodes", "video", str(path), "-o", str(tmp_path / "v.avi")]) == 0
    assert (tmp_path / "v.avi").stat().st_size > 0
    (tmp_path / "void").mkdir()
    with pytest.raises(UserError, match="no episodes in"):
        _cli(["episodes", "ls", str(tmp_path / "void")])


def test_start_and_end_are_measured_on_the_loops_clock(tmp_path):
    class SimClock:  # an interfaces.Clock, as the simulator's loop has
        t = 50.0

        def now(self):
            return self.t

        def sleep_until(self, deadline):
            self.t = max(self.t, deadline)

    clock = SimClock()
    with EpisodeWriter(tmp_path, clock=clock) as writer:
        writer.begin(metadata())
        writer.write(make_step(0))
        clock.t = 61.5
        writer.end("stopped")
    meta = read_episode(writer.last_episode_path).meta
    assert meta["start"]["monotonic"] == 50.0 and meta["end"]["monotonic"] == 61.5
    assert meta["end_reason"] == "stopped"
