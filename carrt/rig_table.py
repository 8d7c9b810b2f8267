"""The rigs `carrt teleop` and `carrt drive` can run on, as one table of named factories.

As LeRobot registers its robots by name, each row names a rig and the function that opens it
("module:function", imported only when that rig is chosen, so a real car never loads the
simulator, and the simulator never loads OpenCV's camera). Every factory takes the same
arguments (the drive's `carrt.session.DriveConfig`, the car config) and returns a
`carrt.rig.Rig`; the session does not know which one it got. A
simulated board (a class with `Board(plant).start()`, `.port`, `.stop()` and a `LABEL`, that
speaks the protocol on a pty: firmware_bridge/virtual.py, firmware_bridge/avr_board.py) plugs
into the simulator's factory through the row's `board`. So a new board is one file (its class)
and one row here.

On the command line: `--rig NAME`; `--sim` is short for `--rig sim`, `--sim --board avr` for
`--rig avr`.
"""

from __future__ import annotations

import contextlib
from typing import Any

from carrt.errors import UserError
from carrt.rig import RigKind, load

RIGS: dict[str, RigKind] = {
    kind.name: kind
    for kind in (
        RigKind(
            "car",
            "the real car: OpenCV camera, board on a serial port, game pad",
            "carrt.rig:open_car_rig",
        ),
        RigKind(
            "sim",
            "the simulator, with the C core built for this machine as its board (virtual board "
            "on a pty in real time, in-process on the simulated clock)",
            "carrt.sim.rig:open_sim_rig",
            board="firmware_bridge.virtual:VirtualBoard",
            simulator=True,
        ),
        RigKind(
            "avr",
            "the simulator, with the firmware binary on an emulated ATmega328P as its board "
            "(real time; needs gcc-avr arduino-core-avr simavr libsimavr-dev)",
            "carrt.sim.rig:open_sim_rig",
            board="firmware_bridge.avr_board:AvrBoard",
            simulator=True,
            always_realtime=True,
        ),
    )
}
BOARD_RIGS = {"virtual": "sim", "avr": "avr"}  # --board NAME, the older spelling


def lookup(name: str) -> RigKind:
    """The row called `name`; any other name is a one-line UserError listing the names."""
    kind = RIGS.get(name)
    if kind is None:
        raise UserError(f"--rig: unknown rig {name!r}; the rigs are {', '.join(RIGS)}")
    return kind


def chosen(rig: str | None, *, sim: bool = False, board: str | None = None) -> RigKind:
    """The rig the command line asks for: --rig, or --sim [--board], or the real car."""
    if rig is not None:
        if sim or board is not None:
            raise UserError("--rig replaces --sim and --board: give one or the other")
        return lookup(rig)
    if board is not None:
        return lookup(BOARD_RIGS[board])
    return lookup("sim" if sim else "car")


def open_rig(stack: contextlib.ExitStack, drive: Any, config: Any, *, driving: bool) -> Any:
    """Open the rig `drive` (a DriveConfig) names, its parts closed by `stack`, with the car
    config `config`; return its `Rig`."""
    kind = lookup(drive.rig)
    return load(kind.factory)(stack, drive, config, driving=driving, kind=kind)
