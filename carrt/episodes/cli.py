"""`carrt episodes ls|show|video|view|…`: look at recordings before they go into training, and
take them to and from LeRobot's format."""

from __future__ import annotations

import argparse
import json
import sys

from carrt.episodes import replay
from carrt.episodes.reader import in_order, list_episodes, read_episode
from carrt.errors import EXIT_USAGE, UserError

# carrt.episodes.contact_sheet imports OpenCV, which every `carrt` command would pay for at start-up
# if it were imported here: the CLI builds all parsers on every run.


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("episodes", help="list, summarise and render recorded episodes")
    sub = parser.add_subparsers(dest="episodes_command", required=True, metavar="ACTION")

    ls = sub.add_parser(
        "ls", help="one line per episode: duration, frames, speed, end reason, flags"
    )
    ls.add_argument(
        "dirs", nargs="*", default=["episodes"], metavar="DIR", help="default: episodes"
    )
    ls.add_argument(
        "--flags", metavar="NAME[,NAME]", help="only the episodes with any of these flags"
    )
    ls.set_defaults(func=run)

    show = sub.add_parser("show", help="an episode's summary and metadata")
    show.add_argument("episode", metavar="EP", help="an episode directory")
    show.add_argument("--json", action="store_true", help="print the summary as JSON")
    show.add_argument(
        "--meta", action="store_true", help="also print the metadata (car config, model, ...)"
    )
    show.add_argument(
        "--verify", action="store_true", help="check every record's CRC, not only the unsynced tail"
    )
    show.set_defaults(func=run)

    video = sub.add_parser(
        "video",
        help="render episodes to one video (H.264, plays in a browser) or a contact sheet",
        description="Render episodes, in order, to one video with the camera, mode, speed, the "
        "person's, the policy's and the executed actions and the plan's mu over H drawn beside.",
        epilog="example: carrt episodes video episodes/20261123-* -o run.mp4",
    )
    video.add_argument(
        "episode", metavar="EP", nargs="+", help="episodes, in order, or folders of them"
    )
    out = video.add_mutually_exclusive_group(required=True)
    out.add_argument(
        "-o", "--output", metavar="OUT", help="video file: .mp4 (H.264) or .avi (MJPG)"
    )
    out.add_argument("--sheet", metavar="PNG", help="write a contact sheet instead")
    video.add_argument("--fps", type=float, default=10.0, help="video frame rate (default 10)")
    video.add_argument("--scale", type=int, default=4, help="video upscaling (default 4)")
    video.add_argument("--every", type=int, default=10, help="sheet: every Nth frame (default 10)")
    video.set_defaults(func=run)

    mark = sub.add_parser(
        "mark",
        help="exclude seconds of an episode from training, or note something, without "
        "rewriting it (marks.json beside it, undoable)",
        description="Marks live beside the recorded files (which are never rewritten): "
        "excluded ranges, in seconds from the episode's first frame, and notes. Training leaves "
        "excluded steps out of every stage.",
        epilog="example: carrt episodes mark episodes/20261123-101500-000 --exclude 12.5-15.0",
    )
    mark.add_argument("episode", metavar="EP", nargs="+", help="episode directories")
    mark.add_argument("--exclude", action="append", default=[], metavar="START-END",
                      help="exclude START-END seconds (repeatable)")  # fmt: skip
    mark.add_argument("--exclude-last", metavar="SECONDS",
                      help="exclude the last SECONDS (e.g. 3s)")  # fmt: skip
    mark.add_argument("--exclude-all", action="store_true", help="exclude the whole episode")
    mark.add_argument("--exclude-flag", action="append", default=[], metavar="NAME[,NAME]",
                      help="exclude the steps a flag names, e.g. frozen-camera")  # fmt: skip
    mark.add_argument("--note", action="append", default=[], help="add a note")
    what = mark.add_mutually_exclusive_group()
    what.add_argument("--list", action="store_true", help="print the marks (the default)")
    what.add_argument("--clear", action="store_true", help="remove every mark")
    what.add_argument(
        "--undo", action="store_true", help="back to the marks before the last change"
    )
    mark.set_defaults(func=run)

    salvage = sub.add_parser(
        "salvage",
        help="write the intact steps of an episode --verify reports damaged as a new episode",
        epilog="example: carrt episodes salvage episodes/20261123-101500-000 -o salvaged/",
    )
    salvage.add_argument("episode", metavar="EP", help="a damaged episode directory")
    salvage.add_argument("-o", "--output", required=True, metavar="DIR",
                         help="folder the new episode goes into")  # fmt: skip
    salvage.set_defaults(func=run)

    rrd = sub.add_parser(
        "rerun",
        help="write episodes as a Rerun recording (.rrd): camera, speed, actions, plan, mode, "
        "collisions, marks on one timeline per episode",
        epilog="example: carrt episodes rerun episodes/20261123-* -o run.rrd && rerun run.rrd",
    )
    rrd.add_argument("episode", metavar="EP", nargs="+", help="episodes, or folders of them")
    rrd.add_argument("-o", "--output", required=True, metavar="FILE.rrd", help="file to write")
    rrd.set_defaults(func=run)

    export = sub.add_parser(
        "export",
        help="write episodes as a LeRobotDataset v3.0 (the Hub's format: parquet and H.264)",
        description="Write episodes as a LeRobotDataset v3.0: the camera as an H.264 video, "
        "the speed as observation.state, the person's action a* as action, carrt's other "
        "fields as carrt.* features (docs/episodes.md); one LeRobot episode per episode or per "
        "run of steps between excluded ranges (excluded steps are never exported).",
        epilog="example: carrt episodes export episodes/ --format lerobot -o my-car-dataset",
    )
    export.add_argument("episode", metavar="EP", nargs="+", help="episodes, or folders of them")
    export.add_argument("--format", required=True, choices=["lerobot"],
                        help="lerobot: LeRobotDataset v3.0")  # fmt: skip
    export.add_argument("-o", "--output", required=True, metavar="OUT",
                        help="the dataset's folder (new, or empty)")  # fmt: skip
    export.add_argument(
        "--video", choices=["lossless", "browser"], default="lossless",
        help="lossless (default): 4:4:4 H.264, frames back within 2/255; browser: 4:2:0, "
        "what browsers and the Hub's visualiser play, a sharp colour edge far off",
    )  # fmt: skip
    export.set_defaults(func=run)

    imp = sub.add_parser(
        "import",
        help="read a LeRobotDataset v3.0 as episodes (a carrt export, or another's with "
        "--camera/--action/--speed)",
        epilog="example: carrt episodes import my-car-dataset -o episodes-imported",
    )
    imp.add_argument("dataset", metavar="IN", help="the dataset's folder (meta/info.json)")
    imp.add_argument("-o", "--output", required=True, metavar="DIR",
                     help="folder the episodes go into")  # fmt: skip
    imp.add_argument("--camera", metavar="KEY", help="its camera's video feature")
    imp.add_argument("--action", metavar="KEY", help="its [steering, throttle] feature")
    imp.add_argument("--speed", metavar="KEY[:I]", help="its speed (entry I of a vector)")
    imp.set_defaults(func=run)

    view = sub.add_parser(
        "view",
        help="scrub episodes in a browser: frame, actions, plan, speed, flags, collisions, laps",
        description="Serve a page that scrubs episodes step by step: the 96x96 frame, a* "
        "(the person's), the policy's and the executed action, the plan's mu +- sigma, speed, "
        "mode, flags, collision labels and lap marks, on a timeline of the whole run.",
    )
    view.add_argument(
        "episode", metavar="EP", nargs="+", help="episodes, in order, or folders of them"
    )
    view.add_argument(
        "--view",
        metavar="[HOST:]PORT",
        default="8090",
        help="where to serve (default 8090 on localhost; 0 picks a free port; another HOST "
        "needs the token printed at start)",
    )
    view.add_argument(
        "--model", action="append", metavar="M.onnx",
        help="also each step's action of this policy as the car would have run it (carrt "
        "episodes replay), as a trace on the timeline; give it twice to compare two",
    )  # fmt: skip
    view.set_defaults(func=run)
    replay.add_parser(sub)
    sub.choices["replay"].set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    actions = {"ls": run_ls, "show": run_show, "video": run_video, "view": run_view,
               "mark": run_mark, "rerun": run_rerun, "salvage": run_salvage,
               "replay": replay.run_replay, "export": run_export,
               "import": run_import}  # fmt: skip
    return actions[args.episodes_command](args)


def run_ls(args: argparse.Namespace) -> int:
    from carrt.episodes.flags import label, parse_names
    from carrt.episodes.summary import summarize

    wanted = parse_names(args.flags) if args.flags is not None else None
    paths = list_episodes(args.dirs)
    summaries = [summarize(read_episode(path)) for path in paths]  # errors before any output
    if wanted is not None:
        summaries = [s for s in summaries if set(s["flags"]) & set(wanted)]
    print(f"{'episode':<22} {'duration':>9} {'frames':>7} {'avg m/s':>8}  end")
    total_s = total_frames = 0
    for s in summaries:
        total_s += s["duration_s"]
        total_frames += s["frames"]
        end = s["end_reason"] + (" (torn tail)" if s["torn_tail"] else "")
        end += f" ({s['excluded_steps']} excluded)" if s["excluded_steps"] else ""
        if s["flags"]:
            end += "  flags: " + ", ".join(label(n, r) for n, r in s["flags"].items())
        print(
            f"{s['name']:<22} {s['duration_s']:>8.1f}s {s['frames']:>7} "
            f"{s['avg_speed_mps']:>8.2f}  {end}"
        )
    kept = f" with {', '.join(wanted)} (of {len(paths)})" if wanted is not None else ""
    print(f"{len(summaries)} episodes{kept}, {total_s / 60:.1f} min, {total_frames} frames")
    return 0


def run_show(args: argparse.Namespace) -> int:
    from carrt.episodes.summary import format_summary, summarize

    ep = read_episode(args.episode, verify_all=args.verify)
    summary = summarize(ep)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(format_summary(summary))
        if args.meta:
            meta = {k: v for k, v in ep.meta.items() if k != "format"}
            print("metadata:")
            print(json.dumps(meta, indent=2, default=str))
        else:
            print("(metadata: --meta)")
    if ep.damage is not None:  # damage is not a torn tail: the run says so and fails
        print(f"carrt episodes: error: {ep.damage.describe(ep.path)}", file=sys.stderr)
        return EXIT_USAGE
    return 0


def run_mark(args: argparse.Namespace) -> int:
    from carrt.episodes import flags as suspect
    from carrt.episodes import marks as mk

    named = [n for text in args.exclude_flag for n in suspect.parse_names(text, "--exclude-flag")]
    episodes = [read_episode(path) for path in in_order(args.episode)]  # errors before changes
    ranges = [mk.parse_range(text) for text in args.exclude]
    last = mk.parse_seconds(args.exclude_last) if args.exclude_last else None
    adds = bool(ranges or last is not None or args.exclude_all or args.note or named)
    if adds and (args.clear or args.undo):
        raise UserError("--clear and --undo stand alone: give them without new marks")
    for ep in episodes:
        if args.undo:
            marks = mk.undo(ep.path)
        elif args.clear:
            marks = mk.change(ep.path, lambda m: (m.exclude.clear(), m.notes.clear(),
                                                  setattr(m, "whole", False)))  # fmt: skip
        elif adds:
            new = list(ranges)
            if last is not None:
                # the steps in (end − last, end]: "the last 3 s" of 10 Hz is 30 steps
                start = round(max(0.0, ep.duration_s - last) + 1e-3, 3)
                new.append((start, round(ep.duration_s + 1.0, 3)))
            flagged = suspect.find_flags(ep, tuple(named)) if named else {}
            for name in named:  # exactly the steps the flag names, as `show` lists them
                new += suspect.exclusions(flagged.get(name, []), ep.timestamps)
                print(f"{ep.name}: {name}: {len(flagged.get(name, []))} range(s)")

            def add(m, new=new):
                m.exclude.extend(r for r in new if r not in m.exclude)
                m.whole = m.whole or args.exclude_all
                m.notes.extend(args.note)

            marks = mk.change(ep.path, add)
        else:
            marks = mk.read_marks(ep.path)
        excluded = int(marks.excluded(ep.timestamps).sum()) if ep.n else 0
        print(f"{ep.name}: {marks.describe()} ({excluded} of {ep.n} steps excluded)")
    return 0


def run_salvage(args: argparse.Namespace) -> int:
    from carrt.episodes.salvage import salvage

    out, kept, total = salvage(args.episode, args.output)
    print(
        f"wrote {out}: {kept} intact steps of {total} (verify: carrt episodes show {out} --verify)"
    )
    return 0


def run_rerun(args: argparse.Namespace) -> int:
    from carrt.episodes.rerun_export import write_rrd

    if not args.output.endswith(".rrd"):
        raise UserError(f"-o {args.output}: a Rerun recording ends in .rrd")
    episodes = [read_episode(path) for path in in_order(args.episode)]
    steps = write_rrd(episodes, args.output)
    print(f"wrote {args.output} ({len(episodes)} episode(s), {steps} steps): rerun {args.output}")
    return 0


def run_export(args: argparse.Namespace) -> int:
    import time

    from carrt.episodes.lerobot_export import export_lerobot

    start = time.perf_counter()
    done = export_lerobot(args.episode, args.output, video=args.video)
    print(
        f"wrote {args.output}: LeRobotDataset v3.0, {done['lerobot_episodes']} episode(s) of "
        f"{done['episodes']} recorded, {done['frames']} frames, "
        f"{time.perf_counter() - start:.1f} s"
    )
    return 0


def run_import(args: argparse.Namespace) -> int:
    from carrt.episodes.lerobot_import import Mapping, import_lerobot

    mapping = Mapping.parse(args.camera, args.action, args.speed)
    paths = import_lerobot(args.dataset, args.output, mapping)
    print(f"wrote {len(paths)} episode(s) into {args.output} (check: carrt episodes ls "
          f"{args.output}; carrt episodes show EP --verify)")  # fmt: skip
    return 0


def run_view(args: argparse.Namespace) -> int:
    from carrt.view.episodes import run_view as serve

    return serve(args)


def run_video(args: argparse.Namespace) -> int:
    from carrt.episodes.contact_sheet import render_contact_sheet
    from carrt.episodes.video import render_video

    episodes = [read_episode(path) for path in in_order(args.episode)]
    if args.sheet:
        if len(episodes) != 1:
            raise UserError("--sheet takes one episode")
        out = render_contact_sheet(episodes[0], args.sheet, every=args.every)
    else:
        out = render_video(episodes, args.output, fps=args.fps, scale=args.scale)
    frames = sum(ep.n for ep in episodes)
    print(f"wrote {out} ({len(episodes)} episode(s), {frames} frames)")
    return 0
