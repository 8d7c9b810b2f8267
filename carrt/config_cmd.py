"""`carrt config init` writes a commented default; `carrt config check` validates a file."""

from __future__ import annotations

import argparse
from pathlib import Path

from carrt import config as car_config
from carrt.errors import UserError


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("config", help="create or check a car configuration file")
    sub = parser.add_subparsers(dest="config_command", required=True, metavar="ACTION")
    init = sub.add_parser("init", help="write a commented default configuration")
    init.add_argument(
        "-o", "--output", default="car.toml", help="file to write (default: %(default)s)"
    )
    init.add_argument("--force", action="store_true", help="overwrite an existing file")
    init.set_defaults(func=run_init)
    check = sub.add_parser("check", help="validate a configuration file")
    check.add_argument("path", help="the car TOML to check")
    check.add_argument(
        "--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
        help="override a key, as drive and teleop would (repeatable)",
    )  # fmt: skip
    check.set_defaults(func=run_check)


def run_init(args: argparse.Namespace) -> int:
    path = Path(args.output)
    if path.exists() and not args.force:
        raise UserError(f"{path} already exists (use --force to overwrite)")
    path.write_text(car_config.render())
    print(f"wrote {path}: set serial.port and camera.source, then run carrt calibrate")
    return 0


def run_check(args: argparse.Namespace) -> int:
    car_config.load(args.path, args.set)
    print(f"{args.path}: ok")
    return 0
