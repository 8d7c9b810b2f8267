"""`carrt episodes export DIR… --format lerobot -o OUT`: episodes as a LeRobotDataset v3.0.

Why: LeRobot users train their policies (ACT, diffusion, …) on LeRobotDataset, share datasets
on the Hugging Face Hub and look at them in its visualiser; a carrt recording in that format
goes there as it is. Written from the format alone, with pyarrow and PyAV (no torch, nothing
from LeRobot), and checked by LeRobot's own reader in the tests.

What goes out: one LeRobot episode per carrt episode, or per run of steps between excluded
ranges (marks are honoured: an excluded step is never exported); the camera as an H.264 video
(yuv420p, a keyframe every GOP frames so the reader seeks fast), the speed as
`observation.state`, the person's action a* as `action`, everything else a carrt step holds as
`carrt.*` features (lerobot_features.py), each episode's carrt metadata as a JSON column of
meta/episodes, and meta/stats.json. The dataset is written into OUT.partial and renamed to OUT
when whole, so an interrupted export never leaves a dataset that looks complete.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from carrt.episodes import format as fmt
from carrt.episodes import lerobot_features as lf
from carrt.episodes import lerobot_stats as ls
from carrt.episodes.marks import apply_marks
from carrt.episodes.reader import Episode, in_order, list_episodes, read_episode
from carrt.errors import UserError

# The camera's H.264: (pixel format, x264 CRF). lossless gives the frames back within 2/255
# through LeRobot's reader (RGB to YUV and back), at ~3.2 kB a frame; browser is what browsers
# and the Hub's visualiser play (4:2:0 chroma: up to ~200/255 off at a sharp colour edge of a
# simulator frame, ~2 on average), at ~2.4 kB. Measured in docs/episodes.md.
VIDEO = {"lossless": ("yuv444p", 0), "browser": ("yuv420p", 18)}
GOP = 10  # a keyframe a second: the reader decodes at most 9 frames to reach any frame
END_EXCLUDED = "excluded"  # a segment's end reason when the steps after it were excluded
IMPORT_KEYS = ("imported", "origin")  # meta the import adds: not the recording's own


def optional_modules() -> tuple[Any, Any]:
    """(pyarrow, av), or one line naming the extra that has them."""
    try:
        import av
        import pyarrow
        import pyarrow.parquet
    except ImportError as exc:
        raise UserError(
            f"LeRobot datasets need pyarrow and PyAV ({exc.name} is missing): "
            "pip install 'carrt[laptop]'"
        ) from None
    return pyarrow, av


@dataclass
class Part:
    """One LeRobot episode: a carrt episode or a segment of it."""

    episode: Episode
    index: int  # episode_index
    meta: dict[str, Any]  # the carrt metadata it carries
    chunk: int = 0
    file: int = 0
    from_index: int = 0  # dataset_from_index
    from_frame: int = 0  # its first frame in its video file


def parts_of(paths: list[str]) -> list[Part]:
    """Every episode's kept segments, in recording order, with the metadata each carries."""
    parts: list[Part] = []
    for path in in_order(paths) if len(paths) > 1 else list_episodes(paths):
        ep = read_episode(path)
        kept = [seg for seg in apply_marks(ep) if seg.n > 0]
        for k, seg in enumerate(kept):
            meta = {key: v for key, v in ep.meta.items() if key not in ("format", *IMPORT_KEYS)}
            origin = ep.meta.get("origin") or {"episode": ep.path.name, "first_step": 0}
            meta["origin"] = {"episode": origin["episode"],
                              "first_step": int(origin["first_step"]) + seg.start}  # fmt: skip
            if k < len(kept) - 1 or seg.start + seg.n < ep.n:
                meta["end"] = {**(meta.get("end") or {}), "reason": END_EXCLUDED}
                meta["end_reason"] = END_EXCLUDED
            parts.append(Part(seg, len(parts), meta))
    if not parts:
        raise UserError(f"{' '.join(paths)}: no steps to export (none recorded, or all excluded)")
    return parts


def place(parts: list[Part]) -> None:
    """Each part's data and video file (an episode never spans two) and where it starts."""
    file_no = frames_in_file = total = 0
    for part in parts:
        if frames_in_file and frames_in_file + part.episode.n > lf.FRAMES_PER_FILE:
            file_no, frames_in_file = file_no + 1, 0
        part.chunk, part.file = divmod(file_no, lf.CHUNKS_SIZE)
        part.from_index, part.from_frame = total, frames_in_file
        frames_in_file += part.episode.n
        total += part.episode.n


def export_lerobot(paths: list[str], out: str | Path, video: str = "lossless") -> dict[str, Any]:
    """Write the dataset; returns what was written (episodes, frames, excluded steps)."""
    pa, av = optional_modules()
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise UserError(f"-o {out} exists: export into a new folder")
    parts = parts_of(paths)
    place(parts)
    partial = out.with_name(out.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    files = sorted({(p.chunk, p.file) for p in parts})
    for chunk, file in files:
        group = [p for p in parts if (p.chunk, p.file) == (chunk, file)]
        keys = {"chunk_index": chunk, "file_index": file}
        where = partial / lf.VIDEO_PATH.format(video_key=lf.CAMERA, **keys)
        _write_video(av, where, group, *VIDEO[video])
        _write_parquet(pa, partial / lf.DATA_PATH.format(**keys), data_table(pa, group))
    episode_rows, stats = episodes_table(pa, parts)
    _write_parquet(pa, partial / lf.EPISODES_PATH.format(chunk_index=0, file_index=0),
                   episode_rows)  # fmt: skip
    _write_parquet(pa, partial / lf.TASKS, tasks_table(pa))
    total = sum(p.episode.n for p in parts)
    info = {
        "codebase_version": lf.CODEBASE_VERSION, "robot_type": "carrt",
        "total_episodes": len(parts), "total_frames": total, "total_tasks": 1,
        "chunks_size": lf.CHUNKS_SIZE, "data_files_size_in_mb": 100,
        "video_files_size_in_mb": 200, "fps": lf.FPS, "splits": {"train": f"0:{len(parts)}"},
        "data_path": lf.DATA_PATH, "video_path": lf.VIDEO_PATH,
        "features": lf.info_features("h264", VIDEO[video][0]),
    }  # fmt: skip
    fmt.write_json_atomic(partial / lf.INFO, info)
    fmt.write_json_atomic(partial / lf.STATS, ls.to_json(stats))
    if out.exists():
        out.rmdir()  # the empty folder the user named
    partial.rename(out)
    fmt.fsync_dir(out.parent)
    episodes = {p.episode.path for p in parts}
    return {"episodes": len(episodes), "lerobot_episodes": len(parts), "frames": total}


def frame_columns(part: Part) -> dict[str, np.ndarray]:
    """One part's rows as named arrays, in info.json's order."""
    ep, n = part.episode, part.episode.n
    cols = {f.key: lf.column(ep.steps, f) for f in lf.FEATURES}
    cols[lf.LABEL.key] = np.asarray(ep.collision, dtype=bool)
    frame_index = np.arange(n, dtype=np.int64)
    cols["timestamp"] = (frame_index / lf.FPS).astype(np.float32)
    cols["frame_index"] = frame_index
    cols["episode_index"] = np.full(n, part.index, dtype=np.int64)
    cols["index"] = part.from_index + frame_index
    cols["task_index"] = np.zeros(n, dtype=np.int64)
    return cols


def arrow_column(pa: Any, values: np.ndarray) -> Any:
    """A scalar column, a fixed-size list (shape [n]) or a list of fixed-size lists ([h, w])."""
    if values.ndim == 1:
        return pa.array(values)
    inner = pa.FixedSizeListArray.from_arrays(pa.array(values.reshape(-1)), values.shape[-1])
    if values.ndim == 2:
        return inner
    offsets = pa.array(np.arange(0, len(values) + 1, dtype=np.int32) * values.shape[1])
    return pa.ListArray.from_arrays(offsets, inner)


def data_table(pa: Any, group: list[Part]) -> Any:
    cols = [frame_columns(p) for p in group]
    return pa.table({k: arrow_column(pa, np.concatenate([c[k] for c in cols])) for k in cols[0]})


def episodes_table(pa: Any, parts: list[Part]) -> tuple[Any, dict[str, dict[str, np.ndarray]]]:
    """meta/episodes' rows (where each episode is, its statistics, its carrt metadata) and the
    dataset's statistics."""
    rows: dict[str, list[Any]] = {}
    whole: dict[str, list[np.ndarray]] = {}
    images = ls.ImageStats()
    for part in parts:
        n, cols = part.episode.n, frame_columns(part)
        frames = ls.ImageStats()
        frames.add(np.asarray(part.episode.frames))
        images.counts += frames.counts
        images.frames += frames.frames
        start = part.from_frame / lf.FPS
        row: dict[str, Any] = {
            "episode_index": part.index, "tasks": [lf.TASK], "length": n,
            "data/chunk_index": part.chunk, "data/file_index": part.file,
            "dataset_from_index": part.from_index, "dataset_to_index": part.from_index + n,
            f"videos/{lf.CAMERA}/chunk_index": part.chunk,
            f"videos/{lf.CAMERA}/file_index": part.file,
            f"videos/{lf.CAMERA}/from_timestamp": start,
            f"videos/{lf.CAMERA}/to_timestamp": start + n / lf.FPS,
        }  # fmt: skip
        episode_stats = {lf.CAMERA: frames.stats()}
        for key, values in cols.items():
            episode_stats[key] = ls.feature_stats(values)
            whole.setdefault(key, []).append(values)
        for key, stats in episode_stats.items():
            for name, value in stats.items():
                row[f"stats/{key}/{name}"] = np.asarray(value).tolist()
        row["meta/episodes/chunk_index"], row["meta/episodes/file_index"] = 0, 0
        row["carrt/episode"] = part.meta["origin"]["episode"]
        row["carrt/first_step"] = part.meta["origin"]["first_step"]
        row["carrt/meta"] = json.dumps(part.meta, default=fmt._json_default, sort_keys=True)
        for key, value in row.items():
            rows.setdefault(key, []).append(value)
    stats = {lf.CAMERA: images.stats()}
    stats.update({key: ls.feature_stats(np.concatenate(v)) for key, v in whole.items()})
    return pa.Table.from_pydict(rows), stats


def tasks_table(pa: Any) -> Any:
    """meta/tasks.parquet as pandas writes a frame indexed by the task's text (LeRobot reads it
    with pandas.read_parquet and looks tasks up by that index)."""
    index = "__index_level_0__"
    pandas_meta = {
        "index_columns": [index],
        "column_indexes": [{"name": None, "field_name": None, "pandas_type": "unicode",
                            "numpy_type": "object", "metadata": {"encoding": "UTF-8"}}],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64",
             "numpy_type": "int64", "metadata": None},
            {"name": None, "field_name": index, "pandas_type": "unicode",
             "numpy_type": "object", "metadata": None},
        ],
        "attributes": {}, "creator": {"library": "carrt"}, "pandas_version": "2.0.0",
    }  # fmt: skip
    table = pa.table({"task_index": pa.array([0], pa.int64()), index: pa.array([lf.TASK])})
    return table.replace_schema_metadata({"pandas": json.dumps(pandas_meta)})


def _write_parquet(pa: Any, path: Path, table: Any) -> None:
    import pyarrow.parquet as pq

    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, path, compression="snappy")


def _write_video(av: Any, path: Path, group: list[Part], pix_fmt: str, crf: int) -> None:
    """The group's frames, in order, one per 1/fps: frame k of the file at k / fps exactly."""
    path.parent.mkdir(parents=True, exist_ok=True)
    h, w, _ = lf.IMAGE_SHAPE
    with av.open(str(path), "w", options={"movflags": "+faststart"}) as container:
        stream = container.add_stream("libx264", rate=lf.FPS)
        stream.width, stream.height, stream.pix_fmt = w, h, pix_fmt
        stream.codec_context.time_base = Fraction(1, lf.FPS)
        stream.options = {"crf": str(crf), "g": str(GOP), "preset": "medium"}
        k = 0
        for part in group:
            for image in part.episode.frames:
                frame = av.VideoFrame.from_ndarray(np.asarray(image), format="rgb24")
                frame.pts, frame.time_base = k, Fraction(1, lf.FPS)
                container.mux(stream.encode(frame))
                k += 1
        container.mux(stream.encode(None))
