"""The paper's Algorithm 1 end to end: imitate once, then N times world model → refine → drive.

    carrt-train --episodes demos/ --out runs/loop --iterations 3 --drive sim   # all in the sim
    carrt-train --episodes demos/ --out runs/loop --iterations 3               # with a real car
    carrt-train --episodes demos/ --out runs/iter1                             # one iteration

DIRL (Cai et al. 2021, Algorithm 1; DESIGN §2), as this file runs it:

    OUT/iter_0   imitation on the demonstrations (--episodes): the policy π₀
    for k = 1..N:
        OUT/iter_k          the world model learns ALL the data so far (continuing iter_{k-1}'s),
                            then π_{k-1} is refined in its imagination: π_k, exported to
                            OUT/iter_k/policy.onnx
        OUT/iter_k/drives   π_k drives and records (a collision ends an episode); these episodes
                            join the data of iteration k+1

`--drive sim`: the simulator drives each policy on --drive-tracks placements, in worker
processes of carrt's own recording command (training/sim_data.py: the drives never run in this
process, which holds torch). `--drive car` (the default): the script stops after exporting π_k
and prints the commands to drive and record it on the car; run the same command again once the
drives are in OUT/iter_k/drives and it goes on. Every step is resumable: a finished one is
skipped, a stopped training resumes from its checkpoint.

`--takeovers`: the take-over rounds of the paper's data loop. While π_k drives, the person (in
the simulator, the scripted expert) takes over before a crash; their commands label the states
the policy itself reached, and iteration k+1 learns them by imitation again (`reimitate`)
before its world model.

Without --iterations this is one iteration exactly as before (training/iteration.py): the flags
below the loop's, IterateConfig's numbers (training/config.py) and `--set` mean the same in both.
Exports run as a `python -m export` process (training/ never imports export/).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script (demo_policy, torchrun): make `training` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from carrt.episodes.reader import list_episodes
from carrt.errors import UserError
from training.config import IterateConfig, UsageError
from training.iteration import _Parser, add_iteration_args, config_from, guarded


class _Help(argparse.RawDescriptionHelpFormatter):
    """The examples as written in the docstring, the flags wrapped as usual."""


DRIVE_SEED_STRIDE = 100_000  # iteration k's drives: simulator seeds placement + stride·k
DONE = ".done"  # a finished step's marker, in its folder


def parse(argv: list[str] | None) -> tuple[argparse.Namespace, IterateConfig]:
    p = _Parser(
        prog="carrt-train", description=__doc__.split("\n")[0],
        epilog="examples:\n" + __doc__.split("\n\n")[1], formatter_class=_Help,
    )  # fmt: skip
    add_iteration_args(p)
    loop = p.add_argument_group("the loop (Algorithm 1; without --iterations: one iteration)")
    loop.add_argument("--iterations", type=int, metavar="N",
                      help="imitation into OUT/iter_0, then N × (world model → refinement → "
                      "the policy drives and records) into OUT/iter_1..N")  # fmt: skip
    loop.add_argument("--drive", choices=("car", "sim"), default="car",
                      help="who drives each policy: car (the loop stops and says how; "
                      "default) or sim (the simulator, in worker processes)")  # fmt: skip
    loop.add_argument("--takeovers", action="store_true",
                      help="take-over rounds: the driver takes over before a crash (sim: the "
                      "scripted expert) and the next iteration re-imitates first")  # fmt: skip
    loop.add_argument("--drive-tracks", default="1000-1009", metavar="SEEDS",
                      help="sim: training placements to drive (default: %(default)s)")  # fmt: skip
    loop.add_argument("--drive-layouts", default="hard", metavar="LIST",
                      help="sim: layouts, taken in turn (default: %(default)s)")  # fmt: skip
    loop.add_argument("--drive-seconds", type=float, default=60.0, metavar="S",
                      help="sim: simulated s per placement (default: %(default)s)")  # fmt: skip
    loop.add_argument("--jobs", type=int, default=2, help="sim: drives at once (default: 2)")
    a = p.parse_args(argv)
    cfg = config_from(a)
    if a.iterations is not None:
        if a.iterations < 1:
            raise UsageError(f"--iterations must be >= 1, got {a.iterations}")
        if a.init or a.world_episodes:
            raise UsageError("--iterations starts from the demonstrations: no --init or "
                             "--world-episodes")  # fmt: skip
        if not cfg.export:
            raise UsageError("--iterations drives the exported policy: export must stay on")
        if int(os.environ.get("WORLD_SIZE", "1")) > 1:
            raise UsageError("the loop runs in one process: torchrun one iteration at a time")
    return a, cfg


def main(argv: list[str] | None = None) -> int:
    try:
        a, cfg = parse(argv)
    except UserError as exc:
        print(f"carrt-train: error: {exc}", file=sys.stderr)
        return 2
    if a.iterations is None:  # carrt-train as it always was: one iteration
        return guarded(lambda: cfg)
    try:
        return loop(a, cfg)
    except UserError as exc:
        print(f"carrt-train: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("carrt-train: interrupted; run the same command to go on from there",
              file=sys.stderr)  # fmt: skip
        return 130


def loop(a: argparse.Namespace, cfg: IterateConfig) -> int:
    """Algorithm 1, top to bottom. Returns the exit status (0 also when it stops for the car)."""
    out = Path(cfg.out)
    demonstrations = list(cfg.episodes)

    # 1. Imitation, once: π₀ learns the person's demonstrations (no world model, no refinement).
    imitation = dataclasses.replace(cfg, out=str(out / "iter_0"), world_model_steps=0,
                                    refine_steps=0)  # fmt: skip
    finished, code = train(imitation, "imitation")
    if not finished:
        return code

    # 2. N iterations: world model on all data → refinement → π_k drives → its episodes join.
    data = list(demonstrations)
    for k in range(1, a.iterations + 1):
        here = out / f"iter_{k}"
        iteration = dataclasses.replace(
            cfg, out=str(here), init=str(out / f"iter_{k - 1}"), episodes=tuple(data),
            reimitate=cfg.reimitate or (a.takeovers and k > 1),
        )  # fmt: skip
        finished, code = train(iteration, f"iteration {k}: world model → refinement")
        if not finished:
            return code
        drives = here / "drives"
        if a.drive == "sim":
            drive_in_simulator(a, here / "policy.onnx", drives, k)
        elif not driven(drives):
            tell_the_person(a, here, drives, k)
            return 0
        data.append(str(drives))

    last = out / f"iter_{a.iterations}"
    print(f"carrt-train: {a.iterations} iteration(s) done; the policy: {last / 'policy.onnx'}; "
          f"report: {last / 'report.md'}. Run again with --iterations {a.iterations + 1} to "
          "go on.")  # fmt: skip
    return 0


def train(cfg: IterateConfig, what: str) -> tuple[bool, int]:
    """One iteration into cfg.out (training/iteration.py), skipped when it already finished; a
    stopped one resumes from its checkpoints. (finished, exit status)."""
    folder = Path(cfg.out)
    if (folder / DONE).is_file():
        print(f"carrt-train: {folder}: {what} (done)")
        return True, 0
    print(f"carrt-train: {folder}: {what}", flush=True)
    code = guarded(lambda: cfg)
    finished = code == 0 and (folder / "policy.onnx").is_file()  # not when stop_after stopped it
    if finished:
        (folder / DONE).touch()
    return finished, code


def drive_in_simulator(a: argparse.Namespace, model: Path, drives: Path, k: int) -> None:
    """π_k drives the training placements in the simulator and records, as a user's `carrt
    drive --sim --autopilot --record` would (with --takeovers the scripted expert takes over
    before a crash). The drives run in worker processes (training/sim_data.py)."""
    from training.sim_data import drive_jobs, parse_tracks, run_jobs

    if (drives / DONE).is_file():
        print(f"carrt-train: {drives}: drives (done)")
        return
    layouts = [x.strip() for x in a.drive_layouts.split(",") if x.strip()]
    jobs = drive_jobs(
        drives, model, parse_tracks(a.drive_tracks), layouts, a.drive_seconds,
        intervene=a.takeovers, seed_offset=DRIVE_SEED_STRIDE * k,
    )  # fmt: skip
    print(f"carrt-train: {drives}: π_{k} drives {len(jobs)} placement(s) in the simulator",
          flush=True)  # fmt: skip
    run_jobs(jobs, max(1, a.jobs), f"drives {k}")
    (drives / DONE).touch()


def driven(drives: Path) -> bool:
    """Whether the person has put π_k's recorded episodes into `drives`."""
    try:
        return bool(list_episodes([str(drives)]))
    except UserError:  # no such folder, or nothing recorded in it yet
        return False


def tell_the_person(a: argparse.Namespace, here: Path, drives: Path, k: int) -> None:
    """The car's turn: how to drive π_k and where its episodes go for the run to go on."""
    take_over = (" Take over with the stick before a crash: your commands label the states the "
                 "policy reached.") if a.takeovers else ""  # fmt: skip
    print(
        f"carrt-train: iteration {k} is trained and exported: {here / 'policy.onnx'}\n"
        f"  1. copy it to the car and drive it there, recording (a collision or e-stop ends an "
        f"episode):{take_over}\n"
        f"       carrt drive --model policy.onnx --config car.toml --record --out drives_{k}\n"
        f"  2. copy the recorded episodes (drives_{k}/) into {drives}/\n"
        f"  3. run this same command again: iteration {k + 1} learns from them"
    )


if __name__ == "__main__":
    sys.exit(main())
