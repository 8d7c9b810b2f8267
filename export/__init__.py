"""Policy → one self-contained ONNX file the car can trust (docs/training.md#export).

`export_policy` and `carrt-export` (by hand, and as a process at the end of every carrt-train
run: training/ never imports export/) do the same thing: trace, attach carrt's metadata, check
parity with PyTorch on recorded frames, validate with carrt's own loader, and only then rename
the file into place.
"""

from carrt.deps import exit_unless_installed

# Without the train extra, one line naming it (exit 2) instead of a traceback from deep inside.
exit_unless_installed("export", ("torch", "onnx"))

from export.onnx_export import (  # noqa: E402
    DEFAULT_TOLERANCE,
    ExportRefused,
    ExportReport,
    export_policy,
)

__all__ = ["DEFAULT_TOLERANCE", "ExportRefused", "ExportReport", "export_policy"]
