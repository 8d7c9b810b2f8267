"""Every reason the arbiter gives, by name: what latched the e-stop, why the car is held at
neutral, why a button press was refused.

Why an enum: the words are for the person (the log's mode and `refused:` lines, the live view,
the simulator's window) while code and tests need to know which reason it was; matching the
words made every rewording a code change and a test change. Each member's value is its text,
with `{placeholders}` for what was measured; `Why.X.text(...)` gives that text as a `WhyText`,
a str that remembers its member, so everything that shows, logs or serialises a reason takes
it as before and `reason.why is Why.X` tells which.
"""

from __future__ import annotations

import enum
from typing import Any


class WhyText(str):
    """A reason's words (a str: printed, logged and sent as JSON unchanged) and its member."""

    why: Why

    def __new__(cls, why: Why, text: str) -> WhyText:
        made = super().__new__(cls, text)
        made.why = why
        return made

    def __reduce__(self) -> tuple[Any, ...]:
        return WhyText, (self.why, str(self))


@enum.unique
class Why(enum.Enum):
    """The arbiter's reasons (carrt/arbitration.py), each with its words."""

    # -- what latched the e-stop (LiveStatus.why, the "mode ESTOP (neutral: e-stop: …)" line)
    ESTOP_BUTTON = "e-stop button"
    PAD_ESTOP = "joystick: e-stop button pressed or pad removed"  # the pad's reader thread
    RECEIVER_LOST = "receiver lost"
    JOYSTICK_DISCONNECTED = "joystick disconnected"
    CAMERA_LOST = "camera lost"  # also AUTO's neutral reason
    CAMERA_LOST_BECAUSE = "camera lost ({because})"  # the camera's own words
    BOARD_ESTOP = "the board reports e-stop"
    BOARD_KEPT_ESTOP = "the board did not leave e-stop after a clear"
    COLLISION = "collision"  # the simulator's collision (carrt/loop.py)
    BROWSER = "browser view"  # the live view's e-stop button (carrt/view/live.py)
    SAID_BY_CALLER = "{words}"  # another caller's own words (a signal handler, a test)

    # -- why the command is neutral (Decision.reason)
    ESTOP = "e-stop: {because}"
    NOT_ARMED = "not armed yet: press {arm} to arm (sticks at neutral)"
    NOT_ARMED_THEN_AUTO = (
        "not armed yet: press {arm} to arm (sticks at neutral), then {auto} for AUTO"
    )
    NO_JOYSTICK = "no joystick connected"
    BOARD_SILENT = "board silent: the transmitter is read through it"
    BOARD_REBOOTED = "{line}"  # the reboot's one line (carrt/faults.py board_reboot_text)
    BOARD_FAILSAFE = "board failsafe"
    BOARD_FAILSAFE_BECAUSE = "board failsafe ({because})"  # the board's Reason
    BOARD_FAILSAFE_HELD = "board failsafe: clear, then arm"
    BOARD_FAILSAFE_BECAUSE_HELD = "board failsafe ({because}): clear, then arm"
    BOARD_DISARMED = "the board disarmed"
    BOARD_DID_NOT_ARM = "the board did not arm"
    DISARMED_BY_HUMAN = "disarmed by the human"
    CLEARED = "cleared: arm when ready"
    NO_FRAME = "no camera frame yet"
    FRAME_OLDER_THAN = "camera frame older than {limit_ms:.0f} ms"
    NO_TELEMETRY = "no telemetry from the board yet"
    TELEMETRY_OLDER_THAN = "telemetry older than {limit_ms:.0f} ms"
    POLICY_NOT_FINITE = "policy output is not finite"
    PLAN_USED_ALREADY = "no plan: the previous plan's next step was used already"
    NO_PLAN = "no plan this tick"

    # -- why a press was refused (Decision.refused, the "refused: …" line)
    ARM_AFTER_CLEAR = "arm refused: arming is a separate press after the clear"
    ARM_WHILE_LATCHED = "arm refused: e-stop is latched: clear first"
    ARM_NO_JOYSTICK = "arm refused: no joystick connected"
    ARM_PAD_NEVER_NEUTRAL = (
        "arm refused: the pad has not reported neutral sticks since it connected: move them"
    )
    ARM_STICKS_OUT = "arm refused: sticks not at neutral"
    ARM_BOARD_CATCHING_UP = "arm refused: waiting for the board to leave its e-stop/failsafe"
    ARM_BOARD_LATCHED = "arm refused: the board is in {state}: clear first"
    CLEAR_NO_JOYSTICK = "clear refused: no joystick connected"
    CLEAR_STICKS_OUT = "clear refused: sticks not at neutral"
    NOTHING_TO_CLEAR = "clear: nothing to clear"
    AUTO_BEFORE_ARM = "auto refused: arm first"
    AUTO_IN_TELEOP = "auto refused: not available in this mode (teleop)"
    AUTO_STICKS_OUT = "auto refused: release the sticks first"
    AUTO_CAMERA_LOST = "auto refused: camera lost"
    AUTO_NO_FRAME = "auto refused: no camera frame yet"
    AUTO_FRAME_OLD = "auto refused: camera frame {age_ms:.0f} ms old"
    AUTO_NO_TELEMETRY = "auto refused: no telemetry from the board yet"
    AUTO_TELEMETRY_OLD = "auto refused: telemetry {age_ms:.0f} ms old"

    def text(self, **measured: Any) -> WhyText:
        """The words, with what was measured put in (a fixed reason is made once)."""
        if not measured:
            return _FIXED[self]
        return WhyText(self, self.value.format(**measured))


_FIXED = {why: WhyText(why, why.value) for why in Why if "{" not in why.value}
