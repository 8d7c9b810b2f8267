"""The car's faults as the person hears them: one line when a fault starts, one when it ends.

A fault is a part not doing its job: the camera's newest frame too old (stale) or no frame at
all (lost), the board silent, the receiver lost, a rebooted board that has not taken the car's
config again. What the car does about each is the arbiter's and the board's (carrt/arbitration
.py, the firmware); this module only says so. Each tick the loop hands it the faults it
measured, each with the reason the part gave, and a line is printed the tick a fault starts and
another once it has been over for `settle_s`: nothing in between, however long it lasts (a
camera frame 160, 170, 180 ms old is one fault, not a line per tick), and a fault that flickers
at its threshold is one fault too.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from firmware_bridge import messages as m

LOG = logging.getLogger("carrt.loop")  # said where the loop's mode lines are

SETTLE_S = 0.5  # a fault must stay gone this long before it is said to be over
# a board wants 5 good pulses of each receiver channel (100 ms) after it boots before it counts
# the receiver: a receiver "lost" that long after a reboot is the reboot, said already, and that
# long after the board is first heard it is the board starting (a transmitter that is off at
# the start is still said, once the board has had the time to count it)
REVALIDATE_S = 0.5


@dataclass
class FaultWatch:
    say: Callable[[float, str], None]  # (loop clock time, the line)
    settle_s: float = SETTLE_S
    _since: dict[str, float] = field(default_factory=dict)  # fault → when it started
    _clear_since: dict[str, float] = field(default_factory=dict)  # fault → when it went away

    @property
    def active(self) -> tuple[str, ...]:
        return tuple(self._since)

    def update(self, now: float, faults: Mapping[str, str]) -> None:
        """`faults`: this tick's faults, name → the part's reason."""
        for name, reason in faults.items():
            self._clear_since.pop(name, None)
            if name not in self._since:
                self._since[name] = now
                self.say(now, f"{name}: {reason}")
        for name in [n for n in self._since if n not in faults]:
            gone = self._clear_since.setdefault(name, now)
            if now - gone >= self.settle_s:
                lasted = gone - self._since.pop(name)
                del self._clear_since[name]
                self.say(now, f"{name}: over after {lasted:.1f} s")


def measured_faults(
    *,
    frame_age_s: float | None,
    max_frame_age_s: float,
    camera_lost_reason: str | None,
    connected: bool,
    telemetry: m.Telemetry | None,
    telemetry_age_s: float,
    max_telemetry_age_s: float,
    receiver_is_controls: bool,
    config_pending_s: float | None,
) -> dict[str, str]:
    """This tick's faults with their reasons, from what the loop measured (pure: tested alone)."""
    return dict(
        _faults(
            frame_age_s, max_frame_age_s, camera_lost_reason, connected, telemetry,
            telemetry_age_s, max_telemetry_age_s, receiver_is_controls, config_pending_s,
        )
    )  # fmt: skip


def _faults(
    frame_age_s, max_frame_age_s, camera_lost_reason, connected, telemetry, telemetry_age_s,
    max_telemetry_age_s, receiver_is_controls, config_pending_s,
) -> Iterator[tuple[str, str]]:  # fmt: skip
    if camera_lost_reason:
        yield "camera lost", camera_lost_reason
    elif frame_age_s is not None and frame_age_s > max_frame_age_s:
        yield (
            "camera stale",
            (
                f"newest frame {frame_age_s * 1e3:.0f} ms old "
                f"(limit {max_frame_age_s * 1e3:.0f} ms): the policy's commands are held at neutral"
            ),
        )
    if not connected:
        yield "board silent", "the serial port is gone (cable, power?): reconnecting"
    elif telemetry is not None and telemetry_age_s > max_telemetry_age_s:
        yield (
            "board silent",
            (
                f"no telemetry for {telemetry_age_s * 1e3:.0f} ms "
                f"(limit {max_telemetry_age_s * 1e3:.0f} ms)"
            ),
        )
    if (
        receiver_is_controls
        and connected
        and telemetry is not None
        and telemetry_age_s <= max_telemetry_age_s
        and not telemetry.flags & m.TelemetryFlags.RC_SIGNAL
    ):
        yield (
            "receiver lost",
            (
                "the board has no valid pulse from the receiver (transmitter off, out of range or "
                "a wire loose; it needs 5 good pulses after a loss or a reboot)"
            ),
        )
    if config_pending_s is not None and config_pending_s > 0.5:
        yield (
            "car config not on the board",
            (
                f"the rebooted board has not acknowledged the car's config for "
                f"{config_pending_s:.1f} s: arming is held"
            ),
        )


class PartsWatch:
    """The loop's eyes on its parts: the board's boot (a new boot id is a reboot, named once)
    and this tick's faults (FaultWatch); their lines are warnings, which neither -q nor the
    scripted expert's quiet log hides, and the newest few are kept for the live view."""

    def __init__(self, parts: Any, config: Any) -> None:
        self.parts, self.config = parts, config
        self.boot = getattr(parts.link, "board", None)  # BoardInfo as the loop last saw it
        self._reboots_seen = parts.link.counters.reboots_detected
        self._config_pending_since: float | None = None
        self._rebooted_at = -float("inf")
        self._first_heard_at: float | None = None  # the first tick with the board's telemetry
        self._receiver_is_controls = config.receiver.controls in ("receiver", "both")
        self.notices: tuple[tuple[float, str], ...] = ()
        self.faults = FaultWatch(self._notice)

    def _notice(self, now: float, line: str) -> None:
        LOG.warning(line)
        self.notices = (*self.notices[-4:], (now, line))

    def board_reboot(self, now: float) -> str:
        """The line naming a reboot the link saw since the last call (said), or ''."""
        link = self.parts.link
        count = link.counters.reboots_detected
        if count == self._reboots_seen:
            return ""
        self._reboots_seen = count
        before, self.boot = self.boot, getattr(link, "board", None)
        text = board_reboot_text(before, self.boot)
        self._rebooted_at = now
        self._notice(now, text)
        return text

    def faults_of(self, tick: Any) -> None:
        """This tick's faults (a Tick, carrt/tick.py, arbitrated), each said when it starts/ends."""
        parts, frame, link = self.parts, tick.frame, self.parts.link
        if getattr(link, "config_pending", False):
            if self._config_pending_since is None:  # (a clock may start at 0.0)
                self._config_pending_since = tick.now
        else:
            self._config_pending_since = None
        pending = self._config_pending_since
        lost = getattr(parts.camera, "lost_reason", None)
        if self._first_heard_at is None and tick.telemetry is not None:
            self._first_heard_at = tick.now
        heard = tick.now if self._first_heard_at is None else self._first_heard_at
        counting = max(self._rebooted_at, heard)  # since when the board could count pulses
        self.faults.update(
            tick.now,
            measured_faults(
                frame_age_s=None if frame is None else tick.now - frame.captured_at,
                max_frame_age_s=self.config.camera.max_age_s,
                camera_lost_reason=lost or ("camera lost" if parts.camera.lost else None),
                connected=getattr(link, "connected", True),
                telemetry=None if tick.telemetry is None else tick.telemetry.telemetry,
                telemetry_age_s=link.telemetry_age_s(),
                max_telemetry_age_s=self.config.encoder.max_age_s,
                receiver_is_controls=self._receiver_is_controls
                and tick.now - counting > REVALIDATE_S,
                config_pending_s=None if pending is None else tick.now - pending,
            ),
        )


def board_metadata(board: Any) -> dict[str, Any] | None:
    """The board's identity as an episode records it (firmware_bridge.link.BoardInfo)."""
    if board is None:
        return None
    cause = getattr(board, "reset_cause", None)
    return {
        "firmware": ".".join(map(str, board.firmware_version)),
        "boot_id": board.boot_id,
        "reset_cause": None if cause is None else m.reset_cause_text(cause),
    }


def board_reboot_text(before: Any, after: Any) -> str:
    """'board rebooted (brown-out; boot id 1a2b3c4d → 5e6f7081): ...', a reboot's one line."""
    cause = getattr(after, "reset_cause", None)
    named = "cause unknown" if cause is None else m.reset_cause_text(cause)
    ids = ""
    if before is not None and after is not None:
        ids = f"; boot id {before.boot_id:08x} → {after.boot_id:08x}"
    return (
        f"board rebooted ({named}{ids}): it gets the car's config again and stays disarmed "
        "until you re-arm"
    )
