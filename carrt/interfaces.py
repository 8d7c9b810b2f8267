"""One small interface per role on the car.

The control loop only ever talks to these. Real drivers (OpenCV camera, pygame joystick,
onnxruntime policy, serial board link, wall clock, disk writer) and their stand-ins (video
file, synthetic events, simulator, simulated clock) implement the same methods, so the loop
cannot tell which it has and every stand-in is a first-class implementation, not a patch.
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass, field, make_dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from carrt.model_contract import IMAGE_SHAPE


class Mode(enum.IntEnum):
    """Who drives. ESTOP is latched until the human clears it."""

    DISARMED = 0
    MANUAL = 1
    AUTO = 2
    ESTOP = 3


# ----------------------------------------------------------------------------- clock
@runtime_checkable
class Clock(Protocol):
    """Monotonic time in seconds; the simulator's clock jumps instead of sleeping."""

    def now(self) -> float: ...

    def sleep_until(self, deadline: float) -> None: ...


# ----------------------------------------------------------------------------- camera
@dataclass(frozen=True)
class CameraFrame:
    """A raw frame as captured: any size, RGB uint8, with the moment it was captured."""

    image: np.ndarray  # (H, W, 3) uint8 RGB, before crop/resize
    captured_at: float  # clock seconds when the frame left the sensor/decoder
    seq: int  # increases by one per captured frame; a gap means frames were skipped


@runtime_checkable
class Camera(Protocol):
    def start(self) -> None: ...

    def stop(self) -> None: ...

    def latest(self) -> CameraFrame | None:
        """The newest frame captured so far (never blocks); None before the first."""
        ...

    def wait_newer(self, seq: int, until: float) -> None:
        """Return once a frame newer than `seq` has been captured, or at `until` on the
        camera's clock, whichever comes first: the loop starts its tick on a frame's arrival
        (carrt/frame_lock.py)."""
        ...

    @property
    def lost(self) -> bool:
        """True when the source has died (device gone, pipeline error, file ended)."""
        ...


# ----------------------------------------------------------------------------- joystick
@dataclass(frozen=True)
class JoystickEvents:
    """Edges since the last poll (buttons pressed), so a press is never missed or repeated."""

    estop: bool = False
    toggle_auto: bool = False  # switch MANUAL <-> AUTO (drive only)
    arm: bool = False  # arm / disarm request (start button)
    toggle_record: bool = False
    lap: bool = False  # lap marker (for `carrt report`)
    clear: bool = False  # clear a latched e-stop (needs neutral sticks)
    quit: bool = False  # window closed / quit requested


@dataclass(frozen=True)
class JoystickState:
    connected: bool
    steering: float  # [-1, 1], after deadzone, + right
    throttle: float  # [-1, 1], after deadzone, + forward
    neutral_since_connect: bool  # every mapped axis has been seen at neutral since (re)connect
    events: JoystickEvents = field(default_factory=JoystickEvents)
    # the controls are read through the board (the RC receiver): when the board goes silent
    # they go with it, and that is the board's failsafe, not a pad pulled out
    through_board: bool = False

    @property
    def sticks_moved(self) -> bool:
        return self.steering != 0.0 or self.throttle != 0.0


@runtime_checkable
class Joystick(Protocol):
    def start(self, on_estop: Any) -> None:
        """Start reading. `on_estop()` is called from the reader thread the moment the e-stop
        button is pressed or the pad is removed, so the e-stop reaches the wire without
        waiting for the next loop tick."""
        ...

    def stop(self) -> None: ...

    def poll(self) -> JoystickState:
        """Current sticks and the button edges since the previous poll."""
        ...


# ----------------------------------------------------------------------------- board
@runtime_checkable
class Board(Protocol):
    """The microcontroller as the loop sees it: the last word on the car, behind a link.

    Implemented by firmware_bridge.link.BoardLink over a serial port (the real board, or the
    virtual one behind a pty) and by firmware_bridge.direct.DirectBoardLink over the same C core
    in-process on a simulated clock. The loop cannot tell them apart.
    """

    counters: Any  # LinkCounters: frames, e-stops, reconnects (the summary reports them)
    error: Exception | None  # a fatal link error (protocol mismatch) the session re-raises

    @property
    def telemetry(self) -> Any:
        """The newest TelemetrySample (telemetry + host receive time), None before the first."""
        ...

    @property
    def board_state(self) -> Any:
        """messages.State as the board last reported it."""
        ...

    def telemetry_age_s(self) -> float: ...

    def set_command(self, steering: float, throttle: float, *, send_now: bool = False) -> Any:
        """The decision the link repeats to the board; returns when it went out (or None)."""
        ...

    def estop(self) -> None:
        """E-stop on the wire now, from the caller's thread."""
        ...

    def set_auto(self, auto: bool) -> None:
        """Whether the policy drives (with a receiver wired, the board lets a stick take over,
        and hands the wheels back on the next 0 -> 1 of this)."""
        ...

    def request_arm(self) -> None: ...

    def request_clear(self) -> None: ...

    def disarm(self) -> None: ...


# ----------------------------------------------------------------------------- policy
@dataclass(frozen=True)
class Plan:
    """The policy's output: a Gaussian over the next H actions (steering, throttle)."""

    mu: np.ndarray  # (H, 2) float32
    sigma: np.ndarray  # (H, 2) float32


@runtime_checkable
class Policy(Protocol):
    metadata: dict[str, str]
    horizon: int

    def predict(self, image: np.ndarray, speed_mps: float) -> Plan:
        """image: (96, 96, 3) uint8 RGB exactly as recorded; speed in m/s."""
        ...


# ----------------------------------------------------------------------------- episodes
@dataclass(frozen=True)
class StepField:
    """One field of a Step: what the loop fills in each period, and its column in steps.bin."""

    name: str
    type: str  # the Step attribute's annotation
    disk: str  # numpy type of its column in steps.bin; "" for the image, which is in frames.u8
    shape: tuple[int | str, ...] = ()  # per step; "horizon": the episode's plan horizon (rows)
    doc: str = ""
    optional: bool = False  # None when absent (the Step's default)


# Everything recorded for one control period (docs/episodes.md), in the record's byte order.
# The Step below and the on-disk record (carrt/episodes/format.py step_dtype) are both built
# from this table, so they cannot disagree; reordering or retyping a row changes the bytes of
# every recorded episode, which is a new format version, not a refactor.
STEP_FIELDS: tuple[StepField, ...] = (
    StepField("index", "int", "<i8", doc="the loop's step index (gaps: steps the writer dropped)"),
    StepField("image", "np.ndarray", "", IMAGE_SHAPE, "uint8 RGB, the policy's input as it saw it"),
    StepField("frame_captured_at", "float", "<f8", doc="clock seconds"),
    StepField("command_sent_at", "float", "<f8",
              doc="clock seconds when the command was written to the link"),
    StepField("wall_time", "float", "<f8", doc="unix seconds at the tick, for humans"),
    StepField("encoder_ticks", "int", "<i8", doc="the board's count, as last reported"),
    StepField("speed_mps", "float", "<f4", doc="metres per second"),
    StepField("human_action", "tuple[float, float]", "<f4", (2,),
              "a*: what the human's sticks said (steering, throttle)"),
    StepField("policy_action", "tuple[float, float]", "<f4", (2,),
              "first step of mu when AUTO, else (nan, nan)"),
    StepField("executed_action", "tuple[float, float]", "<f4", (2,),
              "a: what was sent to the board"),
    StepField("plan_mu", "np.ndarray | None", "<f4", ("horizon", 2),
              "the fresh plan's mean, when AUTO", optional=True),
    StepField("plan_sigma", "np.ndarray | None", "<f4", ("horizon", 2),
              "the fresh plan's standard deviation, when AUTO", optional=True),
    StepField("mode", "Mode", "u1", doc="who drove"),
    StepField("override", "bool", "?", doc="human took over from the policy (intervention edge)"),
    StepField("estop", "bool", "?", doc="e-stop latched this step"),
    StepField("noise", "bool", "?", doc="noise was injected into the executed action"),
    StepField("collision", "bool", "?",
              doc="a collision event happened at this step (sim, or e-stop in drive)"),
    StepField("lap", "bool", "?", doc="the lap-marker button was pressed at this step"),
)  # fmt: skip


def _step_record() -> type:
    """The Step dataclass from STEP_FIELDS: keyword-only (eighteen fields are not positional),
    its docstring the table's docs."""
    doc = "Everything recorded for one control period (docs/episodes.md).\n\n" + "\n".join(
        f"{f.name}: {f.doc}" for f in STEP_FIELDS
    )
    return make_dataclass(
        "Step",
        [
            (f.name, f.type, dataclasses.field(default=None)) if f.optional else (f.name, f.type)
            for f in STEP_FIELDS
        ],
        kw_only=True,
        namespace={"__module__": __name__, "__doc__": doc},
    )


Step = _step_record()


@runtime_checkable
class EpisodeSink(Protocol):
    """Where the loop hands steps. Must never block the loop: it drops and counts instead."""

    def begin(self, metadata: dict[str, Any]) -> None: ...

    def write(self, step: Step) -> bool:
        """Queue a step; False (and a counted drop) when the writer is behind."""
        ...

    def end(self, reason: str) -> None: ...

    def event(self, kind: str, detail: dict[str, Any]) -> None:
        """Something that happened to the car in this episode (a board reboot), kept with it."""
        ...

    @property
    def dropped(self) -> int: ...


@dataclass(frozen=True)
class LiveStatus:
    """What the loop did on its last tick, for whoever watches (the simulator's keyboard window,
    the browser view of carrt/view/).

    The loop replaces it whole once per tick, so a reader on another thread always sees one
    tick's values together, and never makes the loop wait. The arrays and dicts in it are the
    tick's own (made new each tick, never changed after): publishing them costs a reference,
    and whatever a watcher does with them (JPEG, JSON) happens on the watcher's thread.
    """

    mode: Mode = Mode.DISARMED
    why: str = ""  # why the car is held at neutral, or what latched the e-stop
    speed_mps: float = 0.0
    human: tuple[float, float] = (0.0, 0.0)  # (steering, throttle) from the sticks or keys
    executed: tuple[float, float] = (0.0, 0.0)  # what was sent to the board
    recording: bool = False
    episodes: int = 0
    collisions: int = 0
    laps: int = 0
    tick: int = 0  # ticks published so far (the view's frame counter)
    deadline: float = float("nan")  # when the tick started (on its frame), on the loop's clock
    frame: CameraFrame | None = None  # the raw camera frame the tick used
    image: np.ndarray | None = None  # the 96×96 crop the policy saw
    policy: tuple[float, float] | None = None  # the plan's action this tick (fresh or fallback)
    plan: Plan | None = None  # the last fresh plan: μ ± σ over the horizon
    sections_s: dict[str, float] = field(default_factory=dict)  # this tick's section timings
    board_state: str = ""  # as the board last reported it
    telemetry_age_s: float = float("inf")
    link_counters: dict[str, Any] = field(default_factory=dict)  # a copy, taken at the tick
    alert: str = ""  # what the person must know now (recording failed: the disk is full)
    # the session's latest fault and board lines (camera stale, board rebooted), newest last,
    # each with the loop's clock time it was said at
    notices: tuple[tuple[float, str], ...] = ()
