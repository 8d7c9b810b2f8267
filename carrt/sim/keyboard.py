"""Keyboard teleop in a pygame window: the pad for a laptop with none, behind the same interface.

The window shows what the policy would see (the 96×96 camera, enlarged), a top-down map of the
arena with the car, and the commands. Keys are turned into stick values with a ramp, as a
thumb moves a stick, so the recorded human actions are not just -1/0/+1 steps. Space is the
e-stop and goes to the wire from the window's thread at once, like the pad's e-stop button.

  arrows / WASD  steer and throttle      Enter  arm / disarm     Tab  manual <-> auto
  Space          e-stop                  C      clear e-stop     R    record on/off
  L              lap marker              Esc/Q  quit
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from typing import Any

from carrt.interfaces import JoystickEvents, JoystickState

os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")

RAMP_PER_S = 4.0  # stick units per second while a key is held
WINDOW = (96 * 4 + 300, 96 * 4)
FPS = 30


class KeyboardPad:
    def __init__(self, plant: Any, camera: Any, renderer_map: Callable[[Any], Any] | None = None,
                 max_throttle: float = 1.0) -> None:  # fmt: skip
        self.plant = plant
        self.camera = camera
        self.renderer_map = renderer_map
        self.max_throttle = max_throttle
        self._lock = threading.Lock()
        self._steering = 0.0
        self._throttle = 0.0
        self._held: set[str] = set()
        self._edges: dict[str, bool] = {}
        self._on_estop: Callable[[], None] = lambda: None
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._thread: threading.Thread | None = None
        self.status = ""  # a line from the session (mode, speed) drawn in the window

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
        with self._lock:
            edges, self._edges = self._edges, {}
            return JoystickState(
                connected=True,
                steering=self._steering,
                throttle=self._throttle * self.max_throttle,
                neutral_since_connect=True,
                events=JoystickEvents(**edges),
            )

    # ------------------------------------------------------------------ window thread
    def _run(self) -> None:
        import pygame

        pygame.display.init()
        pygame.font.init()
        screen = pygame.display.set_mode(WINDOW)
        pygame.display.set_caption("carrt sim — arrows drive, Enter arms, Space e-stops")
        font = pygame.font.Font(None, 22)
        clock = pygame.time.Clock()
        self._ready.set()
        try:
            while not self._stop.is_set():
                for event in pygame.event.get():
                    self._handle(pygame, event)
                self._ramp(1.0 / FPS)
                self._draw(pygame, screen, font)
                clock.tick(FPS)
        finally:
            pygame.display.quit()

    def _handle(self, pygame: Any, event: Any) -> None:
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

    def _draw(self, pygame: Any, screen: Any, font: Any) -> None:
        screen.fill((20, 20, 24))
        frame = self.camera.latest()
        if frame is not None:
            surface = pygame.surfarray.make_surface(frame.image.swapaxes(0, 1))
            screen.blit(pygame.transform.scale(surface, (96 * 4, 96 * 4)), (0, 0))
        if self.renderer_map is not None:
            top = self.renderer_map(self.plant)
            surface = pygame.surfarray.make_surface(top.swapaxes(0, 1))
            w = WINDOW[0] - 96 * 4 - 10
            h = int(top.shape[0] * w / top.shape[1])
            screen.blit(pygame.transform.scale(surface, (w, h)), (96 * 4 + 5, 5))
        with self._lock:
            text = f"steer {self._steering:+.2f}  throttle {self._throttle:+.2f}"
        for i, line in enumerate((text, self.status, "Enter arm  Tab auto  Space e-stop  C clear")):
            screen.blit(
                font.render(line, True, (230, 230, 230)), (96 * 4 + 8, WINDOW[1] - 70 + 22 * i)
            )
        pygame.display.flip()


def _towards(value: float, target: float, step: float) -> float:
    if value < target:
        return min(target, value + step)
    return max(target, value - step)
