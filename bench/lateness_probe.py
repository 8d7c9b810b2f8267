"""`python -m bench.lateness_probe ARGS`: `carrt ARGS`, and every tick's lateness written out.

The loop's summary gives one p99 per run, which on a shared 2-core machine moves by
milliseconds from run to run; bench_view pools the ticks of several runs instead, and gets them
here: every tick starts when `FrameLock.wait` returns (carrt/frame_lock.py), so wrapping it and
applying `FrameLock.lateness`, the loop's own formula, gives each tick's lateness as the loop
measures it (time from its frame, or from a window that closed without one, to its start).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from carrt.cli import main
from carrt.frame_lock import FrameLock, Trigger

samples: list[float] = []
_wait = FrameLock.wait


def wait(self: FrameLock, clock, camera, deadline: float) -> Trigger:
    trigger = _wait(self, clock, camera, deadline)
    samples.append(self.lateness(trigger, deadline))
    return trigger


if __name__ == "__main__":
    FrameLock.wait = wait
    code = main(sys.argv[1:])
    Path(os.environ["CARRT_LATENESS_OUT"]).write_text(json.dumps(samples))
    sys.exit(code)
