"""When an episode begins and ends: a small rule beside the arbiter, apart from the loop's tick.

An episode is one stretch of driving. It begins when the board confirms it is ARMED (not when
the host asks: a refused arm must not leave a few-step episode of a car that never moved) and
there is a frame to record; it ends the tick driving stops (disarm, e-stop, failsafe) or the
person pauses recording. Why it ended is decided by the loop, which knows about collisions and
the board (carrt/laps.py has the words).
"""

from __future__ import annotations

from dataclasses import dataclass

from carrt.interfaces import Mode

DRIVING = (Mode.MANUAL, Mode.AUTO)


@dataclass
class EpisodeRule:
    record: bool  # the session records at all (--record and a sink)
    paused: bool = False  # the person toggled recording off
    recording: bool = False  # an episode is open

    def toggle_pause(self) -> None:
        if self.record:
            self.paused = not self.paused

    def should_begin(self, mode: Mode, board_armed: bool, have_frame: bool) -> bool:
        return (
            self.record
            and not self.paused
            and not self.recording
            and mode in DRIVING
            and board_armed
            and have_frame
        )

    def should_end(self, mode: Mode) -> bool:
        return self.recording and (mode not in DRIVING or self.paused)
