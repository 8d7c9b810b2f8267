"""The learning half of carrt (PyTorch): data over episodes, models, losses and the DIRL stages.

Nothing under carrt/ imports this package: the car runs the exported ONNX policy without torch.
"""
