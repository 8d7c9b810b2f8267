"""The human's pad, read by pygame (SDL2) in its own thread; the e-stop never waits for a tick.

Modelled on openpilot's joystick dead-man: the pad is a safety device before it is a steering
wheel. The reader thread calls `on_estop()` the moment the e-stop button goes down or the pad
disappears, so the e-stop frame is on the wire within one frame instead of at the next 10 Hz
loop tick; nothing sleeps between taking the event off SDL's queue and that call.

Wireless pads lie after a reconnect: an axis can report its last value, or full scale, until it is
moved (docs/safety.md). So after every (re)connect `neutral_since_connect` stays False until every
mapped axis has been *observed* inside the deadzone: an axis event, or a `get_axis()` reading of the
opened device taken after SDL has pumped it once (before that SDL reports 0 for every axis, which
would be exactly the lie we are guarding against).

Layouts are SDL2's raw joystick indices (no GameController remapping) under SDL's Linux evdev
driver: buttons numbered by evdev key code from BTN_JOYSTICK upwards, axes by ABS code without
the hats. That needs SDL's HIDAPI drivers off (they renumber pads in GameController order when
hidraw is readable, e.g. with Steam's udev rules), so this module sets SDL_JOYSTICK_HIDAPI=0
unless the environment says otherwise. Sticks: left X steers, right Y drives, like an RC
transmitter; pushing a stick forward reads -1, hence `invert_throttle = true` by default.

| role          | xbox (xpad, wired) | ps4 (DualShock 4, hid-playstation) | f710 (switch at X) |
|---------------|--------------------|------------------------------------|--------------------|
| steering axis | 0 left stick X     | 0 left stick X                     | 0 left stick X     |
| throttle axis | 4 right stick Y    | 4 right stick Y                    | 4 right stick Y    |
| e-stop        | 1 B                | 1 circle                           | 1 B                |
| arm / disarm  | 7 Start            | 9 Options                          | 7 Start            |
| manual ↔ auto | 3 Y                | 2 triangle                         | 3 Y                |
| record        | 2 X                | 3 square                           | 2 X                |
| lap marker    | 5 RB               | 5 R1                               | 5 RB               |
| clear e-stop  | 6 Back             | 8 Share                            | 6 Back             |

Other raw indices, for `custom` layouts: xbox/f710 buttons A 0, LB 4, Guide 8, L3 9, R3 10;
axes LT 2, right X 3, RT 5 (triggers rest at -1: never map throttle to one, it never reads
neutral). DualShock 4 (hid-playstation, or hid-sony since Linux 4.10): cross 0, L1 4, L2 6,
R2 7, PS 10, L3 11, R3 12; axes L2 2, right X 3, R2 5. An F710 in DirectInput mode (switch at
D), an Xbox pad over Bluetooth without xpadneo, or any pad on Windows/macOS numbers things
differently: use `custom`. A config field >= 0 overrides the preset's value.

pygame's event queue is process-wide: this reader owns it, so nothing else in the process may
call `pygame.event.get()`, and at most one PygameJoystick runs at a time.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass, fields, replace

from carrt.config import JoystickConfig
from carrt.errors import UserError
from carrt.interfaces import JoystickEvents, JoystickState

os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
# The raw indices in the table above are the evdev driver's; HIDAPI would renumber them.
os.environ.setdefault("SDL_JOYSTICK_HIDAPI", "0")
# Without this SDL drops pad events (the e-stop button included) whenever a pygame window
# exists but lacks focus, e.g. a viewer the user clicked away from.
os.environ.setdefault("SDL_JOYSTICK_ALLOW_BACKGROUND_EVENTS", "1")

import pygame  # (after the environment above: SDL reads it at init)

log = logging.getLogger(__name__)

WAIT_MS = 4  # ~250 Hz: SDL's wait polls every 1 ms inside, so an event is seen within ~1 ms
START_TIMEOUT_S = 5.0


@dataclass(frozen=True)
class Layout:
    """Raw SDL indices of the roles; -1 means the role has no button."""

    steering_axis: int
    throttle_axis: int
    estop: int
    arm: int
    auto: int
    record: int
    lap: int
    clear: int


_XINPUT = Layout(steering_axis=0, throttle_axis=4, estop=1, arm=7, auto=3, record=2, lap=5, clear=6)
PRESETS: dict[str, Layout] = {
    "xbox": _XINPUT,
    "ps4": Layout(
        steering_axis=0, throttle_axis=4, estop=1, arm=9, auto=2, record=3, lap=5, clear=8
    ),
    "f710": _XINPUT,  # XInput mode is the xpad driver, the same layout as an Xbox 360 pad
    "custom": Layout(-1, -1, -1, -1, -1, -1, -1, -1),
}
_CONFIG_FIELD = {
    "steering_axis": "steering_axis",
    "throttle_axis": "throttle_axis",
    "estop": "estop_button",
    "arm": "arm_button",
    "auto": "auto_button",
    "record": "record_button",
    "lap": "lap_button",
    "clear": "clear_button",
}
_REQUIRED = ("steering_axis", "throttle_axis", "estop", "arm", "clear")
# Buttons that become edges for the next poll (the e-stop's edge is set on its fast path).
_EDGES = {"arm": "arm", "auto": "toggle_auto", "record": "toggle_record", "lap": "lap",
          "clear": "clear"}  # fmt: skip


# What each raw button index is labelled on the pad, for the hints that name a button ("press
# Start to arm"); the table in the docstring. `custom` has none: its buttons are "button N".
_XINPUT_NAMES = {0: "A", 1: "B", 2: "X", 3: "Y", 4: "LB", 5: "RB", 6: "Back", 7: "Start",
                 8: "Guide", 9: "L3", 10: "R3"}  # fmt: skip
BUTTON_NAMES: dict[str, dict[int, str]] = {
    "xbox": _XINPUT_NAMES,
    "f710": _XINPUT_NAMES,
    "ps4": {0: "cross", 1: "circle", 2: "triangle", 3: "square", 4: "L1", 5: "R1", 6: "L2",
            7: "R2", 8: "Share", 9: "Options", 10: "PS", 11: "L3", 12: "R3"},
}  # fmt: skip


def button_names(preset: str, layout: Layout) -> dict[str, str]:
    """Role -> the label of its button on this pad (overrides included), roles with a button."""
    names = BUTTON_NAMES.get(preset, {})
    return {
        role: names.get(index, f"button {index}")
        for role in ("arm", "auto", "clear", "estop", "record", "lap")
        if (index := getattr(layout, role)) >= 0
    }


def layout_for(config: JoystickConfig) -> Layout:
    """The preset's layout with every config field >= 0 overriding it."""
    if config.preset not in PRESETS:
        raise UserError(f"config joystick.preset: unknown preset {config.preset!r}")
    overrides = {}
    for f in fields(Layout):
        value = getattr(config, _CONFIG_FIELD[f.name])
        if value >= 0:
            overrides[f.name] = value
    layout = replace(PRESETS[config.preset], **overrides)
    for name in _REQUIRED:
        if getattr(layout, name) < 0:
            raise UserError(f"config joystick.{_CONFIG_FIELD[name]}: must be set for this preset")
    if layout.steering_axis == layout.throttle_axis:
        raise UserError("config joystick.throttle_axis: must differ from steering_axis")
    return layout


class PygameJoystick:
    """A pad read by a pygame reader thread; implements carrt.interfaces.Joystick."""

    def __init__(self, config: JoystickConfig) -> None:
        self.config = config
        self.layout = layout_for(config)
        self.controls = button_names(config.preset, self.layout)  # for the loop's hints
        self._axes = (self.layout.steering_axis, self.layout.throttle_axis)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._thread: threading.Thread | None = None
        self._start_error: BaseException | None = None
        self._on_estop: Callable[[], None] | None = None
        self._connected = False
        self._device: pygame.joystick.JoystickType | None = None
        self._instance_id: int | None = None  # None: accept events from any instance
        self._pumps_since_open = 0
        self._raw = dict.fromkeys(self._axes, 0.0)
        self._seen_neutral: set[int] = set()
        self._edges: dict[str, bool] = {}
        self._events_handled = 0
        self.name = ""  # the pad's name once opened ('' when connected on events alone)
        self.problem = ""  # a mapping the opened pad cannot satisfy, for `carrt check`

    # ------------------------------------------------------------------ the protocol
    def start(self, on_estop: Callable[[], None] | None) -> None:
        """Start the reader; returns once pygame is initialised (raises if it cannot be)."""
        if self._thread is not None:
            raise RuntimeError("joystick already started")
        self._on_estop = on_estop
        self._stop.clear()
        self._ready.clear()
        self._thread = threading.Thread(target=self._run, name="joystick-reader", daemon=True)
        self._thread.start()
        if not self._ready.wait(START_TIMEOUT_S):
            raise UserError("joystick: pygame did not initialise within 5 s")
        if self._start_error is not None:
            self._thread.join(timeout=1.0)
            self._thread = None
            raise UserError(f"joystick: cannot initialise pygame: {self._start_error}")

    def stop(self) -> None:
        """End the reader; it closes the pad and quits pygame's joystick and display itself."""
        thread, self._thread = self._thread, None
        if thread is None:
            return
        self._stop.set()
        thread.join(timeout=2.0)

    def poll(self) -> JoystickState:
        with self._lock:
            connected = self._connected
            steering = self._shape(self._raw[self.layout.steering_axis], False)
            throttle = self._shape(self._raw[self.layout.throttle_axis], True)
            neutral = connected and self._seen_neutral.issuperset(self._axes)
            edges, self._edges = self._edges, {}
        return JoystickState(
            connected=connected,
            steering=steering if connected else 0.0,
            throttle=throttle * self.config.max_throttle if connected else 0.0,
            neutral_since_connect=neutral,
            events=JoystickEvents(**edges),
        )

    @property
    def connected(self) -> bool:
        return self._connected

    @property
    def events_handled(self) -> int:
        """Events taken off pygame's queue so far (lets tests wait for the reader)."""
        return self._events_handled

    # ------------------------------------------------------------------ shaping
    def _shape(self, raw: float, throttle: bool) -> float:
        value = min(max(raw, -1.0), 1.0)
        if abs(value) <= self.config.deadzone:
            return 0.0
        invert = self.config.invert_throttle if throttle else self.config.invert_steering
        return -value if invert else value

    # ------------------------------------------------------------------ reader thread
    def _run(self) -> None:
        try:
            _init_pygame()
        except Exception as exc:  # reported to start()'s caller
            self._start_error = exc
            self._ready.set()
            return
        self._ready.set()
        try:
            while not self._stop.is_set():
                event = pygame.event.wait(WAIT_MS)  # pumps SDL (and the pad) on the way
                if self._device is not None:
                    self._pumps_since_open += 1
                if event.type != pygame.NOEVENT:
                    self._handle(event)
                    for event in pygame.event.get():
                        self._handle(event)
                self._read_device()
        except Exception:
            log.exception("joystick reader failed")
        finally:
            if not self._stop.is_set():  # the reader died: nobody is holding the dead-man
                with self._lock:
                    self._disconnect()
                self._call_estop()
            self._close_device()
            pygame.joystick.quit()
            pygame.display.quit()

    def _handle(self, event: pygame.event.Event) -> None:
        self._events_handled += 1
        kind = event.type
        if kind == pygame.JOYBUTTONDOWN:
            button = getattr(event, "button", -1)
            if button == self.layout.estop:  # from any pad, connected or not: fire first
                self._call_estop()
                with self._lock:
                    self._edges["estop"] = True
            if self._ours(event):
                with self._lock:
                    for role, edge in _EDGES.items():
                        if getattr(self.layout, role) == button:
                            self._edges[edge] = True
        elif kind == pygame.JOYAXISMOTION:
            if self._ours(event):
                self._observe(getattr(event, "axis", -1), float(getattr(event, "value", 0.0)))
        elif kind == pygame.JOYDEVICEREMOVED:
            with self._lock:
                ours = self._connected and self._instance_id in (
                    None,
                    getattr(event, "instance_id", None),
                )
                if ours:
                    self._disconnect()
            if ours:
                self._call_estop()
                self._close_device()
        elif kind == pygame.JOYDEVICEADDED:
            if getattr(event, "device_index", -1) == self.config.device_index:
                self._open(self.config.device_index)
        elif kind == pygame.QUIT:
            with self._lock:
                self._edges["quit"] = True

    def _ours(self, event: pygame.event.Event) -> bool:
        return self._connected and self._instance_id in (None, getattr(event, "instance_id", None))

    def _call_estop(self) -> None:
        """The fast path: the pad's e-stop goes to the wire from this thread, now."""
        callback = self._on_estop
        if callback is not None:
            try:
                callback()
            except Exception:  # the reader must survive to report the next e-stop
                log.exception("joystick on_estop callback failed")

    def _open(self, device_index: int) -> None:
        """A (re)connect: open the device if SDL has one, and demand neutral sticks again."""
        self._close_device()
        device = None
        try:
            device = pygame.joystick.Joystick(device_index)
            device.init()
            instance_id = device.get_instance_id()
        except pygame.error:  # synthetic events without a device: connected on events alone
            device, instance_id = None, None
        with self._lock:
            self._device = device
            self._instance_id = instance_id
            self._pumps_since_open = 0
            self._connected = True
            self._raw = dict.fromkeys(self._axes, 0.0)
            self._seen_neutral = set()
        self.name = device.get_name() if device is not None else ""
        self.problem = ""
        if device is not None:
            missing = [a for a in self._axes if a >= device.get_numaxes()]
            if missing:
                self.problem = (
                    f"pad {self.name!r} has {device.get_numaxes()} axes; mapped axis "
                    f"{missing[0]} does not exist (check joystick.preset)"
                )
            log.info("joystick connected: %s", self.name)

    def _disconnect(self) -> None:  # lock held
        self._connected = False
        self._raw = dict.fromkeys(self._axes, 0.0)
        self._seen_neutral = set()

    def _close_device(self) -> None:
        device, self._device, self._instance_id = self._device, None, None
        if device is not None:
            with contextlib.suppress(pygame.error):
                device.quit()

    def _observe(self, axis: int, value: float) -> None:
        if axis not in self._raw:
            return
        with self._lock:
            self._raw[axis] = value
            if abs(value) <= self.config.deadzone:
                self._seen_neutral.add(axis)

    def _read_device(self) -> None:
        """Observe the opened pad's axes directly: a stuck axis sends no events at all."""
        device = self._device
        if device is None or self._pumps_since_open < 1 or self.problem:
            return
        try:
            values = [(axis, device.get_axis(axis)) for axis in self._axes]
        except pygame.error:
            return
        for axis, value in values:
            self._observe(axis, value)


def _init_pygame() -> None:
    """Video first (SDL's event queue lives there), then joysticks; headless falls back to dummy.

    A Jetson without a display has no usable video driver and SDL never picks its dummy driver
    by itself; the dummy driver still pumps joystick events, which is all this reader needs.
    """
    try:
        pygame.display.init()
    except pygame.error:
        if os.environ.get("SDL_VIDEODRIVER"):
            raise
        os.environ["SDL_VIDEODRIVER"] = "dummy"
        pygame.display.init()
    pygame.joystick.init()
