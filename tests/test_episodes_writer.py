"""The episode writer: many episodes from one writer, fsync progress, its contract, never blocking.

A stalled disk must make write() drop and count steps instead of blocking the loop (or wait, on
simulated time, and keep every step); a caller may reuse its image buffer; an episode that
cannot be created is an error reported, not raised; start and end are measured on the loop's
clock.
"""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest
from episode_factory import assert_step_matches, make_step, metadata

from carrt.episodes import EpisodeWriter, list_episodes, read_episode
from carrt.episodes import writer as writer_mod
from carrt.interfaces import EpisodeSink


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
