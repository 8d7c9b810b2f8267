"""The paper's simulation study on carrt's simulator: imitation learning against DIRL, at scale.

    python -m bench.dirl_sim                        # the study (make study; 137 min, 2 cores)
    python -m bench.dirl_sim --quick                # every step, tiny profile, minutes
    python -m bench.dirl_sim --set seeds=0,1,2 --set iterations=3

Top to bottom, every step one of the project's own commands (logged under OUT/logs):

1. Demonstrations (`carrt-sim-data demos`): the scripted expert on the TRAINING
   placements, both cores, from random places at rest with the loop's noise injection half of
   the time; for the robustness setting the same again with Gaussian noise of σ 0.5 and 1.0 on
   every expert command (the paper's imperfect demonstrator). A second pool of demonstrations on
   other placements gives imitation as many frames as DIRL's iterations add.
2. IL: iterate.py with imitation only.
3. DIRL iteration k: the previous policy drives the training placements alone
   (`sim_data drives`: auto-reset after every collision, each crash labelled: the world model's
   collision examples, which the demonstrations hardly hold); the episodes join the data;
   iterate.py --init continues the world model on all of it, refines the policy in imagination
   and scores the world model against the simulator (training/counterfactual.py, placements
   200-204, never the evaluation ones). Refinement keeps a candidate every 100 steps; each, and
   the policy refinement started from, is driven on validation placements 200-219 and the best
   is the iteration's policy (training/select_by_driving.py; select_by_driving=false: the last
   step's). DIRL -unc: iteration 1's world model, refinement without the uncertainty term,
   chosen the same way.
4. IL at equal frames, once per DIRL iteration k: imitation on the demonstrations plus as many
   frames from the second pool as iterations 1..k's drives added, so every DIRL row is compared
   with imitation on (at least) as many frames as it had.
5. Every policy is driven by `carrt eval` on HELD-OUT placements (100-124 of the `hard` layout,
   never recorded for training), 60 simulated seconds each with auto-reset: the paper's metrics.

Output: OUT/results.json (a row per model, seed and noise, with its runs and its world model's
counterfactual numbers), OUT/table.md (mean ± std over seeds × placements) and
OUT/completion_vs_frames.png. Every finished step is skipped when the study runs again, so an
interrupted study continues where it stopped; progress and an ETA are printed as steps finish.
After the demonstrations, the chains (one per noise and seed) run side by side, `parallel` steps
at once (bench/study_steps.py); selections and evaluations reuse the numbers of weights they have
already driven (identical bytes drive identical laps).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from bench.dirl_table import comparison, il_at_frames_of, plot, table
from bench.study_steps import NotRun, StudyStep, run_chains
from carrt.errors import UserError
from carrt.settings import apply_sets

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class StudyConfig:
    """Every number of the study. The defaults are what the README's table was measured with."""

    out: str = "bench/results/dirl_sim"
    profile: str = "cpu"  # model sizes (training/profiles.py)
    seeds: tuple[int, ...] = (0, 1, 2)  # training seeds: model init, batch order, DIRL drives
    robustness_seeds: tuple[int, ...] = (0,)  # seeds of the σ > 0 chains
    layout: str = "hard"  # 8 obstacles
    train_tracks: str = "1000-1039"  # demonstrations and DIRL drives
    extra_tracks: str = "1040-1099"  # the second demonstration pool (IL at equal frames)
    # held out: never recorded, never tuned on. 25 placements: on 5 (100-104, until 2026-11-24)
    # the placements' own spread was as large as the DIRL-IL differences being judged
    eval_tracks: str = "100-124"
    counterfactual_tracks: str = "200-204"  # held out, for the world model check
    counterfactual_starts: int = 6  # start states per counterfactual placement
    expert_episodes: int = 6  # per training placement, one lap each from a random place
    demo_noise: tuple[float, ...] = (0.0, 0.5, 1.0)  # σ on the expert's commands (robustness)
    iterations: int = 3  # DIRL iterations (σ = 0)
    robustness_iterations: int = 1  # DIRL iterations for σ > 0
    drive_seconds: float = 15.0  # simulated s per training placement per DIRL iteration
    # Noise on the policy's commands in those drives (noise.during_auto): without it steering
    # is a function of the place and the world model learns its collision risk backwards
    # (docs/architecture.md, "what the world model can learn"); the paper's ±0.3 half the time
    # was not enough, ±0.8 held 0.5-1.5 s for 80 % of the time was (counterfactual check).
    drive_explore: bool = True
    explore_fraction: float = 0.8  # share of drive time perturbed (noise.fraction)
    explore_amplitude: float = 0.8  # uniform ± on steering and throttle (noise.amplitude)
    explore_hold_s: tuple[float, ...] = (0.5, 1.5)  # each value held this long (min, max)
    w_image: float = 0.1  # the world model's image-loss weight (training/config.py)
    imitation_steps: int = 3000
    world_model_steps: int = 3000  # iteration 1
    world_model_steps_next: int = 1500  # later iterations continue the previous world model
    refine_steps: int = 300
    refine_w_anchor: float = 10.0  # the safeguard (training/refine.py); 0: the paper's form
    # The second safeguard (training/refine.py): imitation's L1 on the demonstrations during
    # refinement. 50 was measured on validation placements 200-219 (seed 0, iteration 1 → 2:
    # completion 0.49 without it, 0.60 at 10, 0.68 at 50, from 0.73); 0: off.
    refine_w_imitation: float = 50.0
    # Another safeguard: the world model's gradient on the actions, centred over the batch of starts
    # (training/refine.py), so refinement cannot shift every plan alike (measured on the
    # validation placements: uncentred, iteration 2 moved every plan's steering by -0.02 to -0.04
    # and completion fell by 0.2-0.4 within 100 steps). False: the paper's gradient.
    refine_center_gradient: bool = True
    # The third safeguard: refinement keeps a candidate every `refine_candidates_every` steps and
    # the policy it started from is one too; each is driven on validation placements and the best
    # is the iteration's policy (training/select_by_driving.py). False: the last step's policy.
    select_by_driving: bool = True
    refine_candidates_every: int = 100
    select_tracks: str = "200-219"  # validation placements: neither trained on nor evaluated
    select_seconds: float = 30.0  # simulated s per validation placement and candidate
    eval_seconds: float = 60.0  # simulated seconds per held-out placement (a lap is ~7 s)
    threads: int = 2  # torch threads in all
    jobs: int = 2  # simulator processes in all
    # Steps of different chains run at once, each with threads/parallel torch threads and
    # jobs/parallel simulator processes (bench/study_steps.py; measured on the full study: two
    # 1-thread imitation runs side by side do 1.10× the work of one 2-thread run, two 1-process
    # evaluations 1.14×). 1: one step at a time.
    parallel: int = 2
    report_only: bool = False  # --report: tables from the finished steps, nothing run

    def step_threads(self) -> int:
        return max(1, self.threads // max(1, self.parallel))

    def step_jobs(self) -> int:
        return max(1, self.jobs // max(1, self.parallel))

    def iterate_overrides(self) -> list[str]:
        return [f"threads={self.step_threads()}", "progress=false", "figures=false"]


QUICK = dict(
    out="bench/results/dirl_sim_quick", profile="tiny", seeds=(0,), robustness_seeds=(0,),
    train_tracks="1000", extra_tracks="1001", eval_tracks="100", counterfactual_tracks="200",
    counterfactual_starts=2, expert_episodes=2, demo_noise=(0.0, 0.5), iterations=2,
    drive_seconds=5.0, imitation_steps=30, world_model_steps=30, world_model_steps_next=10,
    refine_steps=10, eval_seconds=10.0, refine_candidates_every=5, select_tracks="200",
    select_seconds=5.0,
)  # fmt: skip


# ------------------------------------------------------------------------------- plumbing
def py(*args: str) -> list[str]:
    return [sys.executable, *args]


def iterate_cmd(cfg: StudyConfig, episodes: list[Path], out: Path, *extra: str) -> list[str]:
    sets = [arg for item in cfg.iterate_overrides() for arg in ("--set", item)]
    return py(str(ROOT / "training" / "iterate.py"), "--episodes", *map(str, episodes),
              "--out", str(out), "--profile", cfg.profile, *sets, *extra)  # fmt: skip


def explore_args(cfg: StudyConfig) -> list[str]:
    """`carrt-sim-data drives` arguments for the exploration noise (none when it is off)."""
    if not cfg.drive_explore:
        return []
    lo, hi = cfg.explore_hold_s
    sets = (f"noise.fraction={cfg.explore_fraction}", f"noise.amplitude={cfg.explore_amplitude}",
            f"noise.hold_min_s={lo}", f"noise.hold_max_s={hi}")  # fmt: skip
    return ["--explore", *(arg for item in sets for arg in ("--set", item))]


def frames_in(paths: list[Path]) -> int:
    from training.sim_data import count_frames

    return count_frames(*paths)


def top_up(pool: Path, frames: int) -> list[Path]:
    """Whole episodes from `pool`, in name order, until they hold at least `frames` frames."""
    from carrt.episodes.reader import list_episodes, read_episode

    picked, total = [], 0
    for path in list_episodes([str(pool)]):
        if total >= frames:
            break
        picked.append(Path(path))
        total += read_episode(path).n
    if total < frames:
        raise SystemExit(f"dirl_sim: {pool} holds {total} frames, {frames} needed: more tracks")
    return picked


# ------------------------------------------------------------------------------- the steps
def demonstrations(cfg: StudyConfig, step: StudyStep, sigma: float, tracks: str, tag: str) -> Path:
    data = Path(cfg.out) / "data" / f"{tag}-noise{sigma:g}"
    step(f"{tag}-noise{sigma:g}", py("-m", "training.sim_data", "demos", "--out", str(data),
         "--tracks", tracks, "--layouts", cfg.layout, "--episodes", str(cfg.expert_episodes),
         "--noise", str(sigma), "--jobs", str(cfg.jobs)), data / ".done")  # fmt: skip
    return data


def evaluate(cfg: StudyConfig, step: StudyStep, name: str, run: Path, policy: Path,
             same_as: Path | None = None) -> dict:  # fmt: skip
    """`carrt eval` of the run's policy (in `policy`: the run itself, or the policy chosen by
    driving) on the held-out placements (one simulator seed). `same_as`: an evaluated run with
    byte-identical weights (an iteration that kept its start), whose laps these are: driving is
    deterministic, so they are copied, not driven again."""
    result, marker = run / "eval.json", run / ".done-eval"
    if same_as is not None and not marker.exists() and not step.report_only:
        shutil.copy2(same_as / "eval.json", result)
        marker.touch()
        step.reuse(f"eval-{name}", f"the laps of {same_as.name} (same weights)")
    else:
        step(f"eval-{name}", py("-m", "carrt", "eval", "--model", str(policy / "policy.onnx"),
             "--layout", cfg.layout, "--tracks", cfg.eval_tracks, "--seconds",
             str(cfg.eval_seconds), "--seeds", "0", "--jobs", str(cfg.step_jobs()), "--json",
             str(result)), marker)  # fmt: skip
    return json.loads(result.read_text())


def select(cfg: StudyConfig, step: StudyStep, name: str, run: Path, start: Path,
           data: list[Path]) -> Path:  # fmt: skip
    """The iteration's policy: with select_by_driving, the best of the policy refinement started
    from and its candidates, driven on the validation placements (OUT run/selected, a run
    directory the next --init reads); else the run's own last policy. The chain's earlier
    selections are reused: the start was driven there already (it was chosen there)."""
    if not cfg.select_by_driving:
        return run
    chosen = run / "selected"
    kept = run.glob("candidates/refine*.pt")  # refine<step>.pt, in step order
    candidates = sorted(kept, key=lambda p: int(p.stem.removeprefix("refine")))
    earlier = sorted(run.parent.glob("*/selected/selection.json"))
    step(f"select-{name}", py("-m", "training.select_by_driving", "--out", str(chosen),
         "--candidates", f"start={start / 'policy.pt'}", *map(str, candidates),
         "--episodes", *map(str, data), "--layout", cfg.layout, "--tracks", cfg.select_tracks,
         "--seconds", str(cfg.select_seconds), "--jobs", str(cfg.step_jobs()),
         "--keep", str(run / "world_model.pt"), "--reuse", *map(str, earlier)),
         chosen / ".done")  # fmt: skip
    return chosen


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
    common = ["--seed", str(seed), "--set", f"refine_w_anchor={cfg.refine_w_anchor}",
              "--set", f"refine_w_imitation={cfg.refine_w_imitation}",
              "--set", f"refine_center_gradient={str(cfg.refine_center_gradient).lower()}",
              "--set", f"counterfactual_starts={cfg.counterfactual_starts}",
              "--set", f"counterfactual_tracks={cfg.counterfactual_tracks}",
              "--set", f"counterfactual_layout={cfg.layout}",
              "--set", f"w_image={cfg.w_image}",
              "--set", f"refine_candidates_every={every}"]  # fmt: skip
    imitation = ["--set", f"imitation_steps={cfg.imitation_steps}",
                 "--set", "world_model_steps=0", "--set", "refine_steps=0"]  # fmt: skip

    evaluated: dict[str, Path] = {}  # sha256 of policy.pt → the first run evaluated with it

    def row(model: str, iteration: int, run: Path, data: list[Path], policy: Path | None = None):
        from carrt.policy import file_sha256

        policy = policy or run
        digest = file_sha256(policy / "policy.pt")
        same_as = evaluated.get(digest)
        evaluated.setdefault(digest, run)
        result = evaluate(cfg, step, f"{tag}-{run.name}", run, policy, same_as)
        metrics = json.loads((run / "metrics.json").read_text())
        selection = policy / "selection.json"
        chosen = json.loads(selection.read_text())["chosen"] if selection.is_file() else None
        rows.append({
            "model": model, "iteration": iteration, "demo_noise": sigma, "seed": seed,
            "frames": frames_in(data), "run": str(run), "aggregate": result["aggregate"],
            "runs": result["runs"], "counterfactual": metrics.get("counterfactual"),
            "chosen": chosen, "same_weights_as": same_as and str(same_as),
        })  # fmt: skip
        agg = result["aggregate"]
        print(f"  [{tag}] {model}: completion {agg['completion_ratio']['mean']:.2f}, "
              f"{agg['collisions_per_min']['mean']:.1f} collisions/min"
              + (f" (chosen by driving: {chosen})" if chosen else ""), flush=True)  # fmt: skip

    il = runs / "il"
    step(f"train-{tag}-il", iterate_cmd(cfg, [expert], il, *common, *imitation), il / ".done")
    row("IL", 0, il, [expert])
    data, previous = [expert], il
    expert_frames = frames_in([expert])  # read once: every iteration tops up against it
    for k in range(1, iterations + 1):
        drives = Path(cfg.out) / "data" / f"drives-{tag}-iter{k}"
        step(f"drive-{tag}-iter{k}", py("-m", "training.sim_data", "drives", "--model",
             str(previous / "policy.onnx"), "--out", str(drives), "--tracks", cfg.train_tracks,
             "--layouts", cfg.layout, "--seconds", str(cfg.drive_seconds), "--jobs",
             str(cfg.step_jobs()), *explore_args(cfg)),
             drives / ".done")  # fmt: skip
        data = [*data, drives]
        run = runs / f"dirl{k}"
        wm_steps = cfg.world_model_steps if k == 1 else cfg.world_model_steps_next
        step(f"train-{tag}-dirl{k}", iterate_cmd(cfg, data, run, *common, "--init",
             str(previous), "--set", f"world_model_steps={wm_steps}",
             "--set", f"refine_steps={cfg.refine_steps}"), run / ".done")  # fmt: skip
        policy = select(cfg, step, f"{tag}-dirl{k}", run, previous, data)
        row(f"DIRL iter {k}", k, run, data, policy)
        if k == 1 and sigma == 0:
            # The same world model and start policy: only the uncertainty term differs.
            unc = runs / "unc1"
            step(f"train-{tag}-unc1", iterate_cmd(cfg, data, unc, *common, "--init",
                 str(run / "checkpoints" / "world_model.pt"), "--no-uncertainty",
                 "--set", "world_model_steps=0", "--set", f"refine_steps={cfg.refine_steps}"),
                 unc / ".done")  # fmt: skip
            unc_policy = select(cfg, step, f"{tag}-unc1", unc, previous, data)
            row("DIRL -unc iter 1", 1, unc, data, unc_policy)
        # Imitation on as many frames as this iteration had, from the second demonstration
        # pool (whole episodes in name order, so iteration k's set extends iteration k-1's).
        equal = [expert, *top_up(extra, frames_in(data) - expert_frames)]
        il_eq = runs / f"il-equal{k}"
        step(f"train-{tag}-il-equal{k}", iterate_cmd(cfg, equal, il_eq, *common, *imitation),
             il_eq / ".done")  # fmt: skip
        row(il_at_frames_of(k), k, il_eq, equal)
        previous = policy


def planned_steps(cfg: StudyConfig) -> int:
    chains = [(0.0, s, cfg.iterations) for s in cfg.seeds if 0.0 in cfg.demo_noise]
    chains += [(x, s, cfg.robustness_iterations) for x in cfg.demo_noise if x
               for s in cfg.robustness_seeds]  # fmt: skip
    per_dirl, per_unc = (6, 3) if cfg.select_by_driving else (5, 2)  # + a selection each
    per_chain = sum(2 + per_dirl * k + (per_unc if sigma == 0 else 0) for sigma, _, k in chains)
    return 2 * len(cfg.demo_noise) + per_chain


# ------------------------------------------------------------------------------- main
def parse(argv: list[str] | None) -> StudyConfig:
    p = argparse.ArgumentParser(prog="python -m bench.dirl_sim", description=__doc__.split("\n")[0])
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
        cfg = apply_sets(cfg, a.set, "StudyConfig in bench/dirl_sim.py")
    except UserError as exc:
        p.error(str(exc))
    return dataclasses.replace(cfg, report_only=a.report)


def main(argv: list[str] | None = None) -> int:
    cfg = parse(argv)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    if not cfg.report_only:  # a report must not relabel the run it reads
        (out / "config.json").write_text(json.dumps(dataclasses.asdict(cfg), indent=2) + "\n")
    started = time.monotonic()
    step = StudyStep(out, planned_steps(cfg), report_only=cfg.report_only,
                     parallel=cfg.parallel, cwd=ROOT)  # fmt: skip
    print(f"dirl_sim: profile {cfg.profile}, seeds {list(cfg.seeds)}, {step.planned} steps, "
          f"{cfg.parallel} at once, out {out}", flush=True)  # fmt: skip
    missing = []
    chains = [(0.0, seed, cfg.iterations) for seed in cfg.seeds if 0.0 in cfg.demo_noise]
    chains += [(sigma, seed, cfg.robustness_iterations) for sigma in cfg.demo_noise if sigma
               for seed in cfg.robustness_seeds]  # fmt: skip
    for sigma in cfg.demo_noise:  # every chain needs them: first, each with all `jobs`
        try:
            demonstrations(cfg, step, sigma, cfg.train_tracks, "expert")
            demonstrations(cfg, step, sigma, cfg.extra_tracks, "extra")
        except NotRun as exc:
            missing.append(str(exc))
    rows, stopped = run_chains([functools.partial(chain, cfg, step, *c) for c in chains])
    missing += stopped
    report = (
        table(rows) + "\n\nPaired by seed (model − baseline, each seed's mean over the "
        "held-out placements; mean ± std over seeds):\n\n" + comparison(rows)
    )
    if missing:
        report += f"\n\nNot finished yet (--report): {', '.join(missing)}."
    results = {"config": dataclasses.asdict(cfg), "rows": rows, "complete": not missing,
               "not_finished": missing, "wall_s": time.monotonic() - started}  # fmt: skip
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
