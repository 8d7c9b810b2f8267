"""`carrt calibrate`: find the servo and ESC pulses of this car, interactively, through the link.

(`--receiver` learns the RC transmitter's instead: carrt/calibrate_receiver.py.)

Each adjustment goes the only way the board allows: disarm, send the candidate CONFIG (it
refuses changes while armed), arm again with neutral throttle, and hold the command that shows
the value (straight ahead, full left, ...). A feeder thread keeps sending fresh decisions, so
the board's 300 ms freshness check stays satisfied while the user thinks. The result goes into
the car's TOML (only the [pwm] keys are touched, comments kept, the file checked to load
before it is replaced: carrt/calibration_io.py) and into the board's EEPROM.
"""

from __future__ import annotations

import argparse
import sys
import threading
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TextIO

from carrt import config as car_config
from carrt.calibration_io import commit, disarm_and_wait, plan_edit
from carrt.errors import UserError
from firmware_bridge import messages as m
from firmware_bridge.link import BoardLink, LinkError

SMALL_STEP_US = 10
LARGE_STEP_US = 50


@dataclass(frozen=True)
class CalibrationStep:
    key: str  # PwmConfig field
    steering: float  # command held while adjusting, so the user sees the pulse's effect
    throttle: float
    prompt: str


# Neutral and centre come first: a disarmed board already outputs them, so they need no
# arming, and the steps that do arm need a car that stands still (the board checks).
STEPS = (
    CalibrationStep("throttle_neutral_us", 0.0, 0.0, "car on a stand: wheels not creeping"),
    CalibrationStep("steer_center_us", 0.0, 0.0, "front wheels pointing straight ahead"),
    CalibrationStep("steer_left_us", -1.0, 0.0, "full left lock, servo not straining"),
    CalibrationStep("steer_right_us", 1.0, 0.0, "full right lock, servo not straining"),
)

HELP = "  + / - : ±10 us   ++ / -- : ±50 us   a number: that pulse   Enter: accept   q: quit"


class _Feeder:
    """Repeats the held command with fresh decisions at 20 Hz (the board wants them < 300 ms)."""

    def __init__(self, link: BoardLink) -> None:
        self.link = link
        self.command = (0.0, 0.0)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="calibrate-feeder", daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(0.05):
            self.link.set_command(*self.command)

    def __enter__(self) -> _Feeder:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.link.disarm()
        self.link.set_command(0.0, 0.0)


def _show(link: BoardLink, feeder: _Feeder, board: m.Config, step: CalibrationStep) -> str | None:
    """Apply a candidate config and hold the step's command; return an error text or None."""
    feeder.command = (0.0, 0.0)
    disarm_and_wait(link)
    ack = link.send_config(board)
    if ack.result != m.ConfigResult.ACCEPTED:
        return f"board refused it ({m.ConfigResult(ack.result).name.lower().replace('_', ' ')})"
    if (step.steering, step.throttle) == (0.0, 0.0):
        return None  # a disarmed board outputs centre and neutral by itself
    if link.board_state in (m.State.ESTOP, m.State.FAILSAFE):
        link.clear()
    try:
        link.wait_until_still()
    except LinkError as exc:
        raise UserError(
            f"the wheels keep turning at throttle_neutral_us={board.throttle_neutral_us}: "
            "calibrate the neutral first"
        ) from exc
    link.arm()
    feeder.command = (step.steering, step.throttle)
    return None


def _parse(answer: str, current: int) -> int | None:
    """New pulse for a typed answer; None means accept."""
    answer = answer.strip()
    moves = {"+": SMALL_STEP_US, "-": -SMALL_STEP_US, "++": LARGE_STEP_US, "--": -LARGE_STEP_US}
    if answer == "":
        return None
    if answer in moves:
        return current + moves[answer]
    if answer.isdigit():
        return int(answer)
    raise ValueError(answer)


def calibrate(
    link: BoardLink, config: car_config.CarConfig, stdin: TextIO, stdout: TextIO
) -> car_config.CarConfig | None:
    """Walk through STEPS; return the calibrated config, or None when the user quit."""
    pwm = config.pwm
    with _Feeder(link) as feeder:
        for step in STEPS:
            value = getattr(pwm, step.key)
            print(f"\n{step.key}: adjust until {step.prompt}\n{HELP}", file=stdout)
            while True:
                error = _show(link, feeder, car_config.board_config(config), step)
                if error:
                    print(f"  {value} us: {error}", file=stdout)
                print(f"  {step.key} = {value} us > ", end="", file=stdout, flush=True)
                line = stdin.readline()
                if line == "" or line.strip().lower() == "q":
                    print("\ncalibration abandoned: nothing written", file=stdout)
                    return None
                try:
                    new = _parse(line, value)
                except ValueError:
                    print(f"  not understood: {line.strip()!r}", file=stdout)
                    continue
                if new is None:
                    if error:
                        print("  fix the value first: the board refused it", file=stdout)
                        continue
                    break
                value = max(800, min(2200, new))
                pwm = replace(pwm, **{step.key: value})
                config = replace(config, pwm=pwm)
    return config


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "calibrate", help="find steering and throttle pulses interactively (car on a stand)"
    )
    parser.add_argument("--config", required=True, help="car TOML to update")
    parser.add_argument("--port", help="serial port (overrides serial.port)")
    parser.add_argument(
        "--receiver",
        action="store_true",
        help="learn the RC transmitter's endpoints, centres and e-stop switch instead",
    )
    parser.add_argument(
        "--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
        help="override a key of the config being calibrated (repeatable)",
    )  # fmt: skip
    parser.set_defaults(func=run)


def run(args: argparse.Namespace, stdin: TextIO | None = None, stdout: TextIO | None = None) -> int:
    stdin, stdout = stdin or sys.stdin, stdout or sys.stdout
    overrides = list(args.set) + ([f'serial.port="{args.port}"'] if args.port else [])
    config = car_config.load(args.config, overrides)
    link = BoardLink(config.serial.port, config.serial.baud)
    if getattr(args, "receiver", False):
        from carrt import calibrate_receiver

        with link:
            return calibrate_receiver.run(link, config, Path(args.config), stdin, stdout)
    with link:
        print(f"calibrating the board on {config.serial.port}: put the car on a stand", file=stdout)
        result = calibrate(link, config, stdin, stdout)
        if result is None:
            return 1
        car_config.from_dict(result.to_dict())  # the combination must still be valid
        keys = [s.key for s in STEPS]
        path = Path(args.config)
        # the file's edit is checked before the board stores anything: one refused leaves both
        edit = plan_edit(path, "pwm", {k: getattr(result.pwm, k) for k in keys})
        disarm_and_wait(link)
        ack = link.send_config(car_config.board_config(result, persist=True))
        if ack.result != m.ConfigResult.ACCEPTED or not ack.persisted:
            raise UserError("board did not store the calibration (is it armed, or has no EEPROM?)")
    commit(edit)
    summary = ", ".join(f"{k} {getattr(result.pwm, k)}" for k in keys)
    print(f"\nwrote {summary} to {path} and the board's EEPROM", file=stdout)
    return 0
