"""`carrt episodes import IN -o DIR`: a LeRobotDataset v3.0 as carrt episodes.

Each LeRobot episode becomes a carrt episode that `carrt episodes show --verify`, `carrt-train`
and `carrt episodes replay` read like a recorded one: the frames decoded from the video
(within the codec's error: the export's lossless video gives them back within 2/255), every
other field exact. A dataset carrt exported carries all of carrt's fields (`carrt.*`); one
recorded elsewhere is refused in one line naming what it lacks, unless the user names its
camera, action and speed features (`--camera`, `--action`, `--speed KEY[:I]`): then the rest
is filled as a person's drive (executed = action, mode MANUAL, no flags, no plan), and frames
of another size are cropped and shrunk as the car's camera frames are (carrt/camera.py).

Read with pyarrow and PyAV from the format alone, checked as LeRobot's reader checks it: the
version, the features, the columns' shapes, the timestamps at frame_index / fps, every frame
in its video. Each episode is written into NAME.partial and renamed when whole.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from carrt.episodes import format as fmt
from carrt.episodes import lerobot_features as lf
from carrt.episodes.lerobot_export import optional_modules
from carrt.episodes.reader import collision_labels
from carrt.errors import UserError
from carrt.interfaces import Mode
from carrt.model_contract import IMAGE_SHAPE

TIMESTAMP_TOLERANCE_S = 1e-4  # LeRobot's reader's default tolerance_s


@dataclass(frozen=True)
class Mapping:
    """Which features of a dataset recorded elsewhere hold carrt's camera, action and speed."""

    camera: str = lf.CAMERA
    action: str = "action"
    speed: str = "observation.state"
    speed_index: int = 0
    given: bool = False  # the user named them: fill what carrt's fields would hold

    @classmethod
    def parse(cls, camera: str | None, action: str | None, speed: str | None) -> Mapping:
        if camera is None and action is None and speed is None:
            return cls()
        key, _, index = (speed or "observation.state").partition(":")
        if index and not index.isdigit():
            raise UserError(f"--speed {speed}: KEY or KEY:INDEX (an entry of a vector feature)")
        return cls(camera or lf.CAMERA, action or "action", key, int(index or 0), True)


def _load_json(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"{path.parent.parent}: not a LeRobotDataset (no {path.name})") from None
    except (ValueError, OSError) as exc:
        raise UserError(f"{path}: unreadable ({exc})") from None


def _read_table(path: Path) -> Any:
    import pyarrow
    import pyarrow.parquet as pq

    if not path.is_file():
        raise UserError(f"{path}: missing (the dataset's metadata names it)")
    try:
        return pq.read_table(path)
    except (pyarrow.ArrowException, OSError) as exc:
        raise UserError(f"{path}: not a readable parquet file ({exc})") from None


def check_info(root: Path, mapping: Mapping) -> dict[str, Any]:
    info = _load_json(root / lf.INFO)
    version = info.get("codebase_version")
    if version != lf.CODEBASE_VERSION:
        raise UserError(f"{root}: LeRobotDataset {version}, carrt reads {lf.CODEBASE_VERSION} "
                        "(LeRobot converts older ones: lerobot-convert-dataset-v30)")  # fmt: skip
    if info.get("fps") != lf.FPS:
        raise UserError(f"{root}: recorded at {info.get('fps')} fps; carrt's loop is {lf.FPS} Hz")
    features = info.get("features") or {}
    wanted = (mapping.camera, mapping.action, mapping.speed)
    if not mapping.given:
        wanted += lf.CARRT_EXTRAS
    missing = [key for key in wanted if key not in features]
    if missing:
        hint = "" if mapping.given else (
            ": not a carrt export; name its camera, action and speed features with --camera, "
            "--action and --speed KEY[:I] and the rest is filled as a person's drive"
        )  # fmt: skip
        raise UserError(f"{root}: no feature {', '.join(missing)} (it has "
                        f"{', '.join(sorted(features))}){hint}")  # fmt: skip
    if features[mapping.camera].get("dtype") != "video":
        raise UserError(f"{root}: {mapping.camera} is not a video feature")
    if list(features[mapping.action].get("shape", [])) != [2]:
        raise UserError(f"{root}: {mapping.action} has shape {features[mapping.action]['shape']}, "
                        "carrt's action is [steering, throttle]")  # fmt: skip
    return info


def column_values(table: Any, key: str, feature: dict[str, Any], where: Path) -> np.ndarray:
    """A column as (N,) for shape [1] or (N, *shape), checked against info.json's shape."""
    import pyarrow

    if key not in table.column_names:
        raise UserError(f"{where}: no column {key} (info.json declares it)")
    shape = tuple(feature["shape"])
    col = table.column(key).combine_chunks()
    scalar = not pyarrow.types.is_list(col.type) and not pyarrow.types.is_fixed_size_list(col.type)
    if (shape == (1,)) != scalar:
        kind = "a scalar column" if shape == (1,) else "a list column"
        raise UserError(f"{where}: {key} has shape {list(shape)} and should be {kind}, "
                        f"not {col.type}")  # fmt: skip
    if scalar:
        return col.to_numpy(zero_copy_only=False)
    flat = col
    while pyarrow.types.is_list(flat.type) or pyarrow.types.is_fixed_size_list(flat.type):
        flat = flat.flatten()
    values = flat.to_numpy(zero_copy_only=False)
    if values.size != len(col) * int(np.prod(shape)):
        raise UserError(f"{where}: {key} rows are not of shape {list(shape)}")
    return values.reshape(len(col), *shape)


def decode_video(path: Path) -> dict[int, np.ndarray]:
    """Every frame of a video by its frame number (its time × fps)."""
    _, av = optional_modules()
    if not path.is_file():
        raise UserError(f"{path}: missing (the dataset's episodes name it)")
    frames: dict[int, np.ndarray] = {}
    try:
        with av.open(str(path)) as container:
            for frame in container.decode(video=0):
                frames[round(float(frame.time) * lf.FPS)] = frame.to_ndarray(format="rgb24")
    except av.FFmpegError as exc:
        raise UserError(f"{path}: not a readable video ({exc})") from None
    return frames


def _shrink(image: np.ndarray) -> np.ndarray:
    if image.shape == IMAGE_SHAPE:
        return image
    from carrt.camera import preprocess
    from carrt.config import CameraConfig

    return preprocess(image, CameraConfig())


def import_lerobot(source: str | Path, out: str | Path, mapping: Mapping = Mapping()) -> list[Path]:
    """Write one carrt episode per LeRobot episode into `out`; returns their paths."""
    optional_modules()
    root, out = Path(source), Path(out)
    info = check_info(root, mapping)
    features = info["features"]
    episode_files = sorted((root / "meta" / "episodes").glob("*/*.parquet"))
    if not episode_files:
        raise UserError(f"{root}: no meta/episodes/*/*.parquet (not a v3.0 dataset)")
    episodes = [row for path in episode_files for row in _read_table(path).to_pylist()]
    names = [episode_name(row) for row in episodes]
    clash = [name for name in names if (out / name).exists()]
    if clash or len(set(names)) < len(names):
        raise UserError(f"{out / (clash or names)[0]}: exists already: import into another -o")
    out.mkdir(parents=True, exist_ok=True)
    tables: dict[Path, Any] = {}
    videos: dict[Path, dict[int, np.ndarray]] = {}
    written = []
    for row, name in zip(episodes, names, strict=True):
        keys = {"chunk_index": row["data/chunk_index"], "file_index": row["data/file_index"]}
        data_path = root / info["data_path"].format(**keys)
        if data_path not in tables:  # each file read once, however many episodes it holds
            tables[data_path] = _read_table(data_path)
        table = tables[data_path]
        rows = _episode_rows(table, row, data_path)
        video_path = root / info["video_path"].format(
            video_key=mapping.camera,
            chunk_index=row[f"videos/{mapping.camera}/chunk_index"],
            file_index=row[f"videos/{mapping.camera}/file_index"],
        )
        if video_path not in videos:
            videos[video_path] = decode_video(video_path)
        video = videos[video_path]
        first = round(float(row[f"videos/{mapping.camera}/from_timestamp"]) * lf.FPS)
        missing = [k for k in range(len(rows)) if first + k not in video]
        if missing:
            raise UserError(f"{video_path}: episode {row['episode_index']} has {len(rows)} "
                            f"frames, the video lacks {len(missing)} of them (from frame "
                            f"{missing[0]})")  # fmt: skip
        frames = np.stack([_shrink(video[first + k]) for k in range(len(rows))])
        steps = _steps(rows, features, mapping, data_path)
        meta = _meta(row, root, steps.dtype)
        written.append(_write(out / name, steps, frames, meta))
        _check_labels(rows, steps, meta, name)
    return written


def episode_name(row: dict[str, Any]) -> str:
    origin = row.get("carrt/episode")
    if origin is None:
        return f"lerobot-{int(row['episode_index']):06d}"
    first = int(row.get("carrt/first_step") or 0)
    return str(origin) if first == 0 else f"{origin}+{first}"


def _episode_rows(table: Any, row: dict[str, Any], where: Path) -> Any:
    start, stop = int(row["dataset_from_index"]), int(row["dataset_to_index"])
    index = table.column("index").to_numpy()
    chosen = np.flatnonzero((index >= start) & (index < stop))
    rows = table.take(chosen)
    n = len(rows)
    if n != stop - start or n != int(row["length"]):
        raise UserError(f"{where}: episode {row['episode_index']} should have {row['length']} "
                        f"rows (index {start}..{stop - 1}), the file has {n}")  # fmt: skip
    frame_index = rows.column("frame_index").to_numpy()
    timestamp = rows.column("timestamp").to_numpy().astype(np.float64)
    off = np.abs(timestamp - frame_index / lf.FPS)
    if not np.array_equal(frame_index, np.arange(n)) or (off > TIMESTAMP_TOLERANCE_S).any():
        raise UserError(f"{where}: episode {row['episode_index']}: timestamps are not "
                        f"frame_index / {lf.FPS} (off by up to {off.max():.4f} s)")  # fmt: skip
    return rows


def _steps(rows: Any, features: dict, mapping: Mapping, where: Path) -> np.ndarray:
    n = len(rows)
    horizon = int(features.get("carrt.plan_mu", {}).get("shape", [lf.HORIZON])[0])
    steps = np.zeros(n, dtype=fmt.step_dtype(horizon))
    steps["magic"], steps["seq"] = fmt.MAGIC, np.arange(n)
    if not mapping.given:
        for f in lf.FEATURES:
            steps[f.field] = column_values(rows, f.key, features[f.key], where)
    else:  # a person's drive: what carrt would have recorded of it
        action = column_values(rows, mapping.action, features[mapping.action], where)
        speed = column_values(rows, mapping.speed, features[mapping.speed], where)
        t = rows.column("timestamp").to_numpy().astype(np.float64)
        steps["human_action"] = steps["executed_action"] = action
        steps["speed_mps"] = speed if speed.ndim == 1 else speed[:, mapping.speed_index]
        steps["policy_action"], steps["plan_mu"], steps["plan_sigma"] = np.nan, np.nan, np.nan
        steps["mode"], steps["index"] = int(Mode.MANUAL), np.arange(n)
        steps["frame_captured_at"] = steps["command_sent_at"] = t
    for name in ("human_action", "executed_action", "speed_mps"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            values = steps[name].astype(np.float64)
        if np.isinf(values).any() or (name != "human_action" and np.isnan(values).any()):
            raise UserError(f"{where}: {name} holds NaN or infinity")
    return steps


def _meta(row: dict[str, Any], root: Path, dtype: np.dtype) -> dict[str, Any]:
    if row.get("carrt/meta"):  # a carrt export: the recording's own metadata
        meta = json.loads(row["carrt/meta"])
    else:  # recorded elsewhere: a person's drive that ended normally
        meta = {"schema": fmt.SCHEMA, "command": "import", "car_config": None, "model": None,
                "end": {"reason": "stopped"}, "end_reason": "stopped"}  # fmt: skip
    meta["format"] = fmt.format_metadata(dtype)
    meta["horizon"] = dtype.fields["plan_mu"][0].shape[0]
    meta["counts"] = {"steps": int(row["length"]), "dropped": 0}
    meta["origin"] = {
        "episode": row.get("carrt/episode") or f"lerobot-{int(row['episode_index']):06d}",
        "first_step": int(row.get("carrt/first_step") or 0),
    }
    meta["imported"] = {"from": str(root.resolve()), "lerobot_episode": int(row["episode_index"])}
    return meta


def _write(path: Path, steps: np.ndarray, frames: np.ndarray, meta: dict) -> Path:
    partial = path.with_name(path.name + ".partial")
    partial.mkdir(parents=True, exist_ok=True)
    fmt.write_records(partial, steps, frames, meta)
    partial.rename(path)
    fmt.fsync_dir(path.parent)
    return path


def _check_labels(rows: Any, steps: np.ndarray, meta: dict, name: str) -> None:
    """The collision label derived again from the collisions: a label the export carried that
    the steps cannot give (a collision in steps the person excluded) is said, not invented."""
    if lf.LABEL.key not in rows.column_names:
        return
    carried = rows.column(lf.LABEL.key).to_numpy(zero_copy_only=False).astype(bool)
    derived = collision_labels(steps, end_reason=(meta.get("end") or {}).get("reason")) > 0
    lost = int((carried & ~derived).sum())
    if lost:
        import logging

        logging.getLogger("carrt.episodes").warning(
            "%s: %d collision label(s) came from a collision in excluded steps; the imported "
            "episode does not carry them", name, lost,
        )  # fmt: skip
