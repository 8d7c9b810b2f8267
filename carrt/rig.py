"""What the control loop drives: the real car's parts, or the simulator's, as one `Rig`.

The session builds a rig, hands its parts to the loop and calls `finish` at the end; it does not
know which kind it has. Which one is opened is a row of the table in carrt/rig_table.py. The car's
factory is here; the simulator's is `carrt/sim/rig.py`, which imports this module (and nothing
imports back), so the two never form an import circle.
"""

from __future__ import annotations

import contextlib
import importlib
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from carrt.clock import WallClock
from carrt.errors import UserError
from carrt.interfaces import Board, Camera, Clock, Joystick
from firmware_bridge.link import BoardLink
from firmware_bridge.timing import FIRST_FRAME_TIMEOUT_S


@dataclass
class Rig:
    """What the loop drives: the real car, or the simulator standing in for it."""

    clock: Clock
    camera: Camera
    link: Board
    joystick: Joystick
    describe: str
    collisions: Callable[[], bool] | None = None  # the simulator reports crashes
    follows_mode: list = field(default_factory=list)  # things that need the loop's mode
    watches_loop: list = field(default_factory=list)  # shown the loop's LiveStatus (a window)
    # at the end, with the loop summary and the report's stream (None: say nothing); returns
    # the rig's own results (the simulator's metrics), which run_session hands back
    finish: Callable[[Any, Any], Any] | None = None
    # the simulator's own clock, faster than real time: the loop may wait for the disk there
    simulated_time: bool = False


@dataclass(frozen=True)
class RigKind:
    """One row: a rig's name, what it is, and how to open it."""

    name: str
    summary: str  # for --help and the start-up line
    factory: str  # "module:function"(stack, drive, config, *, driving, kind) -> Rig
    board: str | None = None  # simulator rigs: "module:Class" of the board behind the pty
    simulator: bool = False  # the simulator's flags (--layout, --realtime, ...) apply
    always_realtime: bool = False  # the board runs in wall-clock time only (an emulator)


def load(reference: str) -> Any:
    """Import a "module:attribute" reference now and return the attribute."""
    module, _, attribute = reference.partition(":")
    return getattr(importlib.import_module(module), attribute)


def open_car_rig(
    stack: contextlib.ExitStack, drive: Any, config: Any, *, driving: bool, kind: Any
) -> Rig:
    """The real car: OpenCV camera, serial board, pygame pad; each checked before the next.
    (A factory of carrt/rig_table.py: what `drive` says of the car, its port and camera, is already
    in the car config `config`.)"""
    from carrt.camera import OpenCVCamera
    from carrt.joystick import PygameJoystick

    camera = OpenCVCamera(config.camera, clock=WallClock())
    camera.start()
    stack.callback(camera.stop)
    _wait_first_frame(camera, config.camera.source)
    link = BoardLink(
        config.serial.port,
        config.serial.baud,
        handshake_timeout_s=config.serial.handshake_timeout_s,
    )
    link.open()
    stack.callback(link.close)
    clock = WallClock()
    return Rig(
        clock=clock,
        camera=camera,
        link=link,
        joystick=person_controls(
            config, link, clock, lambda: PygameJoystick(config.joystick), driving=driving
        ),
        describe=f"board on {config.serial.port}, camera {config.camera.source}, "
        f"controls: {config.receiver.controls}",
    )


def person_controls(
    config: Any,
    link: Any,
    clock: Clock,
    pad: Callable[[], Any],
    *,
    driving: bool,
    radio: Any = None,
) -> Any:
    """What the person holds, by `receiver.controls`: the pad, the RC receiver (read back from
    the board; `radio` is the simulator's transmitter), or both. `driving`: a policy may drive
    (letting the transmitter's sticks go gives the wheels back to it)."""
    from carrt.receiver import PadAndReceiver, ReceiverControls

    if config.receiver.controls == "pad":
        return pad()
    receiver = ReceiverControls(link, config.receiver, clock.now, radio=radio, allow_auto=driving)
    if config.receiver.controls == "receiver" or radio is not None:
        return receiver
    return PadAndReceiver(pad(), receiver)


def _wait_first_frame(camera: Any, source: str) -> None:
    deadline = time.monotonic() + FIRST_FRAME_TIMEOUT_S
    while camera.latest() is None:
        if camera.lost or time.monotonic() > deadline:
            raise UserError(f"camera {source}: no frame within {FIRST_FRAME_TIMEOUT_S:.0f} s")
        time.sleep(0.01)
