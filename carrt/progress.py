"""A live status bar while the car records: steps, episodes, mode, speed (tqdm, on a terminal).

Why: a recording session is long and silent otherwise, and a person over SSH on the Jetson
wants to see that frames are being written. The bar runs on its own thread and only reads the
loop's `live` status and summary counters, so the loop never waits for the terminal. tqdm turns
itself off when stderr is not a terminal (logs, tests, CI).
"""

from __future__ import annotations

import contextlib
import sys
import threading
from collections.abc import Iterator
from typing import Any

REFRESH_S = 0.5


@contextlib.contextmanager
def recording_bar(loop: Any, enabled: bool, stream: Any = None) -> Iterator[None]:
    stream = sys.stderr if stream is None else stream
    if not enabled or not stream.isatty():
        yield
        return
    from tqdm import tqdm

    stop = threading.Event()
    bar = tqdm(total=None, unit="step", desc="recording", file=stream, leave=False, mininterval=0)

    def update() -> None:
        shown = 0
        while not stop.wait(REFRESH_S):
            live, steps = loop.live, loop.summary.recorded_steps
            # the status first, so the render `update` makes shows this tick's, not the last one's
            bar.set_postfix_str(
                f"{live.mode.name} {live.speed_mps:.1f} m/s, episode {live.episodes}, "
                f"dropped {loop.summary.dropped_steps}",
                refresh=False,
            )
            bar.update(steps - shown)
            shown = steps

    thread = threading.Thread(target=update, name="recording-bar", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(timeout=2.0)
        bar.close()
