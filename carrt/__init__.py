"""carrt: the on-car runtime. Never imports torch: a Jetson must run it without PyTorch."""

__version__ = "0.1.0"
