"""One small interface per role on the car.

The control loop only ever talks to these. Real drivers (OpenCV camera, pygame joystick,
onnxruntime policy, serial board link, wall clock, disk writer) and their stand-ins (video
file, synthetic events, simulator, simulated clock) implement the same methods, so the loop
cannot tell which it has and every stand-in is a first-class implementation, not a patch.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np


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
@dataclass
class Step:
    """Everything recorded for one control period (docs/episodes.md)."""

    index: int
    image: np.ndarray  # (96, 96, 3) uint8 RGB
    frame_captured_at: float  # clock seconds
    command_sent_at: float  # clock seconds when the command was written to the link
    wall_time: float  # unix seconds at the tick, for humans
    speed_mps: float
    encoder_ticks: int
    human_action: tuple[float, float]  # a*: what the human's sticks said (steering, throttle)
    policy_action: tuple[float, float]  # first step of μ when AUTO, else (nan, nan)
    executed_action: tuple[float, float]  # a: what was sent to the board
    mode: Mode
    override: bool  # human took over from the policy this step (intervention edge)
    estop: bool  # e-stop latched this step
    noise: bool  # noise was injected into the executed action
    collision: bool  # a collision event happened at this step (sim, or e-stop in drive)
    lap: bool  # the lap-marker button was pressed at this step
    plan_mu: np.ndarray | None = None  # (H, 2) when AUTO
    plan_sigma: np.ndarray | None = None  # (H, 2) when AUTO


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
