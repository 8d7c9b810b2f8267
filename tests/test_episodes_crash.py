"""Episodes survive what happens to cars: a killed process, a power cut's torn tail, a full disk."""

from __future__ import annotations

import hashlib
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from episode_factory import assert_step_matches, make_step, write_episode

from carrt.episodes import format as fmt
from carrt.episodes import read_episode

TESTS = Path(__file__).parent

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals and rlimits")


def _child(code: str, *args: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), str(TESTS.parent)])}
    return subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(code), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


def _digest(path: Path) -> dict[str, str]:
    return {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in sorted(path.iterdir())}


def _assert_prefix(ep, seed: int) -> None:
    for i, (record, frame) in enumerate(zip(ep.steps, ep.frames, strict=True)):
        assert_step_matches(record, frame, make_step(i, seed=seed))


RECORDER = """
    import sys, time
    from episode_factory import make_step, metadata
    from carrt.episodes import EpisodeWriter

    writer = EpisodeWriter(sys.argv[1], queue_steps=64, sync_every_s=0.2)
    writer.begin(metadata())
    for i in range(30):
        assert writer.write(make_step(i, seed=1))
    writer.end("stopped")
    assert writer.flush()
    print("finished", writer.last_episode_path, flush=True)
    writer.begin(metadata())
    i = 0
    while True:
        ok = writer.write(make_step(i, seed=2))
        i += 1
        print("step", i, writer.synced, writer.written, int(ok), flush=True)
        time.sleep(0.01)
"""


def test_sigkill_mid_recording_keeps_earlier_episodes_and_the_synced_steps(tmp_path):
    root = tmp_path / "episodes"
    child = _child(RECORDER, str(root))
    try:
        finished = Path(child.stdout.readline().split()[1])
        before = _digest(finished)
        synced = 0
        deadline = time.monotonic() + 20
        while synced < 40 and time.monotonic() < deadline:
            line = child.stdout.readline().split()
            assert line and line[0] == "step", child.stderr.read()
            synced = int(line[2])
        child.send_signal(signal.SIGKILL)
        child.wait(10)
    finally:
        if child.poll() is None:
            child.kill()
        child.stdout.close()
        child.stderr.close()
    assert synced >= 40

    assert _digest(finished) == before
    done = read_episode(finished, verify_all=True)
    assert done.n == 30 and done.finished and not done.torn
    _assert_prefix(done, seed=1)

    current = [p for p in root.iterdir() if p != finished]
    assert len(current) == 1
    ep = read_episode(current[0], verify_all=True)
    assert not ep.finished and ep.end_reason == fmt.END_CRASHED
    assert ep.n >= synced  # every step synced before the kill is there
    _assert_prefix(ep, seed=2)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    return write_episode(tmp_path_factory.mktemp("src"), [make_step(i) for i in range(40)])


def _power_cut_copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    meta = json.loads((dst / fmt.META).read_text())
    meta["end"] = meta["end_reason"] = meta["counts"] = None  # the end never got written
    (dst / fmt.META).write_text(json.dumps(meta))
    return dst


def _truncate(path: Path, size: int, garbage: bytes) -> None:
    with open(path, "r+b") as f:
        f.truncate(size)
        f.seek(0, os.SEEK_END)
        f.write(garbage)


@pytest.mark.parametrize("seed", range(12))
def test_torn_tail_is_recovered_by_the_reader(recorded, tmp_path, seed):
    rng = random.Random(seed)
    ep_dir = _power_cut_copy(recorded, tmp_path / "ep")
    itemsize = read_episode(recorded).steps.dtype.itemsize
    frames_cut = rng.randrange(0, 40 * fmt.FRAME_BYTES + 1)
    steps_cut = rng.randrange(0, 40 * itemsize + 1)
    whole = min(frames_cut // fmt.FRAME_BYTES, steps_cut // itemsize)
    kinds = [b"", bytes(rng.randrange(1, 5000)), rng.randbytes(rng.randrange(1, 5000))]
    _truncate(ep_dir / fmt.FRAMES, frames_cut, rng.choice(kinds))
    _truncate(ep_dir / fmt.STEPS, steps_cut, rng.choice(kinds))
    synced = ep_dir / fmt.SYNCED
    choice = rng.randrange(3)
    if choice == 0:
        synced.unlink()
    elif choice == 1:
        synced.write_text('{"ste')  # torn itself: means "check everything"
    else:
        synced.write_text(json.dumps({"steps": rng.randrange(0, whole + 1)}))

    ep = read_episode(ep_dir)
    assert ep.n == whole
    _assert_prefix(ep, seed=0)
    assert ep.torn == (
        (ep_dir / fmt.FRAMES).stat().st_size != whole * fmt.FRAME_BYTES
        or (ep_dir / fmt.STEPS).stat().st_size != whole * itemsize
    )
    assert len(ep.collision) == whole
    assert read_episode(ep_dir, verify_all=True).n == whole


@pytest.mark.parametrize("target", [fmt.FRAMES, fmt.STEPS])
def test_corruption_after_the_synced_point_cuts_the_episode_there(recorded, tmp_path, target):
    ep_dir = _power_cut_copy(recorded, tmp_path / "ep")
    (ep_dir / fmt.SYNCED).write_text(json.dumps({"steps": 20}))
    size = fmt.FRAME_BYTES if target == fmt.FRAMES else read_episode(recorded).steps.dtype.itemsize
    with open(ep_dir / target, "r+b") as f:
        f.seek(27 * size + size // 2)
        byte = f.read(1)
        f.seek(-1, os.SEEK_CUR)
        f.write(bytes([byte[0] ^ 0x40]))
    ep = read_episode(ep_dir)
    assert ep.n == 27 and ep.torn
    _assert_prefix(ep, seed=0)


def test_verify_all_checks_below_the_synced_point(recorded, tmp_path):
    ep_dir = tmp_path / "ep"
    shutil.copytree(recorded, ep_dir)
    with open(ep_dir / fmt.FRAMES, "r+b") as f:
        f.seek(5 * fmt.FRAME_BYTES + 100)
        f.write(b"\xff\x00\xff")
    assert read_episode(ep_dir).n == 40  # synced steps are trusted: opening stays fast
    assert read_episode(ep_dir, verify_all=True).n == 5


FULL_DISK = """
    import json, resource, signal, sys, time
    from episode_factory import make_step, metadata
    from carrt.episodes import EpisodeWriter

    limit = int(sys.argv[2])
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    writer = EpisodeWriter(sys.argv[1], queue_steps=500, sync_every_s=0.05)
    writer.begin(metadata())
    accepted = []
    for i in range(80):
        accepted.append(writer.write(make_step(i)))
        if i == 60:
            writer.flush()
    full_path = writer.last_episode_path
    writer.end("stopped")
    writer.flush()
    error = writer.error
    writer.begin(metadata())  # the next episode starts afresh (each file has its own limit)
    ok = [writer.write(make_step(i, seed=5)) for i in range(5)]
    writer.close()
    print(json.dumps({
        "accepted": accepted, "error": error, "written": writer.written,
        "dropped": writer.dropped, "full": str(full_path), "next": str(writer.last_episode_path),
        "next_ok": ok, "final_error": writer.error,
    }))
"""


def test_full_disk_stops_the_episode_cleanly(tmp_path):
    limit = 1 << 20
    child = _child(FULL_DISK, str(tmp_path), str(limit))
    out, err = child.communicate(timeout=60)
    assert child.returncode == 0, err
    result = json.loads(out)
    fits = limit // fmt.FRAME_BYTES  # 37 frames fit under a 1 MiB file-size limit

    assert "disk full" in result["error"] and "stopped after" in result["error"]
    ep = read_episode(result["full"], verify_all=True)
    assert ep.n == fits and not ep.torn  # the half-written step was cut off
    _assert_prefix(ep, seed=0)
    assert ep.end_reason == fmt.END_DISK_FULL and ep.meta["end"]["requested"]["reason"] == "stopped"
    assert ep.meta["counts"] == {"steps": fits, "dropped": 80 - fits}
    assert result["accepted"][61:] == [False] * 19  # after the error write() refuses at once

    nxt = read_episode(result["next"])
    assert result["next_ok"] == [True] * 5 and nxt.n == 5 and nxt.end_reason == "stopped"
    assert result["written"] == fits + 5 and result["dropped"] == 80 - fits
    assert np.array_equal(nxt.frames[0], make_step(0, seed=5).image)
