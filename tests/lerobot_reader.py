"""Read LeRobotDatasets with LeRobot's own reader and write what it returned, for
tests/test_episodes_lerobot_reader.py. Runs in the reader's venv (`make test` builds
.venv-lerobot: lerobot-dataset 0.4.4, torchcodec 0.13.0, CPU torch 2.13.0), which has no carrt.

    python tests/lerobot_reader.py OUT.npz DATASET...

For each dataset, every item the reader gives (`dataset[i]` for every i): the camera frame as
uint8 HWC, every other feature as an array, and the episodes' bounds and the task texts.

torchvision 0.28's wheel is a CUDA build whose kernels cannot load beside a CPU torch; LeRobot
imports it, and its import registers fake kernels for the operators `nms` and `qnms`, which must
then be defined: a torch.library with those two definitions, kept referenced, stands in for
them (the dataset path never calls them; every line that reads data is the library's own).
"""

from __future__ import annotations

import json
import os
import sys
import tempfile

os.environ["HF_HUB_OFFLINE"] = "1"  # nothing from the network: the datasets are local
os.environ.setdefault("HF_HOME", tempfile.mkdtemp(prefix="hf-home-"))

import numpy as np
import torch

TORCHVISION_OPS = torch.library.Library("torchvision", "DEF")
TORCHVISION_OPS.define("nms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
TORCHVISION_OPS.define("qnms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")

from ledataset.datasets.lerobot_dataset import LeRobotDataset  # noqa: E402

CAMERA = "observation.images.camera"


def read(root: str) -> tuple[dict[str, np.ndarray], dict]:
    dataset = LeRobotDataset("local/carrt-export", root=root, video_backend="torchcodec")
    items = [dataset[i] for i in range(len(dataset))]
    arrays: dict[str, np.ndarray] = {}
    for key in items[0]:
        if key == "task":
            continue
        values = torch.stack([item[key] for item in items]).numpy()
        if key == CAMERA:  # CHW floats in [0, 1], as LeRobot hands them to a policy
            values = np.round(values.transpose(0, 2, 3, 1) * 255).astype(np.uint8)
        arrays[key] = values
    episodes = dataset.meta.episodes
    about = {
        "len": len(dataset),
        "num_episodes": dataset.num_episodes,
        "fps": dataset.fps,
        "tasks": sorted({item["task"] for item in items}),
        "bounds": [[int(a), int(b)] for a, b in zip(episodes["dataset_from_index"],
                                                    episodes["dataset_to_index"], strict=True)],
        "stats": sorted(dataset.meta.stats),
    }  # fmt: skip
    return arrays, about


def main() -> int:
    out, roots = sys.argv[1], sys.argv[2:]
    saved: dict[str, np.ndarray] = {}
    abouts = []
    for k, root in enumerate(roots):
        arrays, about = read(root)
        saved.update({f"{k}/{key}": value for key, value in arrays.items()})
        abouts.append(about)
    saved["about"] = np.array(json.dumps(abouts))
    np.savez(out, **saved)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
