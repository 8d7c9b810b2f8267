"""The learning half of carrt (PyTorch): data over episodes, models, losses and the DIRL stages.

Nothing under carrt/ imports this package: the car runs the exported ONNX policy without torch.
"""

from carrt.deps import exit_unless_installed

# Without the train extra, one line naming it (exit 2) instead of a traceback from deep inside.
exit_unless_installed("training", ("torch", "onnx"))
