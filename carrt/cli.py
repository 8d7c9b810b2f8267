"""The `carrt` command: one entry point, one sub-command per job on the car.

Sub-commands are registered from their own modules; the ones that need OpenCV, onnxruntime
or pygame are only imported when their parser is built, which is every run, so those modules
keep their heavy imports inside functions where start-up time matters (`carrt check` on a
Jetson should not wait for onnxruntime).
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys

from carrt import __version__
from carrt.deps import missing_package_message
from carrt.errors import EXIT_USAGE, UserError
from carrt.model_contract import ContractError
from firmware_bridge.link import LinkError
from firmware_bridge.native import FirmwareBuildError

EXIT_BROKEN_PIPE = 128 + signal.SIGPIPE  # what a shell reports for a tool its reader closed

# module: function that registers its sub-command(s)
COMMANDS = (
    ("carrt.check", "add_parser"),
    ("carrt.config_cmd", "add_parser"),
    ("carrt.calibrate", "add_parser"),
    ("carrt.session", "add_parsers"),
    ("carrt.episodes.cli", "add_parser"),
    ("carrt.report", "add_parser"),
    ("carrt.model_info", "add_parser"),
    ("carrt.eval_cmd", "add_parser"),
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="carrt", description="Vision-based autonomous RC car racing (DIRL), on the car."
    )
    parser.add_argument("--version", action="version", version=f"carrt {__version__}")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module_name, function in COMMANDS:
        getattr(importlib.import_module(module_name), function)(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (UserError, LinkError, ContractError, FirmwareBuildError) as exc:
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        print(f"carrt {args.command}: error: {message}", file=sys.stderr)
        return EXIT_USAGE
    except ModuleNotFoundError as exc:
        message = missing_package_message(exc)
        if message is None:
            raise
        print(f"carrt {args.command}: error: {message}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # `carrt report DIR | head`: the reader has all it wanted. Point stdout at /dev/null so
        # the interpreter's final flush does not raise again, and exit as `yes | head` would.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_BROKEN_PIPE


if __name__ == "__main__":
    sys.exit(main())
