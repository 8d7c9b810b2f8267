"""Training data from the simulator at scale: many obstacle placements, both cores busy.

    carrt-sim-data demos --out data/expert --tracks 1000-1149 --jobs 2
    carrt-sim-data interventions --model policy.onnx --out data/iter1 \
        --tracks 1000-1149
    carrt-sim-data drives --model policy.onnx --out data/crashes --tracks 1000-1019

Each placement is one run of the project's own recording session (carrt.session.run_session,
called with the config of what a user types):
`carrt teleop --sim --expert auto --record` for demonstrations (the scripted expert drives from
random places at rest, with the loop's noise injection half of the time so the recordings hold
recoveries), and `carrt drive --sim --autopilot --expert-intervene --record` for the next
iteration's data (the policy drives; the expert, playing the person with the pad, takes over
before a collision, and its commands label states the policy itself reached), and
`carrt drive --sim --autopilot --record` for a DIRL iteration's data (the policy drives alone;
every collision is labelled and followed by the auto-reset, the world model's crash examples).
Only episodes are training data, as on a real car; the simulator's saved trajectories
(sim-runs/) are for evaluation.

Runs go to a process pool (one process per core); a finished placement leaves a marker, so an
interrupted call resumes where it stopped. Each placement records into its own hidden staging
folder (`.partial-TRACK`) and is published into OUT only when it finished (renamed to
`.complete-TRACK`, its episodes moved in, the marker written: every step safe to repeat), so an
interrupted placement never leaves episodes beside the ones its rerun records. Ctrl-C, SIGINT or
SIGTERM (to the main process or the whole group) ends the call within seconds in one line: the
workers ignore the interrupt and are ended by the main process. Placements must not overlap
the evaluation ones (the `hard` layout's 100-199): `parse_tracks` refuses them.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import textwrap
from concurrent.futures import as_completed
from pathlib import Path

from tqdm import tqdm

from carrt.arg_types import finite_non_negative, finite_positive, parse_int_list
from carrt.episodes.format import write_json_atomic
from carrt.episodes.reader import list_episodes, read_episode
from carrt.errors import EXIT_USAGE, UserError
from carrt.session import DriveConfig
from carrt.sim.pool import worker_pool
from training.sim_placement import Job, publish, run_placement, staging_of

# Held out, never recorded for training: `carrt eval`'s default 100-104 and the study's
# evaluation placements 105-199 (research/README.md).
EVALUATION_TRACKS = frozenset(range(100, 200))
TASKS_PER_WORKER = 25  # placements a worker process runs before a fresh pool replaces it


EXIT_INTERRUPTED = 130  # the shell's code for a command ended by SIGINT


def parse_tracks(text: str) -> list[int]:
    """'1000-1149' or '1,2,5-7' → sorted unique placement seeds, never an evaluation one."""
    tracks = sorted(set(parse_int_list(text, "tracks")))
    held_out = sorted(set(tracks) & EVALUATION_TRACKS)
    if held_out:
        raise UserError(f"placements {held_out} are held out for evaluation: not for training")
    return tracks


def layout_for(index: int, layouts: list[str]) -> str:
    """Placements take the layouts in turn, so each layout gets every kind of seed."""
    return layouts[index % len(layouts)]


def demo_jobs(
    out: Path,
    tracks: list[int],
    layouts: list[str],
    episodes: int,
    noise: float = 0.0,
    noise_tau: float = 0.0,
) -> list[Job]:
    """noise: σ of Gaussian noise on every expert command (the paper's imperfect demonstrator);
    noise_tau: how long its error lasts (s; 0: fresh every command)."""
    jobs = []
    for i, track in enumerate(tracks):
        layout = layout_for(i, layouts)
        drive = DriveConfig(
            rig="sim", expert=True, record=True, random_start=True, expert_noise=noise,
            expert_noise_tau=noise_tau, seed=track, layout=layout, track_seed=track,
            episodes=episodes, laps=1, out=str(staging_of(out, track)), duration=100000.0,
        )  # fmt: skip
        jobs.append(Job(drive, out / "logs" / f"{layout}-{track}.log", out / f".done-{track}",
                        out, track))  # fmt: skip
    return jobs


def drive_jobs(
    out: Path,
    model: Path,
    tracks: list[int],
    layouts: list[str],
    seconds: float,
    *,
    intervene: bool,
    explore: bool = False,
    sets: tuple[str, ...] = (),
    noise: float = 0.0,
    noise_tau: float = 0.0,
    seed_offset: int = 0,
) -> list[Job]:
    """The policy drives each placement; with `intervene` the expert takes over before a crash,
    without it every crash is recorded (labelled, then the auto-reset) for the world model.
    `explore`: the loop's noise injection perturbs the policy's commands too (noise.during_auto),
    so the crashes and near misses come from varied actions, not only the policy's own.
    `sets`: `carrt drive --set` car config overrides for every placement (noise.amplitude=0.8, …).
    `noise`: σ on the expert's take-over commands (the robustness setting's imperfect person),
    `noise_tau`: how long its error lasts.
    `seed_offset`: added to each placement's simulator seed (noise, starts, camera phase), so a
    later iteration whose policy is unchanged still drives new episodes, not the same ones."""
    jobs = []
    overrides = (("noise.during_auto=true",) if explore else ()) + tuple(sets)
    for i, track in enumerate(tracks):
        layout = layout_for(i, layouts)
        drive = DriveConfig(
            model=str(model), rig="sim", autopilot=True, expert_intervene=intervene,
            # the person's noise is on their take-overs: no person, no noise of theirs
            expert_noise=noise if intervene else 0.0,
            expert_noise_tau=noise_tau if intervene else 0.0,
            sets=overrides, record=True, seed=track + seed_offset, layout=layout,
            track_seed=track, out=str(staging_of(out, track)), duration=float(seconds),
        )  # fmt: skip
        jobs.append(Job(drive, out / "logs" / f"{layout}-{track}.log", out / f".done-{track}",
                        out, track))  # fmt: skip
    return jobs


PERSON = "person.json"  # in OUT: the simulated person's noise its placements were recorded with


def same_person(out: Path, noise: float, noise_tau: float) -> None:
    """Refuse to resume OUT with another person: finished placements are skipped on resume, so
    a different --noise or --noise-tau would mix two demonstrators' recordings under one name.
    OUT/person.json says who recorded it; an OUT with finished placements and no person.json
    was recorded before --noise-tau existed (τ 0), with a σ it does not say (not checked)."""
    path = out / PERSON
    mine = {"noise": noise, "noise_tau": noise_tau}
    if path.is_file():
        try:
            theirs = json.loads(path.read_text())
            theirs = {"noise": float(theirs["noise"]), "noise_tau": float(theirs["noise_tau"])}
        except (ValueError, KeyError, TypeError):
            raise UserError(f"{path}: not a person record (noise, noise_tau)") from None
    else:
        theirs = {"noise": noise, "noise_tau": 0.0} if any(out.glob(".done-*")) else mine
    if theirs != mine:
        raise UserError(
            f"{out} was recorded with --noise {theirs['noise']:g} --noise-tau "
            f"{theirs['noise_tau']:g}, not {noise:g} and {noise_tau:g}: use another --out"
        )
    write_json_atomic(path, mine)  # a kill mid-write leaves the old file or none, never half


class Interrupted(Exception):
    """Ctrl-C, SIGINT or SIGTERM: the call ends, the finished placements kept."""


def _interrupt(signum, frame) -> None:
    raise Interrupted(signal.Signals(signum).name)


def run_jobs(jobs: list[Job], jobs_at_once: int, what: str) -> None:
    """Every job not yet done, `jobs_at_once` processes at a time, with a progress bar; a
    failed placement is named with its log and ends the call (the rest keep their markers)."""
    for job in jobs:  # a placement whose publication was interrupted: finish it
        if not job.marker.exists() and job.complete.exists():
            publish(job)
    todo = [job for job in jobs if not job.marker.exists()]
    if not todo:
        return
    # carrt/sim/pool.py: an executor whose workers use one math thread each. A fresh executor
    # per chunk of TASKS_PER_WORKER tasks per worker bounds what a long-lived worker
    # accumulates; not max_tasks_per_child, with which CPython 3.11/3.12 hangs once every
    # worker has retired (CPython gh-115634: the call waited forever after 100 placements).
    failed: list[tuple[Job, int]] = []
    bar = tqdm(total=len(jobs), initial=len(jobs) - len(todo), desc=what, unit="placement")
    chunk = jobs_at_once * TASKS_PER_WORKER
    for first in range(0, len(todo), chunk):
        pool = worker_pool(jobs_at_once, "forkserver", ignore_interrupts=True)
        try:
            futures = [pool.submit(run_placement, job) for job in todo[first : first + chunk]]
            for future in as_completed(futures):
                job, code = future.result()
                bar.update()
                if code != 0:
                    failed.append((job, code))
        except (KeyboardInterrupt, Interrupted):
            bar.close()
            end_workers(pool)
            done = sum(job.marker.exists() for job in jobs)
            raise Interrupted(f"{done} of {len(jobs)} placements done") from None
        pool.shutdown()
    bar.close()
    if failed:
        job, code = failed[0]
        raise UserError(f"{len(failed)} placement(s) failed, e.g. exit {code}: see {job.log}")


def end_workers(pool) -> None:
    """Cancel what has not started and end the running workers now (they ignore SIGINT): their
    placements' staging folders are removed when they run again."""
    processes = list(getattr(pool, "_processes", {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        process.terminate()
    for process in processes:
        process.join(timeout=5.0)


def count_frames(*dirs: Path) -> int:
    return sum(read_episode(p).n for p in list_episodes([str(d) for d in dirs]))


# What each subcommand records, and an example: `carrt-sim-data <what> --help`.
SUBCOMMANDS = {
    "demos": (
        "Demonstrations: the scripted expert drives each placement from random places at rest, "
        "with the loop's noise injection half of the time (recoveries), recorded as a person's "
        "`carrt teleop --record` would be. The data of imitation (the first policy).",
        "carrt-sim-data demos --out data/expert --tracks 1000-1019 --episodes 4 --jobs 2",
    ),
    "interventions": (
        "Take-over rounds: the policy drives; the expert takes over before a collision and its "
        "commands label the states the policy itself reached.",
        "carrt-sim-data interventions --model runs/iter1/policy.onnx --out data/takeovers1 "
        "--tracks 1000-1019",
    ),
    "drives": (
        "A DIRL iteration's data: the policy drives alone; every collision is labelled and "
        "followed by the auto-reset (the world model's crash examples).",
        "carrt-sim-data drives --model runs/iter1/policy.onnx --out data/drives1 "
        "--tracks 1000-1019",
    ),
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="carrt-sim-data", description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    sub = parser.add_subparsers(dest="what", required=True)
    for name in ("demos", "interventions", "drives"):
        what, example = SUBCOMMANDS[name]
        p = sub.add_parser(
            name, help=what.split(":")[0], description=textwrap.fill(what, 79),
            epilog=f"example:\n  {example}",
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )  # fmt: skip
        p.add_argument("--out", required=True, help="episode directory to fill")
        p.add_argument("--tracks", default="1000-1149", help="placement seeds (ranges, commas)")
        p.add_argument("--layouts", default="hard", help="comma list, taken in turn")
        p.add_argument("--jobs", type=int, default=2, help="processes (default: 2)")
        if name == "demos":
            p.add_argument("--episodes", type=int, default=8, help="episodes per placement")
        else:
            p.add_argument("--model", required=True, help="the policy that drives (.onnx)")
            p.add_argument(
                "--seconds", type=finite_positive, default=60.0, help="simulated s per placement"
            )
            p.add_argument(
                "--seed-offset", type=int, default=0,
                help="added to every placement's simulator seed (another drive, same placements)",
            )  # fmt: skip
        if name in ("demos", "interventions"):  # the expert drives: its commands get σ
            who = "the expert's commands" if name == "demos" else "the take-overs"
            p.add_argument("--noise", type=finite_non_negative, default=0.0, help=f"σ on {who}")
            p.add_argument(
                "--noise-tau", type=finite_non_negative, default=0.0, metavar="SECONDS",
                help="how long that error lasts (0: fresh every command)",
            )  # fmt: skip
        if name == "drives":
            p.add_argument(
                "--explore", action="store_true",
                help="noise injection on the policy's commands half of the time (varied actions)",
            )  # fmt: skip
            p.add_argument(
                "--set", action="append", default=[], metavar="KEY=VALUE", dest="sets",
                help="a `carrt drive --set` for every placement, e.g. noise.amplitude=0.8",
            )  # fmt: skip
    args = parser.parse_args(argv)
    previous = signal.signal(signal.SIGTERM, _interrupt)
    # Ctrl-C as KeyboardInterrupt even when started from a script that ignores SIGINT (a
    # background job of a shell without job control: Python then installs no handler of its own)
    previous_int = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        out = Path(args.out)
        tracks = parse_tracks(args.tracks)
        layouts = [x.strip() for x in args.layouts.split(",") if x.strip()]
        if args.what == "demos":
            jobs = demo_jobs(out, tracks, layouts, args.episodes, args.noise, args.noise_tau)
        else:
            if not Path(args.model).is_file():
                raise UserError(f"no such model: {args.model}")
            intervene = args.what == "interventions"
            jobs = drive_jobs(
                out, Path(args.model), tracks, layouts, args.seconds, intervene=intervene,
                explore=getattr(args, "explore", False), sets=tuple(getattr(args, "sets", ())),
                noise=getattr(args, "noise", 0.0), noise_tau=getattr(args, "noise_tau", 0.0),
                seed_offset=args.seed_offset,
            )  # fmt: skip
        out.mkdir(parents=True, exist_ok=True)
        if args.what in ("demos", "interventions"):
            same_person(out, args.noise, args.noise_tau)
        run_jobs(jobs, max(1, args.jobs), args.what)
        print(f"{out}: {count_frames(out):,} frames")
    except UserError as exc:
        print(f"sim_data: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except (KeyboardInterrupt, Interrupted) as exc:
        done = f": {exc}" if str(exc) and not str(exc).startswith("SIG") else ""
        print(f"sim_data: interrupted{done}; the same command resumes", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        signal.signal(signal.SIGTERM, previous)
        signal.signal(signal.SIGINT, previous_int)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
