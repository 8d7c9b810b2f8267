"""carrt-train: imitation and take-over rounds, one iteration or the loop (--dirl: + refinement).

The world model and refinement in it run only when asked (--dirl), beside the imitated policy.

    carrt-train --episodes demos/ --out runs/iter1                               # one iteration
    carrt-train --episodes demos/ drives1/ --out runs/iter2 --init runs/iter1    # a take-over round
    carrt-train --episodes demos/ --out runs/iter1 --dirl                        # + OUT/refined/
    carrt-train --episodes demos/ --out runs/loop --iterations 3 --drive sim     # all in the sim
    carrt-train --episodes demos/ --out runs/loop --iterations 3                 # with a real car

One iteration is imitation (training/training_run.py without `dirl`): from scratch, or with --init
from the previous policy on every labelled frame given, the person's take-overs in the new drives
included (a take-over round: reimitation_steps at reimitation_lr, the setting the rounds were
measured with). That is what has made driving better: three rounds +0.057 ± 0.031 completion
against imitation at equal frames (research/README.md row 2).

--dirl adds the paper's world-model half, which has not been shown to make driving better
(DIRL_MEASURED below; research/README.md rows 3-7). After the iteration, OUT/refined/ is a second
run from OUT's policy: a world model learns every episode given (from its own initialisation),
the policy is refined in its imagination and exported to OUT/refined/policy.onnx. OUT/policy.onnx
stays the imitated policy, byte for byte what the run without --dirl writes, and OUT/report.md
says how far refinement moved the plan (|Δμ| on held-out frames). The status line is printed
once per command.

--iterations N, the paper's Algorithm 1 with the take-overs every real drive has:

    OUT/iter_0                imitation on the demonstrations (--episodes): π₀
    for k = 1..N:
        OUT/iter_{k-1}/drives π_{k-1} drives and records; the person takes over before a crash
                              (in the simulator the scripted expert), labelling the states the
                              policy itself reached
        OUT/iter_k            π_{k-1} imitates again on all the data so far: π_k
        π_k against π_{k-1}   --drive sim: both drive the validation placements (carrt eval;
                              the paper's metrics, paired over the runs, printed and in
                              OUT/iter_k/report.md); --drive car: the report says how to compare
                              them from their recorded drives (carrt report)
    With --dirl every iteration also has OUT/iter_k/refined/ (in the simulator driven against
    OUT/iter_k too); the loop goes on from the imitated policies.

`--drive sim` drives in worker processes of carrt's own commands (training/sim_data.py and
`carrt eval` processes: the simulator never runs in this process, which holds torch). `--drive
car` (the default) stops when a policy's drives are missing and prints how to drive and record
it on the car; run the same command again once they are in OUT/iter_k/drives. Every step is
resumable: a finished one is skipped, a stopped training resumes from its checkpoint. The flags
of one iteration, TrainingConfig's numbers (training/config.py) and `--set` mean the same in
both. Exports run as a `python -m export` process (training/ never imports export/).
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
from training.compare import DriveFailed, DriveSpec
from training.config import TrainingConfig, UsageError
from training.loop_config import TrainingLoopConfig, add_loop_args, loop_config
from training.loop_config import save as save_loop_config
from training.one_run import run_iteration
from training.training_args import Parser, add_iteration_args, config_from


class _Help(argparse.RawDescriptionHelpFormatter):
    """The examples as written in the docstring, the flags wrapped as usual."""


DRIVE_SEED_STRIDE = 100_000  # π_k's drives: simulator seeds placement + stride·k
DONE = ".done"  # a finished step's marker, in its folder
REFINED = "refined"  # --dirl's run, inside the iteration's folder

# What the world model and refinement were measured to do in the simulator: the refined policy
# against the one refinement started from, completion, mean ± std over seeds, as
# `python -m research.paired_table FILE --sigma σ --pair MODEL:AGAINST` prints it from the
# committed results file (tests/test_train_iterate.py checks each against the file).
DIRL_MEASURED = (
    ("on clean demonstrations, every seed worse", "research/results/dirl_at_il_data.json.gz",
     "IL+refined:IL", 0.0, "-0.040 ± 0.005"),
    ("after three take-over rounds", "research/results/dirl_takeover_check.json.gz",
     "takeovers3+refined:takeovers3", 0.0, "-0.022 ± 0.025"),
    ("only with a person whose errors last",
     "research/results/takeover_tau05_sigma0.5_5seeds.json.gz", "takeovers2+refined:takeovers2",
     0.5, "+0.038 ± 0.009"),
)  # fmt: skip
DIRL_STATUS = (
    "--dirl: the world model and refinement are not validated: in the simulator the refined "
    "policy against the one it started from, completion "
    + ", ".join(f"{value} {what} ({Path(path).name})" for what, path, _, _, value in DIRL_MEASURED)
    + " (research/results/); the refined policy goes into refined/, beside the imitated "
    "policy.onnx, never over it"
)


def parse(argv: list[str] | None) -> tuple[argparse.Namespace, TrainingConfig]:
    p = Parser(
        prog="carrt-train", description=__doc__.split("\n")[0],
        epilog="examples:\n" + __doc__.split("\n\n")[2], formatter_class=_Help,
    )  # fmt: skip
    add_iteration_args(p)
    p.add_argument("--dirl", action="store_true",
                   help="also the world model and refinement in it (not validated: the status "
                   "line says what was measured), into OUT/refined/ beside the imitated "
                   "policy")  # fmt: skip
    add_loop_args(p.add_argument_group(TrainingLoopConfig.GROUPS[0][0]))
    a = p.parse_args(argv)
    cfg = config_from(a)
    if a.world_episodes and not a.dirl:
        raise UsageError("--world-episodes is what the world model learns: it needs --dirl")
    if a.world_episodes:  # read by --dirl's run, after the iteration: refused before it
        from training.stage_data import read_world_episodes

        read_world_episodes(cfg)
    if a.no_uncertainty and not a.dirl:
        raise UsageError("--no-uncertainty is refinement's (the -unc ablation): it needs --dirl")
    if a.dirl and int(os.environ.get("WORLD_SIZE", "1")) > 1:
        raise UsageError("--dirl runs its two runs in one process: not under torchrun "
                         "(torchrun the iteration, then run it again with --dirl)")  # fmt: skip
    if a.iterations is not None:
        settings = loop_config(a)  # each flag against its declaration (training/loop_config.py)
        if a.init or a.world_episodes:
            raise UsageError("--iterations starts from the demonstrations: no --init or "
                             "--world-episodes")  # fmt: skip
        if not cfg.export:
            raise UsageError("--iterations drives the exported policy: export must stay on")
        if int(os.environ.get("WORLD_SIZE", "1")) > 1:
            raise UsageError("the loop runs in one process: torchrun one iteration at a time")
        check_drives(a)
        save_loop_config(settings, cfg.out)  # OUT/training_loop.json: how this loop drives
    return a, cfg


def check_drives(a: argparse.Namespace) -> None:
    """The loop's placements: training drives never on the test placements (parse_tracks) nor
    on the validation ones the comparison drives."""
    from training.sim_data import parse_tracks

    spec = drive_spec(a)
    spec.check()
    shared = sorted(set(parse_tracks(a.drive_tracks)) & set(spec.config()["tracks"]))
    if shared:
        raise UsageError(f"--drive-tracks and --compare-tracks share placement {shared[0]}: the "
                         "comparison drives placements no data came from")  # fmt: skip


def drive_spec(a: argparse.Namespace) -> DriveSpec:
    return DriveSpec(a.compare_tracks, a.compare_seconds, a.compare_seeds, a.jobs)


def main(argv: list[str] | None = None) -> int:
    try:
        a, cfg = parse(argv)
    except UserError as exc:
        print(f"carrt-train: error: {exc}", file=sys.stderr)
        return 2
    if a.dirl:
        print(f"carrt-train: {DIRL_STATUS}", flush=True)
    try:
        if a.iterations is None:
            return one_iteration(a, cfg)
        return loop(a, cfg)
    except UserError as exc:
        print(f"carrt-train: error: {exc}", file=sys.stderr)
        return 2
    except DriveFailed as exc:
        print(f"carrt-train: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("carrt-train: interrupted; run the same command to go on from there",
              file=sys.stderr)  # fmt: skip
        return 130


def imitation_config(cfg: TrainingConfig) -> TrainingConfig:
    """An iteration's run: imitation alone; with --init a take-over round, the previous policy
    fine-tuned (reimitation_steps at reimitation_lr) on every labelled frame given."""
    cfg = dataclasses.replace(cfg, world_episodes=(), dirl=False)
    if cfg.init:
        cfg = dataclasses.replace(
            cfg, imitation_steps=cfg.reimitation_steps, imitation_lr=cfg.reimitation_lr
        )
    return cfg


def dirl_config(cfg: TrainingConfig) -> TrainingConfig:
    """--dirl's run, OUT/refined/: from OUT's policy (and its input scaling), a world model of
    every episode given (--world-episodes' when given) from its own initialisation, then
    refinement in it; no imitation again."""
    out = Path(cfg.out)
    return dataclasses.replace(cfg, out=str(out / REFINED), init=str(out), dirl=True,
                               reimitate=False)  # fmt: skip


def one_iteration(a: argparse.Namespace, cfg: TrainingConfig) -> int:
    """carrt-train without --iterations: the iteration, then with --dirl its refined run."""
    code, done = run_iteration(imitation_config(cfg))
    if not (done and a.dirl):
        return code
    code, done = run_iteration(dirl_config(cfg))
    if done:
        describe_refinement(cfg)
    return code


def describe_refinement(cfg: TrainingConfig) -> None:
    """OUT/report.md and metrics.json ("refined") say where the refined policy is, the status,
    and how far refinement moved the plan on held-out frames; one line says so."""
    from training.compare import change_line, plan_change
    from training.run_report import add_section

    out = Path(cfg.out)
    refined = out / REFINED
    change = plan_change(cfg, out / "policy.pt", refined / "policy.pt")
    model = refined / ("policy.onnx" if (refined / "policy.onnx").is_file() else "policy.pt")
    lines = [
        "## The world model and refinement (--dirl)",
        "",
        DIRL_STATUS.replace("--dirl: the", "The", 1) + ".",
        "",
        f"- the refined policy: `{model.relative_to(out)}`; its run, with the world model's "
        f"held-out metrics: [{REFINED}/report.md]({REFINED}/report.md). `policy.pt` and "
        "`policy.onnx` here are the imitated policy, as a run without --dirl writes them.",
        f"- what refinement changed: {change_line(change)}.",
        "- whether that drives better is not known from it: drive both on validation "
        "placements (`carrt-train --iterations … --drive sim` does; by hand `carrt eval` "
        "with `--tracks 200-219`), or on the car and compare their drives with `carrt report`.",
    ]
    add_section(out, "refined", {"model": str(model), **change}, lines)
    print(f"carrt-train: refinement moved the plan: {change_line(change)}; the refined policy: "
          f"{model}, the imitated one stays {out / 'policy.onnx'}")  # fmt: skip


def loop(a: argparse.Namespace, cfg: TrainingConfig) -> int:
    """Algorithm 1, top to bottom. Returns the exit status (0 also when it stops for the car)."""
    out = Path(cfg.out)
    data = list(cfg.episodes)
    previous: Path | None = None
    for k in range(a.iterations + 1):
        here = out / f"iter_{k}"
        if previous is not None:  # π_{k-1} drives; its episodes join the data
            drives = previous / "drives"
            if a.drive == "sim":
                drive_in_simulator(a, previous / "policy.onnx", drives, k - 1)
            elif not driven(drives):
                tell_the_person(previous, drives, k - 1)
                return 0
            data.append(str(drives))
        iteration = dataclasses.replace(
            cfg, out=str(here), episodes=tuple(data), init=str(previous) if previous else None
        )
        what = "imitation" if previous is None else f"take-over round {k}: imitation again"
        runs = [(imitation_config(iteration), what)]
        if a.dirl:
            runs.append((dirl_config(iteration), "world model → refinement (--dirl)"))
        for run, what in runs:  # each skipped once finished; a stopped one resumes
            folder = Path(run.out)
            if (folder / DONE).is_file():
                print(f"carrt-train: {folder}: {what} (done)")
                continue
            print(f"carrt-train: {folder}: {what}", flush=True)
            code, finished = run_iteration(run)
            if not (finished and (folder / "policy.onnx").is_file()):
                return code
            if run.dirl:
                describe_refinement(iteration)
            (folder / DONE).touch()
        compare(a, here, previous, k)
        previous = here
    last = out / f"iter_{a.iterations}"
    print(f"carrt-train: {a.iterations} iteration(s) done; the policy: {last / 'policy.onnx'}; "
          f"report: {last / 'report.md'}. Run again with --iterations {a.iterations + 1} to "
          "go on.")  # fmt: skip
    return 0


def drive_in_simulator(a: argparse.Namespace, model: Path, drives: Path, k: int) -> None:
    """π_k drives the training placements in the simulator and records while the scripted
    expert takes over before a crash, as a user's `carrt drive --sim --autopilot
    --expert-intervene --record` would. The drives run in worker processes (sim_data.py)."""
    from training.sim_data import drive_jobs, parse_tracks, run_jobs

    if (drives / DONE).is_file():
        print(f"carrt-train: {drives}: drives (done)")
        return
    layouts = [x.strip() for x in a.drive_layouts.split(",") if x.strip()]
    jobs = drive_jobs(
        drives, model, parse_tracks(a.drive_tracks), layouts, a.drive_seconds,
        intervene=True, seed_offset=DRIVE_SEED_STRIDE * k,
    )  # fmt: skip
    print(f"carrt-train: {drives}: π_{k} drives {len(jobs)} placement(s) in the simulator, the "
          "expert taking over before a crash", flush=True)  # fmt: skip
    run_jobs(jobs, max(1, a.jobs), f"drives {k}")
    (drives / DONE).touch()


def driven(drives: Path) -> bool:
    """Whether the person has put π_k's recorded episodes into `drives`."""
    try:
        return bool(list_episodes([str(drives)]))
    except UserError:  # no such folder, or nothing recorded in it yet
        return False


def tell_the_person(here: Path, drives: Path, k: int) -> None:
    """The car's turn: how to drive π_k and where its episodes go for the run to go on."""
    print(
        f"carrt-train: iteration {k}'s policy is trained and exported: {here / 'policy.onnx'}\n"
        f"  1. copy it to the car and drive it there, recording (a collision or e-stop ends an "
        f"episode); take over with the stick before a crash: your commands label the states "
        f"the policy reached:\n"
        f"       carrt drive --model policy.onnx --config car.toml --record --out drives_{k}\n"
        f"  2. copy the recorded episodes (drives_{k}/) into {drives}/\n"
        f"  3. run this same command again: iteration {k + 1} imitates them too"
    )


def compare(a: argparse.Namespace, here: Path, previous: Path | None, k: int) -> None:
    """π_k against π_{k-1} (and with --dirl the refined policy against its start), in
    iteration k's report and printed: driven on the validation placements in the simulator; on
    the car, how to compare their recorded drives."""
    from training.run_report import add_section

    if a.drive == "car":
        if previous is None:
            return
        lines = [
            "## Against the previous iteration (on the car)",
            "",
            f"This policy and π_{k - 1} are compared on the car from their recorded drives: "
            f"`carrt report {previous / 'drives'}` is π_{k - 1}'s, and once you have driven "
            f"this one, `carrt report {here / 'drives'}` is its (laps per minute of driving, "
            "average speed, take-overs, collisions; lap times from the lap marks).",
        ]
        add_section(here, "against_previous", {"on": "car"}, lines)
        print(f"carrt-train: compare π_{k} with π_{k - 1} from their drives on the car: carrt "
              f"report {previous / 'drives'}, and carrt report {here / 'drives'} once you have "
              f"driven π_{k}")  # fmt: skip
        return
    spec = drive_spec(a)
    if previous is not None:
        driven_against(spec, here, here, previous, f"π_{k}", f"π_{k - 1}", "against_previous",
                       "## Against the previous iteration, driven (simulator)")  # fmt: skip
    if a.dirl:
        heading = "## The refined policy against the imitated one, driven (simulator)"
        driven_against(spec, here, here / REFINED, here, f"π_{k} refined", f"π_{k}",
                       "refined_driven", heading)  # fmt: skip


def driven_against(spec: DriveSpec, report: Path, new: Path, old: Path, new_name: str,
                   old_name: str, key: str, heading: str) -> None:  # fmt: skip
    """Both runs' policies drive spec's validation runs (each kept in its validation.json);
    the paired table goes into `report`'s report.md under `heading` and is printed."""
    from training.compare import VALIDATION_FILE, drive_validation, paired, summary, table
    from training.run_report import add_section

    print(f"carrt-train: {new_name} and {old_name} drive {spec.where()}", flush=True)
    results = {}
    for run in (old, new):
        results[run] = drive_validation(run / "policy.onnx", run, spec)
    p = paired(results[new], results[old])
    line = summary(new_name, old_name, p, spec)
    rows = table(new_name, old_name, p)
    kept = [f"`{os.path.relpath(run / VALIDATION_FILE, report)}`" for run in (old, new)]
    lines = [heading, "", line + ".", "", *rows, "",
             f"Each run of both: {' and '.join(kept)} (`{' '.join(spec.command('policy.onnx'))}`; "
             "the test placements 100-199 are never driven here)."]  # fmt: skip
    add_section(report, key, p, lines)
    print(f"carrt-train: {line}")
    print("\n".join(rows), flush=True)


if __name__ == "__main__":
    sys.exit(main())
