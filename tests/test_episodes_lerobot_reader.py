"""carrt's LeRobotDataset export read by LeRobot's own reader (`LeRobotDataset` of
lerobot-dataset 0.4.4 through torchcodec, in the venv `make test` builds for it: see
tests/lerobot_reader.py): every frame read back, every field exact, the timestamps within the
reader's tolerance (it decodes each frame at its timestamp and refuses one more than 1e-4 s
off), one LeRobot episode per piece between excluded steps."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from episode_factory import run_cli

from carrt.episodes import lerobot_features as lf
from carrt.episodes.lerobot_export import export_lerobot
from carrt.episodes.marks import apply_marks
from carrt.episodes.reader import list_episodes, read_episode

REPO = Path(__file__).resolve().parents[1]
READER_PY = Path(os.environ.get("CARRT_LEROBOT_PYTHON", REPO / ".venv-lerobot/bin/python"))


@pytest.fixture(scope="module")
def read_back(sim_episodes, tmp_path_factory):
    """Two exports of the simulator's drives (lossless, and for browsers with one episode cut
    in two by a mark) and what LeRobot's reader gave for each."""
    assert READER_PY.exists(), f"{READER_PY}: LeRobot's reader's venv; make test builds it"
    tmp = tmp_path_factory.mktemp("lerobot")
    marked = tmp / "marked"
    shutil.copytree(sim_episodes, marked)
    first = list_episodes([str(marked)])[0]
    run_cli(["episodes", "mark", str(first), "--exclude", "2.0-3.0"])
    export_lerobot([str(sim_episodes)], tmp / "lossless")
    export_lerobot([str(marked)], tmp / "browser", video="browser")
    out = tmp / "read.npz"
    done = subprocess.run(
        [str(READER_PY), str(REPO / "tests" / "lerobot_reader.py"), str(out),
         str(tmp / "lossless"), str(tmp / "browser")],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    with np.load(out) as saved:
        arrays = {key: saved[key] for key in saved.files}
    about = json.loads(str(arrays.pop("about")))
    parts = {
        "lossless": [read_episode(p) for p in list_episodes([str(sim_episodes)])],
        "browser": [s for p in list_episodes([str(marked)]) for s in apply_marks(read_episode(p))],
    }
    return arrays, about, parts


def test_every_frame_and_field_comes_back_through_lerobots_reader(read_back):
    arrays, about, parts = read_back
    episodes = parts["lossless"]
    total = sum(ep.n for ep in episodes)
    assert about[0]["len"] == total and about[0]["num_episodes"] == len(episodes)
    assert about[0]["fps"] == 10 and about[0]["tasks"] == [lf.TASK]
    frames = np.concatenate([np.asarray(ep.frames) for ep in episodes])
    error = np.abs(arrays[f"0/{lf.CAMERA}"].astype(int) - frames.astype(int))
    assert error.max() <= 2, f"lossless video: worst pixel {error.max()} levels off"
    steps = np.concatenate([ep.steps for ep in episodes])
    for feature in lf.FEATURES:  # the person's action a*, the speed and every carrt field
        values = lf.column(steps, feature)
        if feature.dtype == "float64":  # the file holds them exactly (the import reads them so);
            values = values.astype(np.float32)  # the reader makes a scalar a float32 tensor
        np.testing.assert_array_equal(arrays[f"0/{feature.key}"], values, err_msg=feature.key)
    labels = np.concatenate([ep.collision for ep in episodes]).astype(bool)
    np.testing.assert_array_equal(arrays[f"0/{lf.LABEL.key}"], labels)
    assert labels.any(), "the drives' collisions are labelled"
    frame_index = np.concatenate([np.arange(ep.n) for ep in episodes])
    np.testing.assert_allclose(arrays["0/timestamp"], frame_index / 10, atol=1e-4)
    assert set(about[0]["stats"]) >= {lf.CAMERA, "action", "observation.state"}


def test_a_marked_episode_is_two_lerobot_episodes_without_its_excluded_steps(read_back):
    arrays, about, parts = read_back
    pieces = parts["browser"]
    assert len(pieces) == len(parts["lossless"]) + 1, "the mark cut one episode in two"
    assert about[1]["num_episodes"] == len(pieces)
    assert [b - a for a, b in about[1]["bounds"]] == [p.n for p in pieces]
    steps = np.concatenate([p.steps["index"] for p in pieces])
    np.testing.assert_array_equal(arrays["1/carrt.step_index"], steps)
    frames = np.concatenate([np.asarray(p.frames) for p in pieces]).astype(int)
    error = np.abs(arrays[f"1/{lf.CAMERA}"].astype(int) - frames)
    assert error.mean() < 5, "4:2:0 video: the colour edges blur, the frames are the same"
