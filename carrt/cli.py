"""The `carrt` command: one entry point, one sub-command per job on the car.

Sub-commands are registered from their own modules; the ones that need OpenCV, onnxruntime
or pygame are only imported when their parser is built, which is every run, so those modules
keep their heavy imports inside functions where start-up time matters (`carrt check` on a
Jetson should not wait for onnxruntime).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import signal
import sys

from carrt import __version__
from carrt.deps import missing_package_message
from carrt.errors import EXIT_USAGE
from carrt.user_errors import USER_ERRORS, one_line

EXIT_BROKEN_PIPE = 128 + signal.SIGPIPE  # what a shell reports for a tool its reader closed

# module: function that registers its sub-command(s)
COMMANDS = (
    ("carrt.check", "add_parser"),
    ("carrt.config_cmd", "add_parser"),
    ("carrt.calibrate", "add_parser"),
    ("carrt.session_cmd", "add_parsers"),
    ("carrt.episodes.cli", "add_parser"),
    ("carrt.report", "add_parser"),
    ("carrt.model_info", "add_parser"),
    ("carrt.eval_cmd", "add_parser"),
)


# One example per sub-command, shown under its --help (a test checks every one has one).
EXAMPLES = {
    "check": "carrt check --port /dev/ttyACM0",
    "config": "carrt config init -o car.toml && carrt config check car.toml",
    "config init": "carrt config init -o car.toml",
    "config check": "carrt config check car.toml --set pwm.max_forward=0.4",
    "calibrate": "carrt calibrate --config car.toml --port /dev/ttyACM0",
    "teleop": "carrt teleop --config car.toml --record      # or: carrt teleop --sim",
    "drive": "carrt drive --config car.toml --model policy.onnx --record --view 0.0.0.0:8090\n"
    "  carrt drive --sim --autopilot --model demo --layout hard --track-seed 101 --view 8090",
    "episodes": "carrt episodes ls episodes/",
    "episodes ls": "carrt episodes ls episodes/",
    "episodes show": "carrt episodes show episodes/20261123-101500-000 --meta",
    "episodes video": "carrt episodes video episodes/20261123-* -o run.mp4",
    "episodes view": "carrt episodes view episodes/20261123-* --view 8090",
    "report": "carrt report episodes/ --per-episode",
    "model": "carrt model info policy.onnx",
    "model info": "carrt model info demo --json",
    "eval": "carrt eval --model demo --layout hard --tracks 100-104 --seconds 60 --seeds 0,1",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="carrt",
        description="Vision-based autonomous RC car racing (DIRL), on the car.",
        epilog="example: carrt teleop --sim   (then: carrt COMMAND --help)",
    )
    parser.add_argument("--version", action="version", version=f"carrt {__version__}")
    loud = parser.add_mutually_exclusive_group()
    loud.add_argument("-v", "--verbose", action="store_true", help="also log debug messages")
    loud.add_argument("-q", "--quiet", action="store_true", help="log warnings and errors only")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module_name, function in COMMANDS:
        getattr(importlib.import_module(module_name), function)(subparsers)
    _describe(parser, [])
    return parser


def _describe(parser: argparse.ArgumentParser, path: list[str]) -> None:
    """Give every sub-command its one-line help as description and its example as epilog."""
    for action in parser._actions:
        if not isinstance(action, argparse._SubParsersAction):
            continue
        helps = {a.dest: a.help for a in action._choices_actions}
        for name, sub in action.choices.items():
            sub.formatter_class = argparse.RawDescriptionHelpFormatter
            if not sub.description and helps.get(name):
                sub.description = helps[name][:1].upper() + helps[name][1:] + "."
            example = EXAMPLES.get(" ".join([*path, name]))
            if example and not sub.epilog:
                sub.epilog = f"example:\n  {example}"
            _describe(sub, [*path, name])


class _ConsoleHandler(logging.Handler):
    """Info to the stdout of the moment (tests capture it), warnings and errors to stderr
    with their level in front."""

    def emit(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        if record.levelno >= logging.WARNING:
            print(f"{record.levelname.lower()}: {text}", file=sys.stderr)
        else:
            print(text, file=sys.stdout)


def _setup_logging(args: argparse.Namespace) -> None:
    """The `carrt` loggers: info by default, debug with -v, warnings and errors only with -q."""
    logger = logging.getLogger("carrt")
    if not any(isinstance(h, _ConsoleHandler) for h in logger.handlers):
        logger.addHandler(_ConsoleHandler())
        logger.propagate = False
    logger.setLevel(
        logging.DEBUG if args.verbose else logging.WARNING if args.quiet else logging.INFO
    )


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    _setup_logging(args)
    try:
        return args.func(args)
    except USER_ERRORS as exc:
        print(f"carrt {args.command}: error: {one_line(exc)}", file=sys.stderr)
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
    except OSError as exc:
        message = one_line(exc)  # a full disk: one line; any other OSError is a bug
        if message is None:
            raise
        print(f"carrt {args.command}: error: {message}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
