"""carrt: the on-car runtime. Never imports torch: a Jetson must run it without PyTorch."""

__version__ = "0.1.0"

import os as _os

# pygame prints a banner on import; the CLI's output is for the user's car, not for pygame.
_os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
