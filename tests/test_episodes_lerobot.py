"""LeRobotDataset v3.0 out and in (carrt/episodes/lerobot_export.py, lerobot_import.py): the
round trip exact but for the codec's error on the frames, marks honoured, bad datasets one line
and exit 2. LeRobot's own reader reads the export in tests/test_episodes_lerobot_reader.py."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from episode_factory import mixed_steps, run_cli, write_episode

from carrt.cli import main as carrt
from carrt.episodes import lerobot_features as lf
from carrt.episodes.lerobot_export import IMPORT_KEYS, export_lerobot
from carrt.episodes.lerobot_import import import_lerobot
from carrt.episodes.marks import read_marks
from carrt.episodes.reader import list_episodes, read_episode

STEP_FIELDS = [f.field for f in lf.FEATURES]
LOSSLESS_ERROR = 2  # levels of 255: RGB → 4:4:4 YUV → RGB, rounded twice


def assert_same_steps(a, b) -> None:
    for name in STEP_FIELDS:
        np.testing.assert_array_equal(a.steps[name], b.steps[name], err_msg=name)


def frame_error(a, b) -> int:
    return int(np.abs(np.asarray(a.frames, int) - np.asarray(b.frames, int)).max())


def same_column(a: pa.ChunkedArray, b: pa.ChunkedArray) -> bool:
    """Equal values and type, NaN equal to NaN (Arrow's equals says NaN != NaN)."""
    if a.type != b.type:
        return False
    x, y = (np.asarray(c.to_pylist(), dtype=object) for c in (a, b))
    try:
        return np.array_equal(x.astype(float), y.astype(float), equal_nan=True)
    except (TypeError, ValueError):  # strings, lists of strings
        return a.equals(b)


def crafted(tmp_path: Path) -> Path:
    root = tmp_path / "recorded"
    write_episode(root, mixed_steps(30, seed=1), reason="collision")
    write_episode(root, mixed_steps(25, seed=2))
    return root


def test_recorded_drives_come_back_from_lerobot_exact_but_for_the_codecs_error(
    sim_episodes, tmp_path
):
    dataset, back = tmp_path / "lerobot", tmp_path / "back"
    assert run_cli(["episodes", "export", str(sim_episodes), "--format", "lerobot",
                    "-o", str(dataset)]) == 0  # fmt: skip
    paths = import_lerobot(dataset, back)
    originals = [read_episode(p) for p in list_episodes([str(sim_episodes)])]
    assert [p.name for p in paths] == [ep.path.name for ep in originals]
    for original, path in zip(originals, paths, strict=True):
        imported = read_episode(path, verify_all=True)
        assert imported.damage is None and not imported.torn  # --verify: every CRC holds
        assert_same_steps(original, imported)
        assert frame_error(original, imported) <= LOSSLESS_ERROR
        np.testing.assert_array_equal(original.collision, imported.collision)  # labels again
        ours = {k: v for k, v in original.meta.items() if k != "format"}
        theirs = {k: v for k, v in imported.meta.items() if k not in ("format", *IMPORT_KEYS)}
        assert json.loads(json.dumps(ours)) == theirs
    assert sum(ep.collision.sum() for ep in originals) > 0, "the data has collisions to carry"


def test_export_import_export_is_the_same_dataset(tmp_path):
    first, back, second = tmp_path / "first", tmp_path / "back", tmp_path / "second"
    export_lerobot([str(crafted(tmp_path))], first)
    import_lerobot(first, back)
    export_lerobot([str(back)], second)
    assert json.loads((first / lf.INFO).read_text()) == json.loads((second / lf.INFO).read_text())
    for path in ("data/chunk-000/file-000.parquet", lf.TASKS):
        a, b = pq.read_table(first / path), pq.read_table(second / path)
        assert a.schema.equals(b.schema, check_metadata=True), path
        for name in a.column_names:
            assert same_column(a.column(name), b.column(name)), (path, name)
    a, b = (pq.read_table(d / lf.EPISODES_PATH.format(chunk_index=0, file_index=0))
            for d in (first, second))  # fmt: skip
    for name in a.column_names:  # the frames' statistics move by the codec's error only
        if not name.startswith(f"stats/{lf.CAMERA}/"):
            assert same_column(a.column(name), b.column(name)), name
    stats = (json.loads((d / lf.STATS).read_text()) for d in (first, second))
    for one, other in zip(*(s[lf.CAMERA]["mean"] for s in stats), strict=True):
        assert abs(one[0][0] - other[0][0]) < 1 / 255


def test_excluded_steps_are_never_exported(tmp_path):
    root = crafted(tmp_path)
    first, second = sorted(root.iterdir())
    run_cli(["episodes", "mark", str(first), "--exclude", "1.0-1.5"])
    excluded = read_marks(first).excluded(read_episode(first).timestamps)
    kept = np.flatnonzero(~excluded).tolist()
    assert 0 < len(kept) < 30 and kept[0] == 0 and kept[-1] == 29, "a cut in the middle"
    dataset = tmp_path / "lerobot"
    done = export_lerobot([str(root)], dataset)
    assert done == {"episodes": 2, "lerobot_episodes": 3, "frames": len(kept) + 25}
    rows = pq.read_table(dataset / "data/chunk-000/file-000.parquet")
    steps = rows.column("carrt.step_index").to_pylist()
    episode = rows.column("episode_index").to_pylist()
    assert [s for s, e in zip(steps, episode, strict=True) if e < 2] == kept
    back = import_lerobot(dataset, tmp_path / "back")
    resumed = kept[next(i for i in range(1, len(kept)) if kept[i] != kept[i - 1] + 1)]
    assert [p.name for p in back] == [first.name, f"{first.name}+{resumed}", second.name]
    assert read_episode(back[0]).end_reason == "excluded"  # not the collision: that came later
    assert read_episode(back[1]).end_reason == "collision"


def test_the_dataset_says_what_each_feature_is(tmp_path):
    dataset = tmp_path / "lerobot"
    export_lerobot([str(crafted(tmp_path))], dataset)
    info = json.loads((dataset / lf.INFO).read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == 10
    camera = info["features"][lf.CAMERA]
    assert camera["dtype"] == "video" and camera["info"]["video.codec"] == "h264"
    assert info["features"]["action"]["names"] == ["steering", "throttle"]
    assert set(json.loads((dataset / lf.STATS).read_text())) == set(info["features"])
    docs = (Path(__file__).parents[1] / "docs" / "episodes.md").read_text()
    for feature in (lf.CAMERA, *(f.key for f in lf.ALL_FEATURES)):
        assert f"`{feature}`" in docs, f"docs/episodes.md does not document {feature}"


def export_of(tmp_path: Path) -> Path:
    dataset = tmp_path / "lerobot"
    export_lerobot([str(crafted(tmp_path))], dataset)
    return dataset


def one_line_exit_2(capsys, argv: list[str], *words: str) -> None:
    assert carrt(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    for word in words:
        assert word in err, err


def test_a_damaged_dataset_is_one_line_and_exit_2(tmp_path, capsys):
    dataset = export_of(tmp_path)
    out = str(tmp_path / "out")
    data = dataset / "data/chunk-000/file-000.parquet"
    saved = data.read_bytes()
    data.write_bytes(saved[: len(saved) // 2])
    one_line_exit_2(capsys, ["episodes", "import", str(dataset), "-o", out],
                    "file-000.parquet", "not a readable parquet")  # fmt: skip
    data.write_bytes(saved)
    video = next((dataset / "videos").rglob("*.mp4"))
    video.rename(video.with_suffix(".bak"))
    one_line_exit_2(capsys, ["episodes", "import", str(dataset), "-o", out], "missing")
    video.with_suffix(".bak").rename(video)
    info = json.loads((dataset / lf.INFO).read_text())
    (dataset / lf.INFO).write_text(json.dumps({**info, "codebase_version": "v2.1"}))
    one_line_exit_2(capsys, ["episodes", "import", str(dataset), "-o", out], "v2.1", "v3.0")
    assert not Path(out).exists() or not any(Path(out).iterdir()), "nothing half-imported"


def test_a_feature_of_the_wrong_shape_or_timestamps_off_is_refused(tmp_path, capsys):
    dataset = export_of(tmp_path)
    data = dataset / "data/chunk-000/file-000.parquet"
    table = pq.read_table(data)
    good = table
    i = table.column_names.index("observation.state")
    as_list = pa.array([[v] for v in table.column(i).to_pylist()], pa.list_(pa.float32()))
    pq.write_table(table.set_column(i, "observation.state", as_list), data)
    one_line_exit_2(capsys, ["episodes", "import", str(dataset), "-o", str(tmp_path / "o")],
                    "observation.state", "scalar column")  # fmt: skip
    i = good.column_names.index("timestamp")
    late = pa.array(np.asarray(good.column(i)) + np.float32(0.05), pa.float32())
    pq.write_table(good.set_column(i, "timestamp", late), data)
    one_line_exit_2(capsys, ["episodes", "import", str(dataset), "-o", str(tmp_path / "o")],
                    "timestamps", "0.05")  # fmt: skip


def foreign(tmp_path: Path) -> Path:
    """A dataset recorded elsewhere: other names, no carrt fields, the speed inside a vector."""
    dataset = export_of(tmp_path)
    info = json.loads((dataset / lf.INFO).read_text())
    features = info["features"]
    for key in [k for k in features if k.startswith("carrt.")]:
        del features[key]
    features["observation.images.front"] = features.pop(lf.CAMERA)
    features["observation.state"] = {"dtype": "float32", "shape": [2], "names": ["x", "v"]}
    (dataset / lf.INFO).write_text(json.dumps(info))
    data = dataset / "data/chunk-000/file-000.parquet"
    table = pq.read_table(data)
    table = table.drop([c for c in table.column_names if c.startswith("carrt.")])
    speed = np.asarray(table.column("observation.state"))
    state = pa.FixedSizeListArray.from_arrays(
        pa.array(np.stack([np.zeros_like(speed), speed], 1).ravel()), 2
    )
    i = table.column_names.index("observation.state")
    pq.write_table(table.set_column(i, "observation.state", state), data)
    episodes = dataset / lf.EPISODES_PATH.format(chunk_index=0, file_index=0)
    rows = pq.read_table(episodes)
    rows = rows.drop([c for c in rows.column_names if c.startswith("carrt/")])
    rows = rows.rename_columns([c.replace(lf.CAMERA, "observation.images.front")
                                for c in rows.column_names])  # fmt: skip
    pq.write_table(rows, episodes)
    shutil.move(dataset / "videos" / lf.CAMERA, dataset / "videos" / "observation.images.front")
    return dataset


def test_a_dataset_recorded_elsewhere_is_refused_then_mapped_when_told_how(tmp_path, capsys):
    dataset = foreign(tmp_path)
    out = tmp_path / "mapped"
    one_line_exit_2(capsys, ["episodes", "import", str(dataset), "-o", str(out)],
                    lf.CAMERA, "carrt.mode", "--camera")  # fmt: skip
    assert carrt(["episodes", "import", str(dataset), "-o", str(out), "--camera",
                  "observation.images.front", "--speed", "observation.state:1"]) == 0  # fmt: skip
    original = [read_episode(p) for p in list_episodes([str(tmp_path / "recorded")])]
    imported = [read_episode(p, verify_all=True) for p in list_episodes([str(out)])]
    assert [ep.n for ep in imported] == [ep.n for ep in original]
    for a, b in zip(original, imported, strict=True):
        np.testing.assert_array_equal(a.steps["human_action"], b.steps["human_action"])
        np.testing.assert_array_equal(a.steps["speed_mps"], b.steps["speed_mps"])
        np.testing.assert_array_equal(b.steps["executed_action"], b.steps["human_action"])
        assert b.damage is None and (b.steps["mode"] == 1).all()  # a person's drive
        assert frame_error(a, b) <= LOSSLESS_ERROR


def test_export_needs_a_new_folder_and_leaves_none_half_written(tmp_path, capsys):
    root = crafted(tmp_path)
    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "mine.txt").write_text("a user's file")
    one_line_exit_2(capsys, ["episodes", "export", str(root), "--format", "lerobot",
                             "-o", str(taken)], "exists")  # fmt: skip
    assert (taken / "mine.txt").read_text() == "a user's file"
    assert not (tmp_path / "taken.partial").exists()


def test_imported_episodes_replay_as_the_recorded_ones(sim_episodes, tmp_path):
    """The shipped policy replayed over the drives and over their import: the same actions to
    within what a frame 2/255 off changes."""
    from carrt.episodes import replay
    from carrt.policy import OnnxPolicy
    from carrt.shipped import SHIPPED_MODELS

    export_lerobot([str(sim_episodes)], tmp_path / "lerobot")
    paths = import_lerobot(tmp_path / "lerobot", tmp_path / "back")
    policy = {"shipped": OnnxPolicy(SHIPPED_MODELS["demo"])}
    originals = [read_episode(p) for p in list_episodes([str(sim_episodes)])]
    for original, path in zip(originals, paths, strict=True):
        a, b = replay.replay(original, policy), replay.replay(read_episode(path), policy)
        np.testing.assert_array_equal(a.person, b.person)
        np.testing.assert_array_equal(a.scored, b.scored)
        moved = np.abs(a.actions["shipped"] - b.actions["shipped"])
        assert moved.mean() < 0.01 and moved.max() < 0.1, (moved.mean(), moved.max())
    assert replay.overall([a])["shipped"] == pytest.approx(replay.overall([b])["shipped"], abs=0.02)
