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
import logging
import secrets
import signal
import threading
import time
from pathlib import Path
from typing import Any

from carrt import __version__, layouts, rigs
from carrt import config as car_config
from carrt.arg_types import finite_non_negative
from carrt.disk_space import check_room
from carrt.errors import UserError
from carrt.progress import recording_bar
from firmware_bridge.link import BoardLink, LinkError

LOG = logging.getLogger(__name__)


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    teleop = subparsers.add_parser(
        "teleop", help="drive with the joystick; with --record, record expert episodes"
    )
    _common_arguments(teleop)
    teleop.add_argument(
        "--expert",
        choices=("auto",),
        help="with --sim: the scripted expert drives instead of a person",
    )
    _expert_noise_argument(teleop, "with --expert")
    teleop.set_defaults(func=run_teleop)
    drive = subparsers.add_parser(
        "drive", help="let a policy drive; the joystick overrides and e-stops"
    )
    drive.add_argument(
        "--model",  # required, checked in run_drive: one line, not argparse's usage block
        help="the policy to drive (required): .onnx exported by `carrt-export`, or `demo` for "
        "the shipped policy",
    )
    drive.add_argument(
        "--autopilot",
        action="store_true",
        help="with --sim: arm, engage AUTO, and reset the car after every collision",
    )
    drive.add_argument(
        "--expert-intervene",
        action="store_true",
        help="with --sim --autopilot: the scripted expert plays the person who takes over "
        "when a collision is near (recorded as interventions: override + the expert's a*)",
    )
    _expert_noise_argument(drive, "with --expert-intervene: on the expert's take-overs")
    _common_arguments(drive)
    drive.set_defaults(func=run_drive)


def _expert_noise_argument(parser: argparse.ArgumentParser, when: str) -> None:
    """The imperfect person: the same σ on demonstrations and on take-overs, so a study's noisy
    demonstrator does not become a clean one when it takes over from the policy."""
    parser.add_argument(
        "--expert-noise",
        type=finite_non_negative,
        default=0.0,
        metavar="SIGMA",
        help=f"{when}, add Gaussian noise of this σ to every expert command (the paper's "
        "imperfect demonstrations: 0.5, 1.0)",
    )
    parser.add_argument(
        "--expert-noise-tau",
        type=finite_non_negative,
        default=0.0,
        metavar="SECONDS",
        help="how long the expert's error lasts (an Ornstein-Uhlenbeck process, the same σ per "
        "command); 0 (default): a fresh error every command",
    )


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
    parser.add_argument(
        "--view",
        metavar="[HOST:]PORT",
        help="watch in a browser: camera and crop, mode, actions, plan, timings, link (PORT "
        "serves on localhost; another HOST, e.g. 0.0.0.0:8090, needs the token printed at "
        "start; the page can only e-stop)",
    )
    parser.add_argument(
        "--rig",
        metavar="NAME",
        help="what to drive, from carrt/rigs.py's table: "
        + "; ".join(f"{k.name}: {k.summary}" for k in rigs.RIGS.values())
        + " (default: car)",
    )
    sim = parser.add_argument_group("simulator (no car needed)")
    sim.add_argument("--sim", action="store_true", help="drive the built-in simulator (--rig sim)")
    sim.add_argument(
        "--layout",
        default="easy",
        choices=layouts.NAMES,
        help="obstacles: none, 2, 8, or mixed (4-10 per placement)",
    )
    sim.add_argument("--track-seed", type=int, default=0, help="obstacle placement seed")
    sim.add_argument(
        "--board",
        choices=("virtual", "avr"),
        help="the simulator's board behind the pty in real time: the C core built for this "
        "machine (virtual, default: --rig sim) or the firmware binary on an emulated ATmega328P "
        "(avr: --rig avr; implies --realtime, needs gcc-avr arduino-core-avr simavr "
        "libsimavr-dev)",
    )
    sim.add_argument(
        "--realtime",
        action="store_true",
        help="run at wall-clock speed through the pty (default when a person drives or "
        "--view watches)",
    )
    sim.add_argument(
        "--episodes", type=int,
        help="with --expert/--autopilot: stop after this many episodes (each ends after --laps "
        "laps, 1 unless given, or at a collision)",
    )  # fmt: skip
    sim.add_argument(
        "--laps", type=int,
        help="with --expert/--autopilot: end an episode after this many laps (default: endless, "
        "or 1 with --episodes)",
    )  # fmt: skip
    sim.add_argument("--plot", help="write the run's top-down trajectory plot here (PNG)")
    sim.add_argument(
        "--random-start",
        action="store_true",
        help="with --expert/--autopilot: start every episode at a random place on the track",
    )
    sim.add_argument(
        "--pad", action="store_true", help="drive the simulator with a joystick (default: keyboard)"
    )


# The simulated car has no gearbox to strip: let it use the whole throttle range unless the
# user says otherwise (a real car's config starts at half throttle).
SIM_DEFAULTS = ("pwm.max_forward=1.0", "pwm.max_reverse=1.0")


def load_config(args: argparse.Namespace) -> car_config.CarConfig:
    simulated = rigs.chosen(args).simulator
    overrides = [*(SIM_DEFAULTS if simulated else ()), *args.set]
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
    if args.model is None:
        raise UserError(
            "--model is required: a policy .onnx exported by carrt-export, or demo for the "
            "shipped one (carrt drive --sim --model demo)"
        )
    return _run(args, load_config(args), model_path=args.model)


def _run(args: argparse.Namespace, config: car_config.CarConfig, model_path: str | None) -> int:
    # Imported here: OpenCV, onnxruntime and pygame cost a second of start-up on a Jetson,
    # which `carrt check` and `carrt episodes` should not pay.
    from carrt.episodes.writer import EpisodeWriter
    from carrt.loop import ControlLoop, LoopParts
    from carrt.noise import NoiseInjector
    from carrt.policy import OnnxPolicy

    for flag in ("episodes", "laps"):
        value = getattr(args, flag, None)
        if value is not None and value < 1:
            raise UserError(f"--{flag}: expected at least 1, got {value}")
    policy = None
    if model_path is not None:
        policy = OnnxPolicy(
            model_path,
            providers=tuple(config.loop.providers),
            intra_op_threads=config.loop.intra_op_threads,
            control_period_s=1.0 / config.loop.rate_hz,
        )
        warm = policy.warm_up()
        LOG.info(f"model {policy.path.name}: {policy.provider}, warm-up {warm[-1] * 1e3:.1f} ms")

    with contextlib.ExitStack() as stack:
        view = None
        if getattr(args, "view", None) is not None:
            from carrt.view.server import ViewServer

            view = ViewServer(args.view)  # binds now: a port in use ends here, car untouched
            stack.callback(view.close)
        rig = rigs.open_rig(stack, args, config, driving=policy is not None)
        link = rig.link
        ack = link.keep_config(car_config.board_config(config))  # and after every reboot
        if ack.result != 0:
            raise UserError(
                f"board refused the PWM config from the car config (result {ack.result}): "
                "is it still armed by another process?"
            )

        sink = None
        if args.record:  # before the car moves: a disk without room refuses here
            room = check_room(config.episodes.dir, config.loop.rate_hz,
                              config.episodes.min_free_minutes)  # fmt: skip
            LOG.info(room)
            sink = EpisodeWriter(
                config.episodes.dir,
                queue_steps=config.episodes.queue_steps,
                sync_every_s=config.episodes.sync_every_s,
                # faster than real time a dropped step is lost data for nothing: wait instead
                wait_when_full=rig.simulated_time,
            )
            stack.callback(sink.close)
        parts = LoopParts(
            clock=rig.clock,
            camera=rig.camera,
            link=link,
            joystick=rig.joystick,
            policy=policy,
            sink=sink,
            noise=(
                NoiseInjector(config.noise, seed=args.seed)
                if policy is None or config.noise.during_auto
                else None
            ),
            collisions=rig.collisions,
        )
        metadata = _episode_metadata(config, policy, link, "drive" if policy else "teleop")
        if rigs.chosen(args).simulator:
            metadata["sim"] = {"layout": args.layout, "track_seed": args.track_seed}
        loop = ControlLoop(
            parts,
            config,
            allow_auto=policy is not None,
            record=args.record,
            episode_metadata=metadata,
            max_steps=None if args.duration is None else round(args.duration * config.loop.rate_hz),
            # the scripted expert arms and disarms once per episode: its mode changes are
            # detail (-v), not news, or a 20-episode recording prints 40 of them
            log=LOG.debug if getattr(args, "expert", None) == "auto" else LOG.info,
        )
        for follower in rig.follows_mode:  # the sim's pilot and trajectory tracker
            follower.mode_source = lambda: loop.arbiter.mode
        for watcher in rig.watches_loop:  # the simulator's keyboard window
            watcher.status_source = lambda: loop.live
        if view is not None:
            from carrt.view.live import live_view

            live_view(view, loop, config, "drive" if policy else "teleop")
        rig.joystick.start(on_estop=lambda: loop.estop("joystick"))
        stack.callback(rig.joystick.stop)
        stopped_by = _stop_on_signals(loop, stack)
        LOG.info(f"carrt {'drive' if policy else 'teleop'}: {rig.describe}")
        with recording_bar(loop, enabled=args.record):
            summary = loop.run()
    print(summary.render())
    try:  # the simulator's run files and the summary: a full disk here is one line too
        if rig.finish is not None:
            rig.finish(summary)
        if args.summary_json:
            Path(args.summary_json).write_text(json.dumps(summary.to_dict(), indent=2) + "\n")
    except OSError as exc:
        if summary.write_error is None:
            raise UserError(
                f"could not save the run's files: {exc.strerror} ({exc.filename})"
            ) from None
    if link.error is not None:
        raise link.error
    if summary.write_error is not None:
        raise UserError(
            f"recording failed: {summary.write_error}; the episodes written before it are whole "
            "(carrt episodes show --verify)"
        )
    # Ctrl-C ends a drive cleanly (summary, episodes closed, car stopped), and still exits as
    # every other command stopped by a signal does: 128 + the signal (130 for Ctrl-C).
    return 128 + stopped_by[0] if stopped_by else 0


def _episode_metadata(config, policy, link: BoardLink, mode: str) -> dict[str, Any]:
    from carrt.faults import board_metadata

    board = link.board
    return {
        "carrt_version": __version__,
        "session": mode,
        # One recording session is one placement of the obstacles on a real car: training
        # holds out whole sessions (training.data.placement_key), so each run gets its own id.
        "session_id": f"{time.strftime('%Y%m%d-%H%M%S')}-{secrets.token_hex(3)}",
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
        "board": board_metadata(board),  # the loop names each episode's own boot
    }


def _stop_on_signals(loop: Any, stack: contextlib.ExitStack) -> list[int]:
    """SIGINT/SIGTERM end the run through the normal shutdown (only from the main thread);
    the previous handlers come back when the run ends, so a caller that runs several sessions
    in one process (carrt eval, the tests) is never left with a handler of a finished loop.
    Returns a list that will hold the signal that stopped the run, if one did."""
    caught: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        return caught

    def stop(signum: int, _frame: Any) -> None:
        caught.append(int(signum))
        loop.stop()

    for sig in (signal.SIGINT, signal.SIGTERM):
        stack.callback(signal.signal, sig, signal.getsignal(sig))
        signal.signal(sig, stop)
    return caught


__all__ = ["LinkError", "add_parsers"]
