"""`carrt teleop` and `carrt drive` on the command line: their flags, made into one
`DriveConfig` in one place (`drive_config`), then `carrt.session.run_session`, the same function
`carrt eval`, `carrt-sim-data` and the training loop call from code.

Only argparse lives here: what a drive does is carrt/session.py's, so a caller in code never
builds an argv, and the simulator (which imports the session) never imports a command line.
"""

from __future__ import annotations

import argparse
import sys

from carrt import layouts, rig_table
from carrt.arg_types import finite_non_negative
from carrt.errors import UserError
from carrt.session import LOG, DriveConfig, run_session


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
        help="what to drive, from carrt/rig_table.py's table: "
        + "; ".join(f"{k.name}: {k.summary}" for k in rig_table.RIGS.values())
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


def drive_config(args: argparse.Namespace) -> DriveConfig:
    """The one place the command line becomes a drive: every flag of teleop and drive, the rig
    resolved from --rig / --sim / --board (a wrong or doubled one is a UserError here, before
    anything loads)."""
    rig = rig_table.chosen(args.rig, sim=args.sim, board=args.board).name
    return DriveConfig(
        model=getattr(args, "model", None),
        rig=rig,
        config=args.config,
        sets=tuple(args.set),
        port=args.port,
        camera=args.camera,
        record=args.record,
        out=args.out,
        duration=args.duration,
        seed=args.seed,
        summary_json=args.summary_json,
        view=args.view,
        layout=args.layout,
        track_seed=args.track_seed,
        realtime=args.realtime,
        episodes=args.episodes,
        laps=args.laps,
        plot=args.plot,
        random_start=args.random_start,
        pad=args.pad,
        expert=getattr(args, "expert", None) == "auto",
        autopilot=getattr(args, "autopilot", False),
        expert_intervene=getattr(args, "expert_intervene", False),
        expert_noise=args.expert_noise,
        expert_noise_tau=args.expert_noise_tau,
    )


def run_teleop(args: argparse.Namespace) -> int:
    return _run(drive_config(args))


def run_drive(args: argparse.Namespace) -> int:
    if args.model is None:
        raise UserError(
            "--model is required: a policy .onnx exported by carrt-export, or demo for the "
            "shipped one (carrt drive --sim --model demo)"
        )
    return _run(drive_config(args))


def _run(cfg: DriveConfig) -> int:
    """On the console: start-up lines through the `carrt` logger (-v, -q), the report on
    stdout, the recording bar on stderr. Ctrl-C ends a drive cleanly and still exits as every
    other command stopped by a signal does: 128 + the signal (130 for Ctrl-C)."""
    return run_session(cfg, log=LOG, out=sys.stdout, progress=sys.stderr).exit_code
