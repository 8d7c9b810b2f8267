"""The paper's simulation study on carrt's simulator: imitation learning against DIRL, at scale.

    python -m research.dirl_sim                        # the study (make study; ~9 h, 2 cores)
    python -m research.dirl_sim --quick                # every step, tiny profile, minutes
    python -m research.dirl_sim --set seeds=0,1,2 --set iterations=3

Top to bottom, every step one of the project's own commands (logged under OUT/logs):

1. Demonstrations (`carrt-sim-data demos`): the scripted expert on the TRAINING
   placements, both cores, from random places at rest with the loop's noise injection half of
   the time; for the robustness setting the same again with Gaussian noise of σ 0.5 and 1.0 on
   every expert command (the paper's imperfect demonstrator). A second pool of demonstrations on
   other placements gives imitation as many frames as DIRL's iterations add.
2. IL: iterate.py with imitation only.
3. DIRL iteration k: the previous policy drives placements of its own alone (iteration_tracks)
   (`sim_data drives`: auto-reset after every collision, each crash labelled: the world model's
   collision examples, which the demonstrations hardly hold), then again with the expert
   playing the person who takes over before a crash (`sim_data interventions`, with the
   demonstrations' σ: the override every real-car drive has; its commands label states the
   policy itself reached); the episodes join the data. iterate.py --init first trains the
   previous policy further by imitation on every labelled frame (`reimitate`, the take-overs
   included), continues the world model on all of it, refines the policy in imagination
   and scores the world model against the simulator (research/variants/counterfactual.py, placements
   200-204, never the evaluation ones). Refinement keeps a candidate every 100 steps; each, the
   policy imitation made and the policy the iteration started from are driven on validation
   placements (200-219, 220-239, 240-259 for iterations 1-3); the policy imitation made is kept
   unless a candidate beats it by two standard errors of the paired difference
   (research/variants/select_by_driving.py; select_by_driving=false: the last step's). The policy
   imitation made is also evaluated as its own row ("before refinement"): what refinement adds
   beyond the take-overs.
   takeover_seconds=0 reimitate_steps=0 is the paper's iteration (imitation once, drives
   without a person). Iteration 1 is refined by the world model's gradient, later ones by
   search in its imagination (refine_search, search_from). DIRL -unc: each σ 0 iteration's
   world model and imitated policy, refinement without the uncertainty term, chosen the same
   way; "DIRL search iter 1": iteration 1 refined by search instead.
4. IL at equal frames, once per DIRL iteration k: imitation on the demonstrations plus as many
   frames from the second pool as iterations 1..k's drives added, so every DIRL row is compared
   with imitation on (at least) as many frames as it had.
5. Every policy is driven by `carrt eval` on HELD-OUT placements (100-199 of the `hard` layout,
   never recorded for training), 30 simulated seconds each with auto-reset: the paper's metrics.
   (The runs until 2026-11-25 drove 100-124 × 60 s; `python -m research.redrive` drives a finished
   study's policies again on 100-199.)

Output: OUT/results.json (a row per model, seed and noise, with its runs and its world model's
counterfactual numbers), OUT/table.md (mean ± std over seeds × placements) and
OUT/completion_vs_frames.png. Every finished step is skipped when the study runs again, so an
interrupted study continues where it stopped; progress and an ETA are printed as steps finish.
After the demonstrations, the chains (one per noise and seed) run side by side, `parallel` steps
at once (research/study_steps.py); selections and evaluations reuse the numbers of weights they have
already driven (identical bytes drive identical laps).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # run as a file, from any directory: the repository on the path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.provenance import environment, recorded
from carrt.errors import UserError
from carrt.settings import apply_sets
from research.dirl_steps import (
    ROOT,
    ablations,
    evaluate,
    every_noise_demonstrations,
    frames_in,
    il_equal_data,
    iterate_cmd,
    iteration_drives,
    plan,
    refinement_method,
    reimitate_flags,
    run_settings,
    select,
)
from research.dirl_table import (
    before_refinement,
    comparison,
    il_at_frames_of,
    plot,
    table,
)
from research.paths import outs_at_root
from research.study_config import QUICK, StudyConfig, range_problems
from research.study_steps import StudyStep, finished_steps, run_chains


def chain(
    cfg: StudyConfig,
    step: StudyStep,
    sigma: float,
    seed: int,
    iterations: int,
    rows: list[dict],
) -> None:
    """IL → DIRL 1 (and -unc at σ = 0) → IL at iteration 1's frames → DIRL 2 → … for one noise
    and one seed; each model's row is appended to `rows` as it is evaluated."""
    tag = f"noise{sigma:g}-seed{seed}"
    runs = Path(cfg.out) / "runs" / tag
    expert = Path(cfg.out) / "data" / f"expert-noise{sigma:g}"
    extra = Path(cfg.out) / "data" / f"extra-noise{sigma:g}"
    every = cfg.refine_candidates_every if cfg.select_by_driving else 0  # candidates kept
    common = run_settings(cfg, seed, every)
    imitation = ["--set", f"imitation_steps={cfg.imitation_steps}",
                 "--set", "world_model_steps=0", "--set", "refine_steps=0"]  # fmt: skip

    evaluated: dict[str, Path] = {}  # sha256 of policy.pt → the first eval.json with it

    def row(model: str, iteration: int, run: Path, data: list[Path], policy: Path | None = None,
            candidate: str | None = None, refinement: str | None = None):  # fmt: skip
        """Evaluate and record one model: the run's policy, the one chosen by driving (`policy`)
        or one of its selection's candidates (`candidate`: its name there); `refinement`:
        "gradient" or "search" for a refined row."""
        from carrt.policy import file_sha256

        policy = policy or run
        if candidate:
            selection = json.loads((policy / "selection.json").read_text())
            entry = next(c for c in selection["candidates"] if c["name"] == candidate)
            pt, onnx = Path(entry["checkpoint"]), policy / "candidates" / f"{candidate}.onnx"
            result, chosen = run / f"eval-{candidate}.json", None
        else:
            pt, onnx, result = policy / "policy.pt", policy / "policy.onnx", run / "eval.json"
            selection = policy / "selection.json"
            chosen = json.loads(selection.read_text())["chosen"] if selection.is_file() else None
        digest = file_sha256(pt)
        same_as = evaluated.get(digest)
        evaluated.setdefault(digest, result)
        suffix = f"-{candidate}" if candidate else ""
        out = evaluate(cfg, step, f"{tag}-{run.name}{suffix}", onnx, result, same_as)
        metrics = json.loads((run / "metrics.json").read_text())
        rows.append({
            "model": model, "iteration": iteration, "demo_noise": sigma, "seed": seed,
            "frames": frames_in(data), "run": str(run), "policy": str(onnx),
            "aggregate": out["aggregate"],
            "runs": out["runs"], "counterfactual": metrics.get("counterfactual"),
            "chosen": chosen, "same_weights_as": same_as and str(same_as.parent),
            "refinement": refinement,
        })  # fmt: skip
        agg = out["aggregate"]
        print(f"  [{tag}] {model}: completion {agg['completion_ratio']['mean']:.2f}, "
              f"{agg['collisions_per_min']['mean']:.1f} collisions/min"
              + (f" (chosen by driving: {chosen})" if chosen else ""), flush=True)  # fmt: skip

    il = runs / "il"
    step(f"train-{tag}-il", iterate_cmd(cfg, [expert], il, *common, *imitation), il / ".done")
    row("IL", 0, il, [expert])
    data, previous = [expert], il
    expert_frames = frames_in([expert])  # read once: every iteration tops up against it
    reimitate, again = cfg.reimitate_steps > 0, reimitate_flags(cfg)
    for k in range(1, iterations + 1):
        data = [*data, *iteration_drives(cfg, step, tag, sigma, k, previous)]
        run = runs / f"dirl{k}"
        wm_steps = cfg.world_model_steps if k == 1 else cfg.world_model_steps_next
        settings = run_settings(cfg, seed, every, iteration=k)
        step(f"train-{tag}-dirl{k}", iterate_cmd(cfg, data, run, *settings, "--init",
             str(previous), *again, "--set", f"world_model_steps={wm_steps}",
             "--set", f"refine_steps={cfg.refine_steps}"), run / ".done")  # fmt: skip
        imitated = run / "checkpoints" / "imitation.pt" if reimitate else None
        policy = select(cfg, step, f"{tag}-dirl{k}", k, run, previous, data, imitated)
        method = refinement_method(cfg, k)
        row(f"DIRL iter {k}", k, run, data, policy, refinement=method)
        if imitated and cfg.select_by_driving:
            row(before_refinement(k), k, run, data, policy, candidate="imitated")
        if sigma == 0:
            for name, model, flags, alt_method in ablations(cfg, k):
                alt = runs / name
                step(f"train-{tag}-{name}", iterate_cmd(cfg, data, alt, *settings, "--init",
                     str(run / "checkpoints" / "world_model.pt"), *flags,
                     "--set", "world_model_steps=0", "--set", f"refine_steps={cfg.refine_steps}"),
                     alt / ".done")  # fmt: skip
                alt_policy = select(cfg, step, f"{tag}-{name}", k, alt, previous, data, imitated)
                row(model, k, alt, data, alt_policy, refinement=alt_method)
        # Imitation on as many frames as this iteration had, from the second demonstration pool
        equal = il_equal_data(expert, extra, expert_frames, frames_in(data))
        il_eq = runs / f"il-equal{k}"
        step(f"train-{tag}-il-equal{k}", iterate_cmd(cfg, equal, il_eq, *common, *imitation),
             il_eq / ".done")  # fmt: skip
        row(il_at_frames_of(k), k, il_eq, equal)
        previous = policy


def run_study(cfg: StudyConfig, step: StudyStep) -> tuple[list[dict], list[str]]:
    """Every step of the study through `step`: each noise's demonstrations, then the chains
    (one per noise and seed) side by side. Returns the rows and the steps not finished
    (--report)."""
    chains = [(0.0, seed, cfg.iterations) for seed in cfg.seeds if 0.0 in cfg.demo_noise]
    chains += [(sigma, seed, cfg.robustness_iterations) for sigma in cfg.demo_noise if sigma
               for seed in cfg.robustness_seeds]  # fmt: skip
    missing = every_noise_demonstrations(cfg, step)
    rows, stopped = run_chains([functools.partial(chain, cfg, step, *c) for c in chains])
    return rows, missing + stopped


# ------------------------------------------------------------------------------- main
def parse(argv: list[str] | None) -> StudyConfig:
    p = argparse.ArgumentParser(
        prog="python -m research.dirl_sim", description=__doc__.split("\n")[0]
    )
    p.add_argument("--quick", action="store_true", help="tiny profile, one seed: minutes")
    p.add_argument(
        "--report", action="store_true",
        help="run nothing: write the table and figure from the steps finished so far",
    )  # fmt: skip
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="any StudyConfig field; tuples comma-separated (seeds=0,1,2)")  # fmt: skip
    a = p.parse_args(argv)
    cfg = StudyConfig(**(QUICK if a.quick else {}))
    try:
        cfg = apply_sets(cfg, a.set, "StudyConfig in research/study_config.py")
    except UserError as exc:
        p.error(str(exc))
    longest = max(cfg.iterations, cfg.robustness_iterations)
    if cfg.iteration_tracks and len(cfg.iteration_tracks) < longest:
        p.error(f"iteration_tracks: {len(cfg.iteration_tracks)} entries for {longest} iterations")
    for problem in range_problems(cfg):
        p.error(problem)
    if len(cfg.select_tracks) != 1 and len(cfg.select_tracks) < longest:
        p.error(f"select_tracks: {len(cfg.select_tracks)} entries for {longest} iterations")
    return outs_at_root(dataclasses.replace(cfg, report_only=a.report))


def main(argv: list[str] | None = None) -> int:
    cfg = parse(argv)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    if not cfg.report_only:  # a report must not relabel the run it reads
        (out / "config.json").write_text(json.dumps(dataclasses.asdict(cfg), indent=2) + "\n")
    started = time.monotonic()
    steps = plan(cfg)
    finished = (
        None if cfg.report_only else finished_steps(out, steps, functools.partial(run_study, cfg))
    )
    step = StudyStep(out, steps, report_only=cfg.report_only, parallel=cfg.parallel,
                     cwd=ROOT, finished_before=finished)  # fmt: skip
    print(f"dirl_sim: profile {cfg.profile}, seeds {list(cfg.seeds)}, {step.planned} steps"
          + (f" ({sum(finished.values())} finished before)" if finished else "")
          + f", {cfg.parallel} at once ({cfg.step_threads()} torch threads and"
          + f" {cfg.step_jobs()} simulator processes each), out {out}", flush=True)  # fmt: skip
    rows, missing = run_study(cfg, step)
    report = (
        table(rows) + "\n\nPaired by seed (model − baseline, each seed's mean over the "
        "held-out placements; mean ± std over seeds):\n\n" + comparison(rows)
    )
    if missing:
        report += f"\n\nNot finished yet (--report): {', '.join(missing)}."
    results = {"config": dataclasses.asdict(cfg), "rows": rows, "complete": not missing,
               "not_finished": missing, "wall_s": time.monotonic() - started,
               "environment": environment(), "recorded": recorded(out / "data")}  # fmt: skip
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    (out / "table.md").write_text(report + "\n")
    plot(rows, out / "completion_vs_frames.png")
    print("\n" + report)
    minutes = (time.monotonic() - started) / 60
    written = ", ".join(
        str(out / n) for n in ("results.json", "table.md", "completion_vs_frames.png")
    )
    print(f"\nwritten: {written} ({minutes:.1f} min)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
