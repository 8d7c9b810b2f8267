"""Every rate and timeout of the car's control and safety chain, in one table.

Why one table: these numbers only make sense together (the host sends at 50 Hz so that the
board's 200 ms watchdog hears ten commands before it trips; the loop decides at 10 Hz so that
the board's 300 ms freshness check sees a hung loop within three ticks), and they used to live
in six files in two languages. The board's entries are written into the firmware's generated
header (`python -m firmware_bridge.gen_c`, CARRT_T_<NAME>) and folded into the protocol hash, so
a board flashed with other timing is refused at the handshake like one with another protocol.
The host's entries are imported by name where they are used; tests use the names too.

The user-tunable ages (camera frames, encoder telemetry) and the loop's rate are defaults of the
car config (carrt/config.py) and come from here as well.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Timing:
    name: str
    value: float
    unit: str  # "ms" (integers, the board's clock) or "s" / "Hz" (the host's)
    side: str  # "board": in the firmware and the protocol hash; "host": Python only
    why: str


TABLE: tuple[Timing, ...] = (
    # -- the board (fw_core.c): its last word on the car
    Timing("LINK_TIMEOUT_MS", 200, "ms", "board", "no COMMAND for this long: FAILSAFE (neutral)"),
    Timing("DECISION_STALE_MS", 300, "ms", "board",
           "the decision id unchanged for this long (a hung loop): FAILSAFE"),
    Timing("STALL_MS", 500, "ms", "board",
           "throttle applied, wheels still for this long: FAILSAFE"),
    Timing("WHEELS_STOPPED_MS", 100, "ms", "board", "no encoder tick for this long: wheels still"),
    Timing("TELEMETRY_PERIOD_MS", 20, "ms", "board", "TELEMETRY every 20 ms (50 Hz)"),
    Timing("RC_LOSS_MS", 100, "ms", "board",
           "no valid receiver pulse on a channel for this long: its signal is lost"),
    # -- the host link (firmware_bridge/link.py)
    Timing("SEND_PERIOD_S", 0.02, "s", "host",
           "the sender thread repeats the latest decision at 50 Hz: ten per watchdog period"),
    Timing("HELLO_RETRY_S", 0.1, "s", "host", "handshake: ask for HELLO again after this"),
    Timing("RECONNECT_RETRY_S", 0.1, "s", "host",
           "cable pulled: try to reopen the port this often"),
    # -- the host loop and session (carrt/)
    Timing("LOOP_RATE_HZ", 10.0, "Hz", "host", "the control loop's rate (the paper's 10 Hz)"),
    Timing("CAMERA_MAX_AGE_S", 0.15, "s", "host",
           "default of camera.max_age_s: an older frame never drives (neutral instead)"),
    Timing("ENCODER_MAX_AGE_S", 0.1, "s", "host",
           "default of encoder.max_age_s: older telemetry means no speed (neutral)"),
    Timing("BOARD_GRACE_S", 1.0, "s", "host",
           "arbitration waits this long for the board to confirm an arm or a clear"),
    Timing("FIRST_FRAME_TIMEOUT_S", 3.0, "s", "host", "a camera with no frame by then: refused"),
)  # fmt: skip

BY_NAME = {t.name: t for t in TABLE}

LINK_TIMEOUT_MS = int(BY_NAME["LINK_TIMEOUT_MS"].value)
DECISION_STALE_MS = int(BY_NAME["DECISION_STALE_MS"].value)
STALL_MS = int(BY_NAME["STALL_MS"].value)
WHEELS_STOPPED_MS = int(BY_NAME["WHEELS_STOPPED_MS"].value)
TELEMETRY_PERIOD_MS = int(BY_NAME["TELEMETRY_PERIOD_MS"].value)
RC_LOSS_MS = int(BY_NAME["RC_LOSS_MS"].value)
SEND_PERIOD_S = BY_NAME["SEND_PERIOD_S"].value
HELLO_RETRY_S = BY_NAME["HELLO_RETRY_S"].value
RECONNECT_RETRY_S = BY_NAME["RECONNECT_RETRY_S"].value
LOOP_RATE_HZ = BY_NAME["LOOP_RATE_HZ"].value
# the loop's tick, and the step every model is trained and exported at (carrt.control_period_s)
CONTROL_PERIOD_S = 1.0 / LOOP_RATE_HZ
CAMERA_MAX_AGE_S = BY_NAME["CAMERA_MAX_AGE_S"].value
ENCODER_MAX_AGE_S = BY_NAME["ENCODER_MAX_AGE_S"].value
BOARD_GRACE_S = BY_NAME["BOARD_GRACE_S"].value
FIRST_FRAME_TIMEOUT_S = BY_NAME["FIRST_FRAME_TIMEOUT_S"].value


def board_entries() -> tuple[Timing, ...]:
    return tuple(t for t in TABLE if t.side == "board")


def canonical() -> str:
    """The board's timing as the protocol hash sees it: names and values, no prose."""
    return "timing " + ",".join(f"{t.name}={int(t.value)}" for t in board_entries())


def render_markdown() -> str:
    rows = ["| name | value | side | why |", "|---|---|---|---|"]
    for t in TABLE:
        value = f"{t.value:g} {t.unit}"
        rows.append(f"| `{t.name}` | {value} | {t.side} | {t.why} |")
    return "\n".join(rows)
