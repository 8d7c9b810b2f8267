"""`carrt eval`: drive a policy over simulated placements and print the paper's table.

Only the parser and the checks of what the user typed live here: the simulator (and
onnxruntime) are imported when the command runs, so a real car's start-up never loads them.

    carrt eval --model policy.onnx --layout hard --tracks 100-104 --seconds 60 --seeds 0,1
    carrt eval --expert --tracks 100-104            # the scripted expert's baseline
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from carrt import layouts
from carrt.arg_types import finite_positive, format_int_list, parse_int_list
from carrt.errors import UserError
from carrt.model_contract import trained_on

LOG = logging.getLogger(__name__)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "eval",
        help="drive a policy on simulated placements (fast, auto-reset) and print the paper's "
        "table: completion, collisions/min, average speed, laps, and the racing numbers laps/min, "
        "lap time and progress per metre driven (mean ± std)",
    )
    who = parser.add_mutually_exclusive_group(required=True)
    who.add_argument("--model", help="policy .onnx to evaluate, or `demo` for the shipped one")
    who.add_argument("--expert", action="store_true", help="evaluate the scripted expert")
    parser.add_argument(
        "--layout", default="hard", choices=layouts.NAMES, help="obstacles (default: %(default)s)"
    )
    parser.add_argument(
        "--tracks", default="100-104", help="placement seeds: ranges and lists, e.g. 100-104,120"
    )
    parser.add_argument("--seconds", default="60", help="simulated seconds per run (default 60)")
    parser.add_argument("--seeds", default="0", help="run seeds (camera phase), e.g. 0,1,2")
    parser.add_argument("--jobs", type=int, default=1, help="parallel processes (default 1)")
    parser.add_argument(
        "--expert-intervene",
        action="store_true",
        help="let the scripted expert take over before collisions (measures the policy with "
        "a safety driver)",
    )
    parser.add_argument("--json", help="also write per-run and aggregate numbers here")
    parser.set_defaults(func=run_eval)


def run_eval(args: argparse.Namespace) -> int:
    tracks = parse_int_list(args.tracks, "tracks")
    seeds = parse_int_list(args.seeds, "seeds")
    try:  # checked here, not by argparse: carrt's errors are one line (no usage block)
        seconds = finite_positive(args.seconds)
    except argparse.ArgumentTypeError as exc:
        raise UserError(f"--seconds: {exc}") from None
    if args.jobs < 1:
        raise UserError(f"--jobs: expected at least 1, got {args.jobs}")
    model = None
    if args.model is not None:
        from carrt.policy import OnnxPolicy
        from carrt.shipped import resolve_model

        path = resolve_model(args.model)

        policy = OnnxPolicy(path)  # refuses a model that breaks the contract, before any run
        model = str(path)
        seen = trained_on(policy.metadata, args.layout, tracks)
        if seen:
            LOG.warning(
                f"{len(seen)} of the {len(tracks)} placements ({format_int_list(seen)}, layout "
                f"{args.layout}) are ones {path.name} was trained on: on those the numbers say "
                "how it repeats what it saw, not how it drives a place it never saw (choose on "
                "validation 200-259, report on test 100-199)"
            )
    if args.expert_intervene and model is None:
        raise UserError(
            "--expert-intervene needs --model (the expert cannot take over from itself)"
        )
    from carrt.sim.evaluate import evaluate, format_table

    label = "scripted expert" if model is None else Path(model).name
    runs = len(tracks) * len(seeds)
    print(
        f"carrt eval: {label} on {args.layout} placements {args.tracks}, seeds {args.seeds}: "
        f"{runs} run(s) of {seconds:g} simulated s, auto-reset after collisions"
    )
    result = evaluate(
        model, args.layout, tracks, seconds, seeds, args.jobs, intervene=args.expert_intervene
    )
    print(format_table(result, label))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
        print(f"numbers written to {args.json}")
    return 0
