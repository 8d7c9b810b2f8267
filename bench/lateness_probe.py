"""`python -m bench.lateness_probe ARGS`: `carrt ARGS`, and every tick's lateness written out.

The loop's summary gives one p99 per run, which on a shared 2-core machine moves by
milliseconds from run to run; bench_view pools the ticks of several runs instead, and gets them
here, through the public Clock interface only: the loop sleeps until each tick's deadline on
the main thread (the simulated camera sleeps on its own), so the time past the deadline when
that sleep returns is the tick's lateness, as the loop measures it.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from pathlib import Path

from carrt.cli import main
from carrt.clock import WallClock

samples: list[float] = []
_sleep_until = WallClock.sleep_until


def sleep_until(self: WallClock, deadline: float) -> None:
    _sleep_until(self, deadline)
    if threading.current_thread() is threading.main_thread():
        samples.append(time.monotonic() - deadline)


if __name__ == "__main__":
    WallClock.sleep_until = sleep_until
    code = main(sys.argv[1:])
    Path(os.environ["CARRT_LATENESS_OUT"]).write_text(json.dumps(samples))
    sys.exit(code)
