"""`carrt teleop` and `carrt drive`: assemble the parts, run the loop, always leave the car stopped.

Start-up order is chosen so that everything that can be wrong is found before the car can
move: config, then the model (validated and warmed up), then the camera (first frame), then
the board (handshake, calibration sent), and only then the joystick that can arm it. Whatever
ends the run (quit, Ctrl-C, SIGTERM, an exception) goes through the same shutdown: disarm,
neutral command, episode closed, link closed. A SIGKILL or a power cut skips all of that, and
then the board's 200 ms watchdog stops the car on its own.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import signal
import threading
import time
from pathlib import Path
from typing import Any

from carrt import __version__
from carrt import config as car_config
from carrt.clock import WallClock
from carrt.errors import UserError
from firmware_bridge.link import BoardLink, LinkError

FIRST_FRAME_TIMEOUT_S = 3.0


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    teleop = subparsers.add_parser(
        "teleop", help="drive with the joystick; with --record, record expert episodes"
    )
    _common_arguments(teleop)
    teleop.set_defaults(func=run_teleop)
    drive = subparsers.add_parser(
        "drive", help="let a policy drive; the joystick overrides and e-stops"
    )
    drive.add_argument("--model", required=True, help="policy .onnx exported by `python -m export`")
    _common_arguments(drive)
    drive.set_defaults(func=run_drive)


def _common_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="car TOML (default: built-in defaults)")
    parser.add_argument(
        "--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="override a key"
    )
    parser.add_argument("--port", help="serial port (overrides serial.port)")
    parser.add_argument("--camera", help="camera source (overrides camera.source)")
    parser.add_argument("--record", action="store_true", help="record episodes")
    parser.add_argument("--out", help="episode directory (overrides episodes.dir)")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    parser.add_argument("--seed", type=int, default=0, help="noise injection seed")
    parser.add_argument("--summary-json", help="also write the end-of-run summary here")


def load_config(args: argparse.Namespace) -> car_config.CarConfig:
    overrides = list(args.set)
    for flag, key in (
        ("port", "serial.port"),
        ("camera", "camera.source"),
        ("out", "episodes.dir"),
    ):
        value = getattr(args, flag, None)
        if value is not None:
            overrides.append(f'{key}="{value}"')
    return car_config.load(args.config, overrides)


def run_teleop(args: argparse.Namespace) -> int:
    return _run(args, load_config(args), model_path=None)


def run_drive(args: argparse.Namespace) -> int:
    return _run(args, load_config(args), model_path=args.model)


def _run(args: argparse.Namespace, config: car_config.CarConfig, model_path: str | None) -> int:
    # Imported here: OpenCV, onnxruntime and pygame cost a second of start-up on a Jetson,
    # which `carrt check` and `carrt episodes` should not pay.
    from carrt.camera import OpenCVCamera
    from carrt.episodes.writer import EpisodeWriter
    from carrt.joystick import PygameJoystick
    from carrt.loop import ControlLoop, LoopParts
    from carrt.noise import NoiseInjector
    from carrt.policy import OnnxPolicy

    policy = None
    if model_path is not None:
        policy = OnnxPolicy(
            model_path,
            providers=tuple(config.loop.providers),
            intra_op_threads=config.loop.intra_op_threads,
            control_period_s=1.0 / config.loop.rate_hz,
        )
        warm = policy.warm_up()
        print(f"model {Path(model_path).name}: {policy.provider}, warm-up {warm[-1] * 1e3:.1f} ms")

    with contextlib.ExitStack() as stack:
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
        ack = link.send_config(car_config.board_config(config))
        if ack.result != 0:
            raise UserError(
                f"board refused the PWM config from the car config (result {ack.result}): "
                "is it still armed by another process?"
            )

        sink = None
        if args.record:
            sink = EpisodeWriter(
                config.episodes.dir,
                queue_steps=config.episodes.queue_steps,
                sync_every_s=config.episodes.sync_every_s,
            )
            stack.callback(sink.close)
        joystick = PygameJoystick(config.joystick)
        parts = LoopParts(
            clock=WallClock(),
            camera=camera,
            link=link,
            joystick=joystick,
            policy=policy,
            sink=sink,
            noise=NoiseInjector(config.noise, seed=args.seed) if policy is None else None,
        )
        loop = ControlLoop(
            parts,
            config,
            allow_auto=policy is not None,
            record=args.record,
            episode_metadata=_episode_metadata(
                config, policy, link, "drive" if policy else "teleop"
            ),
            max_steps=None if args.duration is None else round(args.duration * config.loop.rate_hz),
        )
        joystick.start(on_estop=lambda: loop.estop("joystick"))
        stack.callback(joystick.stop)
        _stop_on_signals(loop)
        print(
            f"carrt {'drive' if policy else 'teleop'}: board on {config.serial.port}, "
            f"camera {config.camera.source}; arm with the pad's arm button (sticks centred)"
        )
        summary = loop.run()
    print(summary.render())
    if args.summary_json:
        Path(args.summary_json).write_text(json.dumps(summary.to_dict(), indent=2) + "\n")
    if link.error is not None:
        raise link.error
    return 0


def _wait_first_frame(camera: Any, source: str) -> None:
    deadline = time.monotonic() + FIRST_FRAME_TIMEOUT_S
    while camera.latest() is None:
        if camera.lost or time.monotonic() > deadline:
            raise UserError(f"camera {source}: no frame within {FIRST_FRAME_TIMEOUT_S:.0f} s")
        time.sleep(0.01)


def _episode_metadata(config, policy, link: BoardLink, mode: str) -> dict[str, Any]:
    board = link.board
    return {
        "carrt_version": __version__,
        "session": mode,
        "car_config": config.to_dict(),
        "rate_hz": config.loop.rate_hz,
        "camera_source": config.camera.source,
        "model": None
        if policy is None
        else {
            "sha256": policy.sha256,
            "metadata": dict(policy.metadata),
            "provider": policy.provider,
        },
        "board": None
        if board is None
        else {"firmware": ".".join(map(str, board.firmware_version)), "boot_id": board.boot_id},
    }


def _stop_on_signals(loop: Any) -> None:
    """SIGINT/SIGTERM end the run through the normal shutdown (only from the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: loop.stop())


__all__ = ["LinkError", "add_parsers"]
