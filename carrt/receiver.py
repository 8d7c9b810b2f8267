"""The car's own RC transmitter as the person's controls, read back from the board.

The receiver is wired to the board, not to this computer: the board decodes its pulses and
rules on them itself (the switch's e-stop, a stick's take-over in AUTO, MANUAL straight through,
the loss failsafe; firmware_bridge/firmware/carrt_fw/src/fw_core.h), and reports the three
channels in every TELEMETRY. This module turns that report into the same `Joystick` contract the
game pad implements, so the loop, the arbiter, the episode record and the live view cannot tell
which the person holds: the sticks become steering and throttle in [-1, 1] by the receiver's
calibration (`[receiver]` in the car's config), and what a pad does with buttons a transmitter
does with its switch and with gestures of the sticks:

- the switch to its e-stop position: e-stop (the board has latched it already);
- the switch back to run: clear (with the sticks centred, as the pad's clear);
- steering held full right with the throttle at neutral for `gesture_s`, then let go, while the
  board is disarmed: arm (on the letting go: arming wants the sticks centred);
- in `carrt drive`, while the receiver drives (MANUAL, or after a take-over), both sticks let go
  for `release_s`: the policy drives again (AUTO). A stick in AUTO takes over, on the board: so
  a person takes over by touching a stick and gives back by letting go.

`PadAndReceiver` is the two together (`controls = "both"`). `RadioStandIn` is the simulator's
transmitter: it takes a keyboard's or a scripted expert's sticks and buttons and puts them on the
board's receiver pins as pulses, so the whole path runs without hardware.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from carrt.config import ReceiverConfig
from carrt.interfaces import JoystickEvents, JoystickState
from firmware_bridge import messages as m

RECEIVER_KEYS = {
    "arm": "steering held full right for the gesture time, then let go (throttle at neutral)",
    "auto": "both sticks let go for the release time (in drive)",
    "estop": "the transmitter's switch",
    "clear": "the switch back to run (sticks centred)",
}
FULL = 0.9  # a stick past this is "full" for a gesture
STALE_S = 0.25  # telemetry older than this: the receiver counts as disconnected


def stick(width_us: int, low_us: int, centre_us: int, high_us: int, deadzone_us: int) -> float:
    """A receiver pulse as -1..1 about its centre, 0 inside the deadzone (the board's), clipped.
    `low_us` is the pulse at -1 (full left, full brake), whichever side of the centre it is."""
    offset = width_us - centre_us
    if abs(offset) <= deadzone_us:
        return 0.0
    end = high_us if (offset > 0) == (high_us > centre_us) else low_us
    span = end - centre_us
    value = (abs(offset) - deadzone_us) / max(abs(span) - deadzone_us, 1)
    sign = 1.0 if end == high_us else -1.0
    return max(-1.0, min(1.0, sign * value))


@dataclass
class _Hold:
    """How long a gesture has been held (None: not held)."""

    since: float | None = None
    fired: bool = False

    def update(self, held: bool, now: float, hold_s: float) -> bool:
        """True once, when the gesture has been held for hold_s."""
        if not held:
            self.since, self.fired = None, False
            return False
        if self.since is None:
            self.since = now
        if not self.fired and now - self.since >= hold_s:
            self.fired = True
            return True
        return False


class ReceiverControls:
    """The transmitter as a Joystick, from the board's TELEMETRY (see the module docstring).

    `link` is the board link (its `telemetry`, `telemetry_age_s()`), `clock` the loop's clock.
    `radio` (the simulator's RadioStandIn) is advanced at each poll, before the board is read.
    """

    def __init__(
        self,
        link: Any,
        config: ReceiverConfig,
        clock: Callable[[], float],
        radio: Any = None,
        *,
        allow_auto: bool = False,
    ) -> None:
        self.link = link
        self.config = config
        self.clock = clock
        self.radio = radio
        self.allow_auto = allow_auto
        self.controls = dict(RECEIVER_KEYS)
        self.controls["arm"] = f"steering held full right for {config.gesture_s:g} s, let go"
        self.controls["auto"] = f"both sticks let go for {config.release_s:g} s"
        self._on_estop: Callable[[], None] | None = None
        self._was_connected = False
        self._neutral_seen = False
        self._switch_estop: bool | None = None
        self._arm_hold = _Hold()
        self._auto_hold = _Hold()
        self._arm_armed = False  # the arm gesture was held: arm when the stick is let go

    def start(self, on_estop: Callable[[], None]) -> None:
        self._on_estop = on_estop
        if self.radio is not None:
            self.radio.start(on_estop)

    def stop(self) -> None:
        if self.radio is not None:
            self.radio.stop()

    def sticks_from(self, tel: m.Telemetry) -> tuple[float, float]:
        c = self.config
        steering = stick(
            tel.rc_steer_us, c.steer_left_us, c.steer_center_us, c.steer_right_us, c.deadzone_us
        )
        throttle = stick(
            tel.rc_throttle_us,
            c.throttle_reverse_us,
            c.throttle_neutral_us,
            c.throttle_forward_us,
            c.deadzone_us,
        )
        return steering, throttle

    def poll(self) -> JoystickState:
        if self.radio is not None:
            self.radio.update()
        now = self.clock()
        sample = self.link.telemetry
        tel = sample.telemetry if sample is not None else None
        age = self.link.telemetry_age_s()
        connected = (
            tel is not None
            and math.isfinite(age)
            and age <= STALE_S
            and bool(tel.flags & m.TelemetryFlags.RC_SIGNAL)
        )
        if not connected:
            self._was_connected = self._neutral_seen = False
            self._arm_hold.update(False, now, 0.0)
            self._auto_hold.update(False, now, 0.0)
            self._arm_armed = False
            lost = JoystickState(False, 0.0, 0.0, False, through_board=True)
            return with_passed_on(lost, self.radio)
        if not self._was_connected:
            self._was_connected, self._neutral_seen = True, False
        steering, throttle = self.sticks_from(tel)
        if steering == 0.0 and throttle == 0.0:
            self._neutral_seen = True
        events = self._events(tel, steering, throttle, now)
        state = JoystickState(True, steering, throttle, self._neutral_seen, events)
        return with_passed_on(state, self.radio)

    def _events(self, tel: m.Telemetry, steering: float, throttle: float, now: float):
        switch_estop = tel.rc_switch_us >= self.config.estop_us
        estop = switch_estop and self._switch_estop is False
        clear = not switch_estop and self._switch_estop is True
        if switch_estop and self._switch_estop is None:
            estop = True  # already at e-stop when first seen: the host latches it too
        self._switch_estop = switch_estop
        if estop and self._on_estop is not None:
            self._on_estop()
        hold = self.config.gesture_s
        disarmed = tel.state == m.State.DISARMED
        if self._arm_hold.update(disarmed and throttle == 0.0 and steering >= FULL, now, hold):
            self._arm_armed = True
        arm = False
        if steering == 0.0 and throttle == 0.0:  # let go: the gesture counts now
            arm, self._arm_armed = self._arm_armed, False
        elif throttle != 0.0:
            self._arm_armed = False  # driving off is no gesture
        receiver_drives = tel.state == m.State.ARMED and bool(
            tel.flags & m.TelemetryFlags.RC_DRIVES
        )
        toggle_auto = self._auto_hold.update(
            self.allow_auto and receiver_drives and steering == 0.0 and throttle == 0.0,
            now,
            self.config.release_s,
        )
        return JoystickEvents(estop=estop, clear=clear, arm=arm, toggle_auto=toggle_auto)


class PadAndReceiver:
    """`controls = "both"`: the pad's buttons and either's sticks (the receiver's once moved).

    Connected only while both are: losing either while driving is the e-stop the arbiter
    latches for a lost pad (and the board's failsafe for a lost receiver)."""

    def __init__(self, pad: Any, receiver: ReceiverControls) -> None:
        self.pad = pad
        self.receiver = receiver
        self.controls = dict(getattr(pad, "controls", {}))

    def start(self, on_estop: Callable[[], None]) -> None:
        self.pad.start(on_estop)
        self.receiver.start(on_estop)

    def stop(self) -> None:
        self.pad.stop()
        self.receiver.stop()

    def poll(self) -> JoystickState:
        pad, rx = self.pad.poll(), self.receiver.poll()
        sticks = rx if rx.sticks_moved else pad
        e, f = pad.events, rx.events
        events = JoystickEvents(
            estop=e.estop or f.estop, toggle_auto=e.toggle_auto or f.toggle_auto,
            arm=e.arm or f.arm, toggle_record=e.toggle_record, lap=e.lap,
            clear=e.clear or f.clear, quit=e.quit,
        )  # fmt: skip
        return JoystickState(
            connected=pad.connected and rx.connected,
            steering=sticks.steering,
            throttle=sticks.throttle,
            neutral_since_connect=pad.neutral_since_connect and rx.neutral_since_connect,
            events=events,
            through_board=pad.connected and not rx.connected,
        )


class RadioStandIn:
    """The simulator's transmitter: a keyboard's or a scripted expert's sticks and buttons, put
    on the board's receiver pins (`board.set_receiver(steer_us, throttle_us, switch_us)`).

    Its buttons become what a person does with a transmitter: e-stop flips the switch to its
    e-stop position and clear flips it back (or to e-stop and back, for a latch of the host's);
    arm holds the steering full right and lets go; auto lets both sticks go; each for the
    gesture time plus a little, the device's sticks set aside meanwhile. The device's quit, lap
    and record buttons have no radio twin: they are passed on.
    """

    MARGIN_S = 0.25  # a gesture is held this much longer than needed
    SWITCH_CYCLE_S = 0.3  # clear: the switch at e-stop this long, then back to run

    def __init__(
        self, device: Any, board: Any, config: ReceiverConfig, clock: Callable[[], float]
    ) -> None:
        self.device = device
        self.board = board
        self.config = config
        self.clock = clock
        self.switch_estop = False
        self._widths = self.board_widths(0.0, 0.0)
        self._gesture: tuple[float, float] | None = None  # (steering held, until)
        self._release_until = 0.0
        self._switch_back_at = 0.0
        self.passed_on = JoystickEvents()

    def start(self, on_estop: Callable[[], None]) -> None:
        # the device's own fast e-stop path flips the switch at once
        self.device.start(lambda: self._flip(True))

    def stop(self) -> None:
        self.device.stop()

    def _flip(self, estop: bool) -> None:
        self.switch_estop = estop
        self._send(self._widths)

    def board_widths(self, steering: float, throttle: float) -> tuple[int, int]:
        c = self.config

        def width(v: float, low: int, mid: int, high: int) -> int:
            v = max(-1.0, min(1.0, float(v)))
            return round(mid + (high - mid) * v) if v >= 0 else round(mid + (mid - low) * v)

        return (
            width(steering, c.steer_left_us, c.steer_center_us, c.steer_right_us),
            width(throttle, c.throttle_reverse_us, c.throttle_neutral_us, c.throttle_forward_us),
        )

    def _send(self, widths: tuple[int, int]) -> None:
        self._widths = widths
        switch = self.config.estop_us + 200 if self.switch_estop else self.config.estop_us - 500
        self.board.set_receiver(widths[0], widths[1], max(800, min(2200, switch)))

    def update(self) -> None:
        state = self.device.poll()
        now = self.clock()
        ev = state.events
        if ev.estop:
            self.switch_estop = True
        elif ev.clear and not self.switch_estop and now >= self._switch_back_at:
            # the host's own latch (a collision, a lost camera): a person clears it by flipping
            # the switch to e-stop and back, which is what the stand-in does
            self.switch_estop, self._switch_back_at = True, now + self.SWITCH_CYCLE_S
        elif ev.clear:
            self.switch_estop = False
        if self.switch_estop and self._switch_back_at and now >= self._switch_back_at:
            self.switch_estop, self._switch_back_at = False, 0.0
        if self._gesture is None and now >= self._release_until:
            if ev.arm:
                self._gesture = (1.0, now + self.config.gesture_s + self.MARGIN_S)
            elif ev.toggle_auto:  # both sticks let go
                self._gesture = (0.0, now + self.config.release_s + self.MARGIN_S)
        self.passed_on = JoystickEvents(quit=ev.quit, lap=ev.lap, toggle_record=ev.toggle_record)
        if self._gesture is not None:
            steering, until = self._gesture
            if now >= until:
                self._gesture = None
                self._release_until = now + 0.25  # the stick let go, centred for a moment
                self._send(self.board_widths(0.0, 0.0))
            else:
                self._send(self.board_widths(steering, 0.0))
            return
        if now < self._release_until:
            self._send(self.board_widths(0.0, 0.0))
            return
        self._send(self.board_widths(state.steering, state.throttle))


def with_passed_on(state: JoystickState, radio: RadioStandIn | None) -> JoystickState:
    """The receiver's state plus the stand-in device's quit/lap/record presses."""
    if radio is None:
        return state
    p = radio.passed_on
    return replace(
        state,
        events=replace(
            state.events, quit=p.quit, lap=p.lap or state.events.lap,
            toggle_record=p.toggle_record or state.events.toggle_record,
        ),
    )  # fmt: skip
