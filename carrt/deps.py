"""Optional packages, and the one line a user sees when one is missing.

The car's install carries only what every car needs (pyproject.toml): onnxruntime and OpenCV
come from the platform on a Jetson (NVIDIA's onnxruntime-gpu, JetPack's OpenCV with GStreamer),
and the simulator's and plots' packages come with the `laptop` extra. So a command can meet a
package that is not there; it must then say which one and how to get it, exit 2, and never
show a traceback. The hints live here, once, for the CLI and the entry points of training and
export.
"""

from __future__ import annotations

import importlib.util
import sys

from carrt.errors import EXIT_USAGE

LAPTOP = "pip install 'carrt[laptop]'"
TRAIN = "pip install 'carrt[train]'"

# top-level module -> (what it is, how to install it)
INSTALL_HINTS: dict[str, tuple[str, str]] = {
    "onnxruntime": (
        "onnxruntime",
        f"on a laptop: {LAPTOP}; on a Jetson: NVIDIA's onnxruntime-gpu wheel (docs/jetson.md)",
    ),
    "cv2": (
        "OpenCV",
        f"on a laptop: {LAPTOP}; on a Jetson: JetPack's OpenCV, seen by a venv made with "
        "--system-site-packages (docs/jetson.md)",
    ),
    "gymnasium": ("gymnasium (the simulator's environment API)", LAPTOP),
    "matplotlib": ("matplotlib (plots)", LAPTOP),
    "av": ("PyAV (H.264 episode videos)", f"{LAPTOP} (or pip install av)"),
    "rerun": ("the Rerun SDK (episodes in Rerun)", f"{LAPTOP} (or pip install rerun-sdk)"),
    "pygame": ("pygame (joystick and simulator window)", "pip install pygame"),
    # a car's venv made before calibration needed it (carrt/toml_edit.py)
    "tomlkit": ("tomlkit (editing car.toml)", "pip install tomlkit (or reinstall carrt)"),
    "torch": ("PyTorch (training)", TRAIN),
    "onnx": ("onnx (export)", TRAIN),
    "tqdm": ("tqdm (training progress)", TRAIN),
    "tensorboard": ("tensorboard (training logs)", TRAIN),
}


def missing_package_message(exc: ModuleNotFoundError) -> str | None:
    """The one-line explanation for a missing optional package, or None for any other module
    (a missing module of carrt itself is a bug and keeps its traceback)."""
    top = (exc.name or "").split(".")[0]
    if top not in INSTALL_HINTS:
        return None
    what, how = INSTALL_HINTS[top]
    return f"this needs {what}, which is not installed: {how}"


def exit_unless_installed(program: str, modules: tuple[str, ...]) -> None:
    """For entry points outside the CLI (training/, export/): one line and exit 2 when a
    package of their extra is missing, before any import of it can raise a traceback."""
    for name in modules:
        if importlib.util.find_spec(name) is None:
            what, how = INSTALL_HINTS[name]
            print(f"{program}: error: this needs {what}, which is not installed: {how}",
                  file=sys.stderr)  # fmt: skip
            raise SystemExit(EXIT_USAGE)
