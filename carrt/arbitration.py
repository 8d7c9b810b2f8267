"""The host's one place for safety arbitration: who drives this tick, and when nobody may.

The microcontroller still has the last word (watchdog, freshness, latch, arming checks, stall);
this module decides what the host asks for, so the two agree and the human sees why the car is
not moving. Everything here is a pure function of the inputs and the arbiter's own small state,
apart from `estop()`, the fast path: the joystick's reader thread calls it the moment the e-stop
button is pressed or the pad is removed, and it calls `on_estop()` (the link's `estop()`, which
writes an e-stop frame at once) from that thread instead of waiting for the next 10 Hz tick.

Modes (docs/safety.md): DISARMED → MANUAL / AUTO → ESTOP, and ESTOP is latched: only an explicit
clear (with a connected pad and neutral sticks) leaves it, and it leads to DISARMED, never
straight back to driving. Every entry into ESTOP, from whichever thread, calls `on_estop()`
exactly once.

Why the board's state is an input: the board may stop the car by itself (failsafe, reboot, its
own e-stop latch). The host follows it down (FAILSAFE/DISARMED → DISARMED, ESTOP → ESTOP) so it
never believes it is driving a car that is not listening, and the human must clear and arm again.
Telemetry lags the host's requests by a frame or two, so after a clear or an arm the board gets
a grace period (`BOARD_GRACE_S`, the link's own timeout for both) to catch up.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from carrt.config import CameraConfig, EncoderConfig
from carrt.interfaces import JoystickState, Mode
from carrt.reasons import Why, WhyText
from firmware_bridge.messages import Reason, State
from firmware_bridge.timing import BOARD_GRACE_S

"""How long the board may lag a clear or an arm before the host stops waiting for it."""


def arm_hint(controls: Mapping[str, str], allow_auto: bool) -> WhyText:
    """What a parked car tells its driver, naming the keys of the device in hand (`controls`,
    role → key or button name: the joystick's own `controls`; the role where it has none)."""
    arm = controls.get("arm", "the arm button")
    if allow_auto:
        return Why.NOT_ARMED_THEN_AUTO.text(arm=arm, auto=controls.get("auto", "the auto button"))
    return Why.NOT_ARMED.text(arm=arm)


@dataclass(frozen=True)
class ArbiterInputs:
    """Everything one decision depends on, measured at the start of the tick."""

    now: float  # clock seconds (the loop's clock), for the board grace periods
    joystick: JoystickState
    frame_age_s: float | None  # age of the newest camera frame; None before the first
    camera_lost: bool
    telemetry_age_s: float  # inf before the first telemetry
    board_state: State
    plan_action: tuple[float, float] | None = None  # μ of the plan computed this tick
    fallback_action: tuple[float, float] | None = None  # next step of the previous plan
    board_reason: int = 0  # messages.Reason, only used to explain a failsafe
    board_takeover: bool = False  # the board reports the receiver driving (a stick took over)
    camera_lost_reason: str = ""  # the camera's own words for why it is lost
    # the link saw a new boot id since the last tick: the board restarted, disarmed, and the
    # loop names it (board_reboot_text); '' when it did not
    board_rebooted: str = ""


@dataclass(frozen=True)
class Decision:
    """What the loop sends this tick, and which one-shot link requests go with it."""

    mode: Mode
    steering: float
    throttle: float
    source: str  # 'neutral' | 'human' | 'policy' | 'plan-fallback'
    reason: str = ""  # why the command is neutral (a WhyText); '' when someone drives
    refused: str = ""  # why a button press this tick was refused (a WhyText); '' when none was
    override: bool = False  # the human took over from the policy this tick (an intervention)
    estop: bool = False  # ESTOP was latched since the previous decision (from any thread)
    arm_request: bool = False  # the loop should ask the board to arm (link.arm)
    disarm_request: bool = False  # the loop should drop the arm request (link.disarm)
    clear_request: bool = False  # the loop should clear the board's latch (link.clear)


def _clip(value: float) -> float:
    return min(max(float(value), -1.0), 1.0)


def _finite(action: tuple[float, float]) -> bool:
    return all(math.isfinite(float(v)) for v in action)


def _failsafe(reason: int, held: bool = False) -> WhyText:
    """'board failsafe (link timeout)', or without the parenthesis when the loop gave no reason;
    `held`: the parked car's reason, which adds what to do."""
    if not reason:
        return (Why.BOARD_FAILSAFE_HELD if held else Why.BOARD_FAILSAFE).text()
    try:
        because = Reason(reason).name.lower().replace("_", " ")
    except ValueError:
        because = f"reason {reason}"
    why = Why.BOARD_FAILSAFE_BECAUSE_HELD if held else Why.BOARD_FAILSAFE_BECAUSE
    return why.text(because=because)


class Arbiter:
    """Mode machine and command selection; `step()` once per tick, `estop()` from any thread.

    `deadzone` is an extra margin on the joystick's values for sticks that arrive without a
    deadzone applied (a scripted expert, a keyboard); PygameJoystick already zeroes values
    inside its deadzone, so 0 (any non-zero stick value counts as moved) is right for it.
    """

    def __init__(
        self,
        *,
        allow_auto: bool,
        camera: CameraConfig,
        encoder: EncoderConfig,
        deadzone: float = 0.0,
        on_estop: Callable[[], None] | None = None,
        controls: Mapping[str, str] | None = None,
    ) -> None:
        self.allow_auto = allow_auto
        self.max_frame_age_s = camera.max_age_s
        self.max_telemetry_age_s = encoder.max_age_s
        self.deadzone = deadzone
        self._on_estop = on_estop
        self._lock = threading.Lock()
        self._mode = Mode.DISARMED
        self._why = arm_hint(controls or {}, allow_auto)
        self._estop_reason: str = ""  # a WhyText while latched
        self._estop_edge = False
        self._interventions = 0
        self._clear_since: float | None = None  # clear sent, board not yet out of its latch
        self._armed_since: float | None = None  # arm sent, board not yet seen ARMED
        self._board_armed_seen = False
        self._fallback_used = False
        self._reboot_why = ""  # a reboot's line, the parked car's reason until the next arm

    # ------------------------------------------------------------------ state
    @property
    def mode(self) -> Mode:
        return self._mode

    @property
    def interventions(self) -> int:
        return self._interventions

    @property
    def estop_reason(self) -> str:
        """What latched the e-stop (a WhyText), '' when none is latched."""
        return self._estop_reason

    # ------------------------------------------------------------------ fast path
    def estop(self, why: str = Why.PAD_ESTOP.text()) -> None:
        """Latch ESTOP now and put it on the wire from the calling thread (once per latch);
        `why` a WhyText, or a caller's own words (kept as Why.SAID_BY_CALLER).

        The callback runs under the lock on purpose: a clear cannot slip in between the latch
        and the frame on the wire, so the host and the board never disagree about the latch.
        """
        if not isinstance(why, WhyText):
            why = Why.SAID_BY_CALLER.text(words=why)
        with self._lock:
            self._latch(why)

    def _latch(self, why: WhyText) -> None:
        if self._mode == Mode.ESTOP:
            return
        self._mode = Mode.ESTOP
        self._estop_reason = why
        self._estop_edge = True
        self._clear_since = self._armed_since = None
        if self._on_estop is not None:
            self._on_estop()

    # ------------------------------------------------------------------ the tick
    def step(self, inputs: ArbiterInputs) -> Decision:
        with self._lock:
            return self._step(inputs)

    def _step(self, inp: ArbiterInputs) -> Decision:
        js, ev = inp.joystick, inp.joystick.events
        board = State(inp.board_state)
        moved = self._moved(js)
        arm = disarm = clear = override = False
        refused = ""

        # 0. A rebooted board is disarmed and re-validates its receiver: the car stops as a
        # disarm named by the reboot, not as the "joystick disconnected" that follows from it.
        rebooted = inp.board_rebooted and Why.BOARD_REBOOTED.text(line=inp.board_rebooted)
        if rebooted and self._mode in (Mode.MANUAL, Mode.AUTO):
            disarm = self._disarm(rebooted)
        elif rebooted and self._mode == Mode.DISARMED:
            self._why = rebooted
        self._reboot_why = rebooted or self._reboot_why

        # 1. Everything that latches ESTOP.
        if ev.estop:
            self._latch(Why.ESTOP_BUTTON.text())
        if not js.connected and self._mode in (Mode.MANUAL, Mode.AUTO):
            if js.through_board and inp.telemetry_age_s > self.max_telemetry_age_s:
                # the transmitter is read through a board that stopped talking: the board's
                # watchdog stops the car; the host follows it down (a reboot is then named)
                disarm = self._disarm(Why.BOARD_SILENT.text())
            else:  # the person's controls are gone: named as the part that went
                gone = Why.RECEIVER_LOST if js.through_board else Why.JOYSTICK_DISCONNECTED
                self._latch(gone.text())
        if inp.camera_lost and self._mode == Mode.AUTO:
            because = inp.camera_lost_reason
            lost = Why.CAMERA_LOST_BECAUSE.text(because=because) if because else None
            self._latch(lost or Why.CAMERA_LOST.text())
        if board == State.ESTOP:
            if self._clear_since is None:
                self._latch(Why.BOARD_ESTOP.text())
            elif inp.now - self._clear_since > BOARD_GRACE_S:
                self._latch(Why.BOARD_KEPT_ESTOP.text())
        if self._clear_since is not None and board not in (State.ESTOP, State.FAILSAFE):
            self._clear_since = None

        # 2. Follow the board down when it stopped listening to us.
        if self._mode in (Mode.MANUAL, Mode.AUTO):
            if board == State.FAILSAFE:
                disarm = self._disarm(_failsafe(inp.board_reason))
            elif board == State.ARMED:
                self._board_armed_seen = True
            elif board == State.DISARMED and (
                self._board_armed_seen
                or self._armed_since is None
                or inp.now - self._armed_since > BOARD_GRACE_S
            ):
                went = Why.BOARD_DISARMED if self._board_armed_seen else Why.BOARD_DID_NOT_ARM
                disarm = self._disarm(went.text())

        # 3. Button edges.
        if self._mode == Mode.ESTOP:
            if ev.clear and not ev.estop:
                refused, clear = self._clear(js, moved, inp.now)
            if ev.arm and not refused:
                refused = (Why.ARM_AFTER_CLEAR if clear else Why.ARM_WHILE_LATCHED).text()
        elif self._mode == Mode.DISARMED:
            if ev.clear:
                if board in (State.ESTOP, State.FAILSAFE):
                    refused, clear = self._clear(js, moved, inp.now)
                else:
                    refused = Why.NOTHING_TO_CLEAR.text()
            if ev.arm:
                refusal = self._arm_refusal(js, moved, board)
                if refusal:
                    refused = refusal
                else:
                    self._mode = Mode.MANUAL
                    self._armed_since, self._board_armed_seen = inp.now, False
                    self._reboot_why = ""
                    arm = True
            elif ev.toggle_auto:
                refused = Why.AUTO_BEFORE_ARM.text()
        elif ev.arm:
            disarm = self._disarm(Why.DISARMED_BY_HUMAN.text())
        elif self._mode == Mode.AUTO and (moved or inp.board_takeover):
            self._mode = Mode.MANUAL
            self._interventions += 1
            override = True
        elif ev.toggle_auto:
            if self._mode == Mode.AUTO:
                self._mode = Mode.MANUAL
            else:
                refusal = self._auto_refusal(inp, moved)
                if refusal:
                    refused = refusal
                else:
                    self._mode = Mode.AUTO
                    self._fallback_used = False

        # 4. The command.
        steering, throttle, source, reason = self._command(inp, board)
        estop_edge, self._estop_edge = self._estop_edge, False
        return Decision(
            mode=self._mode,
            steering=_clip(steering),
            throttle=_clip(throttle),
            source=source,
            reason=reason,
            refused=refused,
            override=override,
            estop=estop_edge,
            arm_request=arm,
            disarm_request=disarm,
            clear_request=clear,
        )

    # ------------------------------------------------------------------ rules
    def _moved(self, js: JoystickState) -> bool:
        return abs(js.steering) > self.deadzone or abs(js.throttle) > self.deadzone

    def _disarm(self, why: WhyText) -> bool:
        self._mode = Mode.DISARMED
        self._why = why
        self._armed_since = None
        return True

    def _clear(self, js: JoystickState, moved: bool, now: float) -> tuple[str, bool]:
        if not js.connected:
            return Why.CLEAR_NO_JOYSTICK.text(), False
        if moved:
            return Why.CLEAR_STICKS_OUT.text(), False
        self._mode = Mode.DISARMED
        self._why = Why.CLEARED.text()
        self._estop_reason = ""
        self._clear_since = now
        return "", True

    def _arm_refusal(self, js: JoystickState, moved: bool, board: State) -> str:
        if not js.connected:
            return Why.ARM_NO_JOYSTICK.text()
        if not js.neutral_since_connect:
            return Why.ARM_PAD_NEVER_NEUTRAL.text()
        if moved:
            return Why.ARM_STICKS_OUT.text()
        if self._clear_since is not None:
            return Why.ARM_BOARD_CATCHING_UP.text()
        if board in (State.ESTOP, State.FAILSAFE):
            return Why.ARM_BOARD_LATCHED.text(state=board.name.lower())
        return ""

    def _auto_refusal(self, inp: ArbiterInputs, moved: bool) -> str:
        if not self.allow_auto:
            return Why.AUTO_IN_TELEOP.text()
        if moved:
            return Why.AUTO_STICKS_OUT.text()
        return self._staleness(inp, refusal=True)

    def _staleness(self, inp: ArbiterInputs, refusal: bool = False) -> str:
        """Why AUTO cannot drive now; '' when it can. A refusal (one per press) says how old;
        the neutral reason of a tick names only the limit, so it stays the same tick after tick
        and the person is told once (the loop's fault line has the age)."""
        if inp.camera_lost:
            return (Why.AUTO_CAMERA_LOST if refusal else Why.CAMERA_LOST).text()
        if inp.frame_age_s is None:
            return (Why.AUTO_NO_FRAME if refusal else Why.NO_FRAME).text()
        if inp.frame_age_s > self.max_frame_age_s:
            if refusal:
                return Why.AUTO_FRAME_OLD.text(age_ms=inp.frame_age_s * 1000)
            return Why.FRAME_OLDER_THAN.text(limit_ms=self.max_frame_age_s * 1000)
        if inp.telemetry_age_s > self.max_telemetry_age_s:
            if math.isinf(inp.telemetry_age_s):
                return (Why.AUTO_NO_TELEMETRY if refusal else Why.NO_TELEMETRY).text()
            if refusal:
                return Why.AUTO_TELEMETRY_OLD.text(age_ms=inp.telemetry_age_s * 1000)
            return Why.TELEMETRY_OLDER_THAN.text(limit_ms=self.max_telemetry_age_s * 1000)
        return ""

    def _command(self, inp: ArbiterInputs, board: State) -> tuple[float, float, str, str]:
        if self._mode == Mode.ESTOP:
            return 0.0, 0.0, "neutral", Why.ESTOP.text(because=self._estop_reason)
        if self._mode == Mode.DISARMED:
            if self._reboot_why:  # its receiver re-validating is part of it, not news
                return 0.0, 0.0, "neutral", self._reboot_why
            if not inp.joystick.connected:
                silent = inp.telemetry_age_s > self.max_telemetry_age_s
                if inp.joystick.through_board and silent:
                    return 0.0, 0.0, "neutral", Why.BOARD_SILENT.text()
                return 0.0, 0.0, "neutral", Why.NO_JOYSTICK.text()
            if board == State.FAILSAFE and self._clear_since is None:
                return 0.0, 0.0, "neutral", _failsafe(inp.board_reason, held=True)
            return 0.0, 0.0, "neutral", self._why
        if self._mode == Mode.MANUAL:
            return inp.joystick.steering, inp.joystick.throttle, "human", ""
        stale = self._staleness(inp)
        if stale:
            return 0.0, 0.0, "neutral", stale
        if inp.plan_action is not None:
            self._fallback_used = False
            if not _finite(inp.plan_action):
                return 0.0, 0.0, "neutral", Why.POLICY_NOT_FINITE.text()
            return inp.plan_action[0], inp.plan_action[1], "policy", ""
        if inp.fallback_action is not None and not self._fallback_used:
            self._fallback_used = True
            if not _finite(inp.fallback_action):
                return 0.0, 0.0, "neutral", Why.POLICY_NOT_FINITE.text()
            return inp.fallback_action[0], inp.fallback_action[1], "plan-fallback", ""
        if inp.fallback_action is not None:
            return 0.0, 0.0, "neutral", Why.PLAN_USED_ALREADY.text()
        return 0.0, 0.0, "neutral", Why.NO_PLAN.text()
