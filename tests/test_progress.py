"""The recording status bar: counts the loop's recorded steps, never on a non-terminal."""

from __future__ import annotations

import io
import re
import time

from carrt.interfaces import LiveStatus, Mode
from carrt.progress import recording_bar


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


class FakeLoop:
    class summary:  # stands in for LoopSummary's counters
        recorded_steps = 0
        dropped_steps = 0

    live = LiveStatus(mode=Mode.MANUAL, speed_mps=1.5, episodes=2)


def test_the_bar_follows_the_recorded_steps_on_a_terminal():
    screen, loop = Terminal(), FakeLoop()
    with recording_bar(loop, enabled=True, stream=screen):
        for _ in range(12):
            loop.summary.recorded_steps += 10
            time.sleep(0.1)
    text = screen.getvalue()
    # the status shows from the first tick's render on (on a loaded machine 1.2 s may hold one)
    assert "recording" in text and "MANUAL 1.5 m/s, episode 2" in text
    counts = [int(n) for n in re.findall(r"(\d+)step \[", text)]
    assert counts and max(counts) >= 50 and counts == sorted(counts), text[-300:]


def test_no_bar_when_not_recording_or_not_a_terminal():
    for stream, enabled in ((Terminal(), False), (io.StringIO(), True)):
        with recording_bar(FakeLoop(), enabled=enabled, stream=stream):
            time.sleep(0.6)
        assert stream.getvalue() == ""
