"""Keyboard teleop in a pygame window: the pad for a laptop with none, behind the same interface.

The window shows what the policy would see (the 96×96 camera, enlarged), a top-down map of the
arena with the car, and below them what the loop did on its last tick (mode and why, speed,
recording, the keys' and the executed steering and throttle as bars) and the keys. Keys are
turned into stick values with a ramp, as a thumb moves a stick, so the recorded human actions
are not just -1/0/+1 steps. Space is the e-stop and goes to the wire from the window's thread at
once, like the pad's e-stop button.

After a collision the car is lifted back onto the track at once (as the simulator's stand-in
person does; the e-stop stays latched until C), so clear, arm and drive on works; Backspace puts
a car that is not driving back on the track at any time (stuck against the fence, turned round).

  arrows / WASD  steer and throttle      Enter  arm / disarm     Tab  manual <-> auto
  Space          e-stop                  C      clear e-stop     R    record on/off
  Backspace      car back on the track   L      lap marker       F12  screenshot
  Esc / Q        quit
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from carrt.errors import UserError
from carrt.interfaces import JoystickEvents, JoystickState, LiveStatus, Mode

os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

RAMP_PER_S = 4.0  # stick units per second while a key is held
CAMERA_PX = 96 * 4
PANEL_PX = 190  # status, bars and keys below the camera and the map
WINDOW = (CAMERA_PX + 380, CAMERA_PX + PANEL_PX)
FPS = 30
NOTE_S = 4.0  # how long a message stays in the window
MODE_COLOURS = {
    Mode.MANUAL: (90, 200, 120),
    Mode.AUTO: (90, 160, 255),
    Mode.ESTOP: (240, 70, 70),
}
LEGEND = (
    "arrows/WASD drive   Enter arm/disarm   Tab manual/auto   Space E-STOP   C clear",
    "Backspace car back on track   R record   L lap   F12 screenshot   Esc quit",
)
# role -> key, for the loop's hints ("press Enter to arm"); the keys _handle maps
CONTROLS = {"arm": "Enter", "auto": "Tab", "clear": "C", "estop": "Space"}


def require_display() -> None:
    """Refuse to open an invisible window: without a display SDL falls back to an offscreen
    driver, and the person would drive a car they cannot see (SDL_VIDEODRIVER set by hand,
    e.g. `dummy` in tests, is taken as meant)."""
    if os.environ.get("SDL_VIDEODRIVER"):
        return
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise UserError(
            "the keyboard window needs a display (DISPLAY is not set): run it on a desktop, "
            "drive with a pad (--pad), or let the scripted expert drive (--expert auto)"
        )


class KeyboardPad:
    controls = CONTROLS

    def __init__(
        self,
        plant: Any,
        camera: Any,
        renderer_map: Callable[[Any], Any] | None = None,
        max_throttle: float = 1.0,
        screenshot: str = "carrt-window.png",
    ) -> None:
        self.plant = plant
        self.camera = camera
        self.renderer_map = renderer_map
        self.max_throttle = max_throttle
        self.screenshot = Path(screenshot)
        self._lock = threading.Lock()
        self._steering = 0.0
        self._throttle = 0.0
        self._held: set[str] = set()
        self._edges: dict[str, bool] = {}
        self._reset_wanted = False
        self._note = ("", 0.0)  # a message for the person (a refused reset, a screenshot), until
        self._on_estop: Callable[[], None] = lambda: None
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._thread: threading.Thread | None = None
        self.status_source: Callable[[], LiveStatus] = LiveStatus  # the session: the loop's

    def start(self, on_estop: Callable[[], None]) -> None:
        self._on_estop = on_estop
        self._thread = threading.Thread(target=self._run, name="keyboard-pad", daemon=True)
        self._thread.start()
        self._ready.wait(5.0)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def poll(self) -> JoystickState:
        """On the loop's thread: the keys as sticks, and the person's hands on the car."""
        self._lift_back_if_needed()
        with self._lock:
            edges, self._edges = self._edges, {}
            return JoystickState(
                connected=True,
                steering=self._steering,
                throttle=self._throttle * self.max_throttle,
                neutral_since_connect=True,
                events=JoystickEvents(**edges),
            )

    def _lift_back_if_needed(self) -> None:
        mode = self.status_source().mode
        with self._lock:
            wanted, self._reset_wanted = self._reset_wanted, False
        with self.plant.lock:
            crashed = self.plant.world.collided
        driving = mode in (Mode.MANUAL, Mode.AUTO)
        if wanted and driving:
            self._say("disarm (Enter) or e-stop (Space) before moving the car")
            return
        if (crashed and not driving) or wanted:  # a crash: once the loop has e-stopped
            with self.plant.lock:
                self.plant.reset()  # on the line, heading along the track, clear of obstacles
            self._say("car back on the track" + (": C clears the e-stop" if crashed else ""))

    def _say(self, text: str) -> None:
        with self._lock:
            self._note = (text, time.monotonic() + NOTE_S)

    # ------------------------------------------------------------------ window thread
    def _run(self) -> None:
        import pygame

        pygame.display.init()
        pygame.font.init()
        screen = pygame.display.set_mode(WINDOW)
        pygame.display.set_caption("carrt sim — arrows drive, Enter arms, Space e-stops")
        fonts = (pygame.font.Font(None, 30), pygame.font.Font(None, 21))
        clock = pygame.time.Clock()
        self._ready.set()
        try:
            while not self._stop.is_set():
                for event in pygame.event.get():
                    self._handle(pygame, event, screen)
                self._ramp(1.0 / FPS)
                self._draw(pygame, screen, fonts)
                clock.tick(FPS)
        finally:
            pygame.display.quit()

    def _handle(self, pygame: Any, event: Any, screen: Any) -> None:
        keys = {
            pygame.K_LEFT: "left", pygame.K_a: "left", pygame.K_RIGHT: "right",
            pygame.K_d: "right", pygame.K_UP: "up", pygame.K_w: "up",
            pygame.K_DOWN: "down", pygame.K_s: "down",
        }  # fmt: skip
        presses = {
            pygame.K_RETURN: "arm", pygame.K_TAB: "toggle_auto", pygame.K_c: "clear",
            pygame.K_r: "toggle_record", pygame.K_l: "lap", pygame.K_ESCAPE: "quit",
            pygame.K_q: "quit",
        }  # fmt: skip
        if event.type == pygame.QUIT:
            self._edge("quit")
        elif event.type == pygame.KEYDOWN and event.key == pygame.K_SPACE:
            self._edge("estop")
            self._on_estop()  # at once, from this thread
        elif event.type == pygame.KEYDOWN and event.key == pygame.K_BACKSPACE:
            with self._lock:
                self._reset_wanted = True
        elif event.type == pygame.KEYDOWN and event.key == pygame.K_F12:
            pygame.image.save(screen, str(self.screenshot))
            self._say(f"saved {self.screenshot}")
        elif event.type == pygame.KEYDOWN and event.key in presses:
            self._edge(presses[event.key])
        elif event.type in (pygame.KEYDOWN, pygame.KEYUP) and event.key in keys:
            with self._lock:
                if event.type == pygame.KEYDOWN:
                    self._held.add(keys[event.key])
                else:
                    self._held.discard(keys[event.key])

    def _edge(self, name: str) -> None:
        with self._lock:
            self._edges[name] = True

    def _ramp(self, dt: float) -> None:
        with self._lock:
            # the protocol's sign: Left is −1 (steer_left_us), Right +1
            steer_target = ("right" in self._held) - ("left" in self._held)
            throttle_target = ("up" in self._held) - ("down" in self._held)
            self._steering = _towards(self._steering, steer_target, RAMP_PER_S * dt)
            self._throttle = _towards(self._throttle, throttle_target, RAMP_PER_S * dt)

    # ------------------------------------------------------------------ drawing
    def _draw(self, pygame: Any, screen: Any, fonts: tuple[Any, Any]) -> None:
        big, small = fonts
        screen.fill((20, 20, 24))
        frame = self.camera.latest()
        if frame is not None:
            surface = pygame.surfarray.make_surface(frame.image.swapaxes(0, 1))
            screen.blit(pygame.transform.scale(surface, (CAMERA_PX, CAMERA_PX)), (0, 0))
        if self.renderer_map is not None:
            top = self.renderer_map(self.plant)
            surface = pygame.surfarray.make_surface(top.swapaxes(0, 1))
            w = WINDOW[0] - CAMERA_PX - 10
            h = int(top.shape[0] * w / top.shape[1])
            screen.blit(pygame.transform.scale(surface, (w, h)), (CAMERA_PX + 5, 5))
        live = self.status_source()
        with self._lock:
            note, until = self._note
        note = note if time.monotonic() < until else ""
        y = CAMERA_PX + 8
        mode = live.mode.name + (f": {live.why}" if live.why else "")
        screen.blit(big.render(mode, True, MODE_COLOURS.get(live.mode, (200, 200, 200))), (8, y))
        rec = f"REC episode {live.episodes}" if live.recording else "not recording"
        line = (f"{live.speed_mps:4.2f} m/s   {rec}   collisions {live.collisions}   "
                f"laps {live.laps}")  # fmt: skip
        screen.blit(small.render(line, True, (230, 230, 230)), (8, y + 30))
        if note:
            screen.blit(small.render(note, True, (250, 210, 90)), (8, y + 50))
        bars = (("steering", 0, -1.0), ("throttle", 1, -1.0))
        for row, (name, i, lo) in enumerate(bars):
            top_y = y + 74 + 26 * row
            screen.blit(small.render(name, True, (230, 230, 230)), (8, top_y))
            _bar(pygame, screen, small, (90, top_y), "keys", live.human[i], lo)
            _bar(pygame, screen, small, (90 + 330, top_y), "executed", live.executed[i], lo)
        for k, text in enumerate(LEGEND):
            screen.blit(small.render(text, True, (170, 170, 180)), (8, y + 130 + 20 * k))
        pygame.display.flip()


def _bar(pygame: Any, screen: Any, font: Any, at: tuple[int, int], label: str, value: float,
         lo: float) -> None:  # fmt: skip
    """A labelled bar from lo to +1 with zero marked: left of zero is left / braking."""
    x, y = at
    screen.blit(font.render(label, True, (170, 170, 180)), (x, y))
    x0, width, height = x + 70, 180, 14
    pygame.draw.rect(screen, (60, 60, 70), (x0, y, width, height), 1)
    zero = x0 + int(width * (0 - lo) / (1 - lo))
    end = x0 + int(width * (min(max(value, lo), 1.0) - lo) / (1 - lo))
    left, right = sorted((zero, end))
    pygame.draw.rect(screen, (120, 190, 250), (left, y + 2, max(right - left, 1), height - 4))
    pygame.draw.line(screen, (230, 230, 230), (zero, y - 2), (zero, y + height + 2))
    screen.blit(font.render(f"{value:+.2f}", True, (230, 230, 230)), (x0 + width + 6, y))


def _towards(value: float, target: float, step: float) -> float:
    if value < target:
        return min(target, value + step)
    return max(target, value - step)
