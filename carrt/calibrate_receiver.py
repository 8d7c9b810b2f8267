"""`carrt calibrate --receiver`: learn the RC transmitter's endpoints, centres and e-stop switch.

The receiver is wired to the board, which measures its three channels and reports them in every
TELEMETRY; so this asks the person to put each stick and the switch in a position, reads the
board's widths there (the median of a short window, with the receiver's signal valid throughout)
and writes them to the car's `[receiver]` section (comments kept, checked to load before the
file is replaced) and, with the receiver fields the board rules with, to its EEPROM. Nothing
moves: the board stays disarmed throughout.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TextIO

from carrt import config as car_config
from carrt.calibration_io import commit, disarm_and_wait, plan_edit
from carrt.errors import UserError
from firmware_bridge import messages as m

SAMPLE_S = 0.3
SWITCH_MARGIN_US = 200  # e-stop and run positions at least this far apart


@dataclass(frozen=True)
class Position:
    name: str
    prompt: str


POSITIONS = (
    Position("centre", "both sticks centred (throttle at neutral), the switch at run"),
    Position("left", "the steering stick held full left"),
    Position("right", "the steering stick held full right"),
    Position("forward", "the throttle held full forward"),
    Position("reverse", "the throttle held full brake/reverse"),
    Position("estop", "the switch in the position that shall stop the car"),
    Position("run", "the switch back at run"),
)


def read_receiver(link, seconds: float = SAMPLE_S) -> tuple[int, int, int]:
    """Median steering, throttle and switch widths over `seconds` of TELEMETRY; UserError when
    the receiver's signal is missing at any moment of it."""
    samples = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        sample = link.telemetry
        tel = sample.telemetry if sample is not None else None
        if tel is None or not tel.flags & m.TelemetryFlags.RC_SIGNAL:
            raise UserError(
                "no signal from the RC receiver: is the transmitter on, the receiver bound, and "
                "its channels 1-3 wired to D4, D5, D6 of the board?"
            )
        samples.append((tel.rc_steer_us, tel.rc_throttle_us, tel.rc_switch_us))
        time.sleep(0.02)
    return tuple(round(statistics.median(column)) for column in zip(*samples, strict=True))


def derive(readings: dict[str, tuple[int, int, int]], deadzone_us: int) -> dict[str, int]:
    """The `[receiver]` keys from the positions' readings; UserError names what is wrong."""
    steer_c, throttle_c, _ = readings["centre"]
    values = {
        "steer_center_us": steer_c,
        "steer_left_us": readings["left"][0],
        "steer_right_us": readings["right"][0],
        "throttle_neutral_us": throttle_c,
        "throttle_forward_us": readings["forward"][1],
        "throttle_reverse_us": readings["reverse"][1],
    }
    for key, centre, channel in (
        ("steer_left_us", steer_c, "steering (channel 1, D4)"),
        ("steer_right_us", steer_c, "steering (channel 1, D4)"),
        ("throttle_forward_us", throttle_c, "throttle (channel 2, D5)"),
        ("throttle_reverse_us", throttle_c, "throttle (channel 2, D5)"),
    ):
        if abs(values[key] - centre) <= 2 * deadzone_us:
            raise UserError(
                f"calibrate --receiver: the {channel} barely moved for {key.removesuffix('_us')} "
                f"({values[key]} us against {centre} us at the centre): is that stick on that "
                "channel?"
            )
    if (values["steer_left_us"] > steer_c) == (values["steer_right_us"] > steer_c):
        raise UserError("calibrate --receiver: full left and full right are on the same side")
    estop, run = readings["estop"][2], readings["run"][2]
    if estop < run + SWITCH_MARGIN_US:
        raise UserError(
            f"calibrate --receiver: the switch reads {estop} us at e-stop and {run} us at run; "
            "the e-stop position must give the longer pulse: reverse channel 3 on the "
            "transmitter (or use its other position as e-stop)"
        )
    values["estop_us"] = (estop + run) // 2
    return values


def calibrate_receiver(
    link, config: car_config.CarConfig, stdin: TextIO, stdout: TextIO
) -> car_config.CarConfig | None:
    """Ask for each position and read it; the calibrated config, or None when the user quit."""
    readings: dict[str, tuple[int, int, int]] = {}
    for position in POSITIONS:
        print(f"  {position.prompt}, then Enter (q: quit) > ", end="", file=stdout, flush=True)
        line = stdin.readline()
        if line == "" or line.strip().lower() == "q":
            print("\ncalibration abandoned: nothing written", file=stdout)
            return None
        readings[position.name] = read_receiver(link)
        steer, throttle, switch = readings[position.name]
        print(f"    steering {steer} us, throttle {throttle} us, switch {switch} us", file=stdout)
    values = derive(readings, config.receiver.deadzone_us)
    result = replace(config, receiver=replace(config.receiver, **values))
    car_config.from_dict(result.to_dict())  # the combination must still be valid
    return result


def run(link, config: car_config.CarConfig, path: Path, stdin: TextIO, stdout: TextIO) -> int:
    print("calibrating the RC receiver through the board: the car does not move", file=stdout)
    result = calibrate_receiver(link, config, stdin, stdout)
    if result is None:
        return 1
    keys = [
        "steer_left_us", "steer_center_us", "steer_right_us", "throttle_reverse_us",
        "throttle_neutral_us", "throttle_forward_us", "estop_us",
    ]  # fmt: skip
    values = {k: getattr(result.receiver, k) for k in keys}
    edit = plan_edit(path, "receiver", values)  # checked before the board stores anything
    disarm_and_wait(link)
    ack = link.send_config(car_config.board_config(result, persist=True))
    if ack.result != m.ConfigResult.ACCEPTED or not ack.persisted:
        raise UserError("board did not store the calibration (is it armed, or has no EEPROM?)")
    commit(edit)
    summary = ", ".join(f"{k} {v}" for k, v in values.items())
    print(f"\nwrote {summary} to {path} and the board's EEPROM", file=stdout)
    if result.receiver.controls == "pad":
        print(
            f"the receiver is calibrated but not yet the person's controls: set "
            f'receiver.controls = "receiver" (or "both") in {path}',
            file=stdout,
        )
    return 0
