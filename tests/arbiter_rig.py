"""An arbiter on a fake 10 Hz clock, and joystick states, for the arbitration tests.

The rules for arming, AUTO and the sticks (test_arbitration.py) and the e-stop latch, the
board's states and the e-stop fast path (test_arbitration_estop.py) all step the same `Rig`.
"""

from __future__ import annotations

import threading

from carrt.arbitration import Arbiter, ArbiterInputs, Decision
from carrt.config import CameraConfig, EncoderConfig
from carrt.interfaces import JoystickEvents, JoystickState, Mode
from carrt.reasons import Why
from firmware_bridge.messages import State

CAMERA = CameraConfig(max_age_s=0.15)
ENCODER = EncoderConfig(max_age_s=0.1)


def why(reason: str) -> Why | None:
    """Which reason the arbiter gave (carrt/reasons.py), None for '' or a caller's own words."""
    return getattr(reason, "why", None)


def pad(steering=0.0, throttle=0.0, *, connected=True, neutral=True, **edges) -> JoystickState:
    return JoystickState(
        connected=connected,
        steering=steering,
        throttle=throttle,
        neutral_since_connect=neutral,
        events=JoystickEvents(**edges),
    )


class Rig:
    """An arbiter, a clock, and the last inputs; each call to `tick` is one 10 Hz step."""

    def __init__(self, *, allow_auto=True, deadzone=0.0):
        self.estops: list[str] = []
        self.arbiter = Arbiter(
            allow_auto=allow_auto,
            camera=CAMERA,
            encoder=ENCODER,
            deadzone=deadzone,
            on_estop=lambda: self.estops.append(threading.current_thread().name),
        )
        self.now = 100.0
        self.board = State.DISARMED

    def tick(self, js: JoystickState | None = None, **fields) -> Decision:
        self.now += 0.1
        fields.setdefault("board_state", self.board)
        inputs = ArbiterInputs(
            now=self.now,
            joystick=js if js is not None else pad(),
            frame_age_s=fields.pop("frame_age_s", 0.03),
            camera_lost=fields.pop("camera_lost", False),
            telemetry_age_s=fields.pop("telemetry_age_s", 0.01),
            **fields,
        )
        return self.arbiter.step(inputs)

    def arm(self) -> Decision:
        decision = self.tick(pad(arm=True))
        assert decision.mode == Mode.MANUAL and decision.arm_request, decision
        self.board = State.ARMED
        return decision

    def auto(self) -> Decision:
        self.arm()
        decision = self.tick(pad(toggle_auto=True), plan_action=(0.1, 0.4))
        assert decision.mode == Mode.AUTO, decision
        return decision
