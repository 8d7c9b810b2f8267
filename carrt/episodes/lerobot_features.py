"""carrt's steps as LeRobotDataset v3.0 features: one table, read by the export and the import.

Why a table: each carrt step field becomes one LeRobot feature (its name, dtype, shape and the
names of its entries, as meta/info.json states them), and the import reads each back into the
same field; a field named once here cannot be exported under one name and read under another.
What a LeRobot policy learns is `action`: the person's action a* (what carrt's imitation learns
too), beside the camera (`observation.images.camera`, an H.264 video) and the speed
(`observation.state`). carrt's other fields ride along as `carrt.*` features, so the round trip
export → import → export is exact; docs/episodes.md documents each.

The format, as the reader (`lerobot-dataset` 0.4.4) checks it: a shape-[1] feature is a scalar
column, a shape-[n] one a fixed-size list, a shape-[h, w] one a list of fixed-size lists;
`timestamp` is frame_index / fps (float32), the video's frame k of an episode at its
`from_timestamp` + k / fps.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from carrt.model_contract import HORIZON, IMAGE_SHAPE

CODEBASE_VERSION = "v3.0"
FPS = 10  # the car's control rate: one step, one frame
CAMERA = "observation.images.camera"
TASK = "drive laps of the track without touching an obstacle"
CHUNKS_SIZE = 1000  # files per chunk folder (LeRobot's default)
FRAMES_PER_FILE = 20_000  # ~10 MB of parquet, ~60 MB of 96x96 H.264: under LeRobot's 100/200 MB

INFO = "meta/info.json"
STATS = "meta/stats.json"
TASKS = "meta/tasks.parquet"
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"

# What the reader adds to every dataset (LeRobot's DEFAULT_FEATURES).
INDEX_FEATURES = {
    "timestamp": ("float32", (1,)),
    "frame_index": ("int64", (1,)),
    "episode_index": ("int64", (1,)),
    "index": ("int64", (1,)),
    "task_index": ("int64", (1,)),
}


@dataclass(frozen=True)
class Feature:
    """One LeRobot feature and the carrt step field it holds."""

    key: str  # the LeRobot feature name
    field: str  # the step field (carrt/episodes/format.py step_dtype)
    dtype: str  # numpy dtype name as info.json states it
    shape: tuple[int, ...]
    names: tuple[str, ...] | None
    doc: str  # what it is, for docs/episodes.md (tests/test_episodes_lerobot.py checks it)


PLAN_NAMES = ("step", "steering_throttle")
STEERING_THROTTLE = ("steering", "throttle")

FEATURES: tuple[Feature, ...] = (
    Feature("observation.state", "speed_mps", "float32", (1,), ("speed_mps",),
            "the measured speed (m/s), from the wheel encoder"),
    Feature("action", "human_action", "float32", (2,), STEERING_THROTTLE,
            "the person's action a* in [-1, 1]: what imitation learns (NaN where no person "
            "drove)"),
    Feature("carrt.policy_action", "policy_action", "float32", (2,), STEERING_THROTTLE,
            "the policy's first planned action (NaN where no policy ran)"),
    Feature("carrt.executed_action", "executed_action", "float32", (2,), STEERING_THROTTLE,
            "the action sent to the board after arbitration (what the car did)"),
    Feature("carrt.plan_mu", "plan_mu", "float32", (HORIZON, 2), PLAN_NAMES,
            "the policy's plan μ over its horizon (NaN rows: no plan)"),
    Feature("carrt.plan_sigma", "plan_sigma", "float32", (HORIZON, 2), PLAN_NAMES,
            "the plan's σ over its horizon (NaN rows: no plan)"),
    Feature("carrt.mode", "mode", "uint8", (1,), None,
            "who drove: 0 DISARMED, 1 MANUAL, 2 AUTO, 3 ESTOP"),
    Feature("carrt.override", "override", "bool", (1,), None,
            "the person took over from the policy at this step"),
    Feature("carrt.estop", "estop", "bool", (1,), None, "an e-stop was latched at this step"),
    Feature("carrt.noise", "noise", "bool", (1,), None,
            "noise was injected into the executed action (the paper's exploration)"),
    Feature("carrt.collision", "collision", "bool", (1,), None,
            "a collision was detected at this step (the recorded event)"),
    Feature("carrt.lap", "lap", "bool", (1,), None, "a lap mark (the line crossed)"),
    Feature("carrt.step_index", "index", "int64", (1,), None,
            "the loop's step number (a gap: steps the writer dropped)"),
    Feature("carrt.frame_captured_at", "frame_captured_at", "float64", (1,), None,
            "when the camera captured the frame (the loop's clock, s): the real times, where "
            "`timestamp` is frame_index / fps"),
    Feature("carrt.command_sent_at", "command_sent_at", "float64", (1,), None,
            "when the step's command went to the board (the loop's clock, s)"),
    Feature("carrt.wall_time", "wall_time", "float64", (1,), None,
            "the step's wall-clock time (Unix s)"),
    Feature("carrt.encoder_ticks", "encoder_ticks", "int64", (1,), None,
            "the wheel encoder's count"),
)  # fmt: skip
# Derived, not stored in a carrt step: the paper's collision label (the 0.5 s before a collision
# and an episode that ended in one), which the import derives again and checks.
LABEL = Feature("carrt.collision_label", "", "bool", (1,), None,
                "the collision label c: 1 in the 0.5 s before a collision (the world model's "
                "target); the import derives it again from carrt.collision")  # fmt: skip
ALL_FEATURES = (*FEATURES, LABEL)

# What a dataset recorded elsewhere must have (or be told with --camera/--action/--speed).
REQUIRED = (CAMERA, "action", "observation.state")
CARRT_EXTRAS = tuple(f.key for f in ALL_FEATURES if f.key.startswith("carrt."))


def info_features(codec: str, pix_fmt: str) -> dict[str, dict]:
    """The `features` of meta/info.json, in the order the columns are written."""
    h, w, c = IMAGE_SHAPE
    out: dict[str, dict] = {
        CAMERA: {
            "dtype": "video",
            "shape": [h, w, c],
            "names": ["height", "width", "channels"],
            "info": video_info(codec, pix_fmt),
        }
    }
    for f in ALL_FEATURES:
        names = list(f.names) if f.names is not None else None
        out[f.key] = {"dtype": f.dtype, "shape": list(f.shape), "names": names}
    for key, (dtype, shape) in INDEX_FEATURES.items():
        out[key] = {"dtype": dtype, "shape": list(shape), "names": None}
    return out


def video_info(codec: str, pix_fmt: str) -> dict[str, Any]:
    h, w, c = IMAGE_SHAPE
    return {
        "video.height": h, "video.width": w, "video.codec": codec, "video.pix_fmt": pix_fmt,
        "video.is_depth_map": False, "video.fps": FPS, "video.channels": c, "has_audio": False,
    }  # fmt: skip


def column(steps: np.ndarray, feature: Feature) -> np.ndarray:
    """A step field as the feature's array: (N,) for shape [1], else (N, *shape)."""
    values = np.asarray(steps[feature.field]).astype(feature.dtype)
    return values.reshape(len(steps), *feature.shape) if feature.shape != (1,) else values
