"""The lap rule every table uses: the loop's summary, the simulator's metrics and `carrt report`.

The person presses the lap button each time the car crosses the line, the start of a trial
included, so N marks make N-1 laps. A trial goes on across a collision, an e-stop or a board
failsafe (the car is reset and re-armed, the lap in progress continues); a deliberate disarm ends
it, and the next trial's first mark starts a lap without closing one. The simulator's stand-in
person follows the same rule, so for one run all three tables count the same laps.
"""

from __future__ import annotations

from dataclasses import dataclass

from carrt.interfaces import Mode

TRIAL_GOES_ON = ("collision", "estop", "failsafe")  # episode ends after which the car is reset


@dataclass
class LapCounter:
    """Counts laps live from lap marks and episode ends, by the rule above."""

    laps: int = 0
    marks: int = 0
    _open: bool = False  # a mark has started a lap that no mark has closed yet

    def mark(self) -> None:
        self.marks += 1
        if self._open:
            self.laps += 1
        self._open = True

    def trial_end(self, reason: str) -> None:
        """An episode ended for `reason` (the episode's end reason)."""
        if reason not in TRIAL_GOES_ON:
            self._open = False

    @staticmethod
    def end_reason(mode: Mode, collision: bool, board_failsafe: bool) -> str:
        """Why driving stopped, in the episode format's words."""
        if mode == Mode.ESTOP:
            return "collision" if collision else "estop"
        if mode == Mode.DISARMED:
            return "failsafe" if board_failsafe else "disarmed"
        return "stopped"
