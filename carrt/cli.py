"""The `carrt` command: one entry point, one sub-command per job on the car."""

from __future__ import annotations

import argparse
import sys

from carrt import __version__
from carrt import check as check_cmd
from carrt.errors import EXIT_USAGE, UserError
from firmware_bridge.link import LinkError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="carrt", description="Vision-based autonomous RC car racing (DIRL), on the car."
    )
    parser.add_argument("--version", action="version", version=f"carrt {__version__}")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    check_cmd.add_parser(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (UserError, LinkError) as exc:
        print(f"carrt {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
