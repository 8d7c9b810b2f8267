"""Refinement from real outcomes, judged by driving: does it beat the policy it refines?

    python -m research.outcome_check                    # σ 0, two rounds, seeds 0-2 (~40 min here)
    python -m research.outcome_check --set seeds=0 --set outcome_steps=200
    python -m research.outcome_check --set outcome_iterations=3 --set eval_tracks=200-259
    python -m research.outcome_check --set demo_noise=1.0

The study's chain (per demonstration noise σ, `demo_noise`, and seed) up to DIRL iteration 1's
imitation (research/dirl_sim.py, its settings and its commands): demonstrations, IL, the
iteration's drives (exploration noise, every crash labelled) and take-overs, the previous
policy imitating again on every labelled frame ("imitated", the policy the study's selection
keeps unless refinement beats it). Then, from imitated, `refine_outcomes`
(research/variants/refine_outcomes.py) in two arms with everything else equal:

- "outcomes": the executed actions of the drives weighted by their advantage (real return over
  a cross-fitted ridge baseline on the policy's features);
- "uniform" (σ 0 only): the same windows, every one weighted 1 (`outcome_advantage=false`):
  imitation of the noisy drives with no outcome in it, which says whether the advantage
  carries the signal.

With `outcome_iterations` k > 1, "outcomes<k>": the previous iteration's outcomes policy drives
the training placements (exploration and take-overs, as iteration 1's drives) and is refined
again the same way on every drive so far: the DIRL loop with recorded outcomes in place of
imagination. "IL-equal<k>" (`il_equal`) imitates the demonstrations topped up from the study's
second pool to the last round's frames: the paper's comparison at equal data.

Every policy is driven on the held-out placements (100-199 × 30 s, as the study); the table
pairs each arm with imitated seed by seed (each seed's difference ± its paired standard error
over the placements, then mean ± std over seeds). The arms' settings are fixed here, before any
driving, and the number of rounds on validation placements (`eval_tracks=200-259`, their
results in files of their own): none was tuned on the placements they are judged on.
OUT/results.json holds every run and each arm's outcome diagnostics (baseline R², effective
sample share).
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

if __package__ in (None, ""):  # run as a file, from any directory: the repository on the path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from research.check_steps import (
    imitation_flags,
    read_sets,
    run_check,
    study_for,
    suffix,
    write_results,
)
from research.check_steps import report as paired_report
from research.dirl_steps import (
    evaluate,
    frames_in,
    il_equal_data,
    iterate_cmd,
    iteration_drives,
    reimitate_flags,
)
from research.study_config import StudyConfig
from research.study_steps import StudyStep

ARMS = {"outcomes": "true", "uniform": "false"}  # arm → outcome_advantage


@dataclass
class CheckConfig:
    """The study's settings (StudyConfig) plus the refinement arms'."""

    out: str = "research/runs/outcome"
    seeds: tuple[int, ...] = (0, 1, 2)
    outcome_steps: int = 500  # refinement steps of each arm
    outcome_lr: float = 3e-4  # the study's re-imitation learning rate
    outcome_batch: int = 64  # the imitation batch of the cpu profile
    outcome_w_imitation: float = 1.0  # imitation's L1 on the demonstrations beside it
    outcome_temperature: float = 1.0  # τ of the advantage weights
    # rounds of refinement from outcomes (≥ 2 drives again); 2 drove best of 1-3 on validation
    # placements 200-259 (docs/dirl_outcome_validation.json, in git at 38d191d)
    outcome_iterations: int = 2
    # "IL-equal<k>": imitation on the demonstrations plus the study's second pool (extra_tracks)
    # topped up to the frames the last outcomes iteration learnt from (the paper's comparison)
    il_equal: bool = True
    # where every policy is judged: the study's held-out test placements; choices between
    # settings are made on validation placements (200-259) and only then judged here
    eval_tracks: str = StudyConfig.eval_tracks
    demo_noise: tuple[float, ...] = (0.0,)  # σ of the demonstrations (the paper's 0, 0.5, 1.0)
    parallel: int = 2
    study: StudyConfig = field(default_factory=StudyConfig)


def arm_flags(cfg: CheckConfig, advantage: str) -> list[str]:
    sets = ("refine_outcomes=true", f"outcome_advantage={advantage}",
            f"refine_steps={cfg.outcome_steps}", f"refine_lr={cfg.outcome_lr}",
            f"refine_batch_size={cfg.outcome_batch}", "world_model_steps=0",
            f"refine_w_imitation={cfg.outcome_w_imitation}",
            f"outcome_temperature={cfg.outcome_temperature}")  # fmt: skip
    return [arg for s in sets for arg in ("--set", s)]


def chain(cfg: CheckConfig, step: StudyStep, sigma: float, seed: int, rows: list[dict]) -> None:
    """IL → drives → imitated → each arm, every policy evaluated, for one demonstration noise
    and seed (the uniform control at σ 0 only: the question it answers is not the noise's)."""
    study = cfg.study
    tag = f"noise{sigma:g}-seed{seed}"
    runs = Path(cfg.out) / "runs" / tag
    expert = Path(cfg.out) / "data" / f"expert-noise{sigma:g}"
    imitation = imitation_flags(study, seed)
    il = runs / "il"
    step(f"train-{tag}-il", iterate_cmd(study, [expert], il, *imitation), il / ".done")
    data = [expert, *iteration_drives(study, step, tag, sigma, 1, il)]
    imitated = runs / "imitated"
    again = reimitate_flags(study)
    step(f"train-{tag}-imitated", iterate_cmd(study, data, imitated, "--seed", str(seed),
         "--init", str(il), *again, "--set", "world_model_steps=0", "--set", "refine_steps=0"),
         imitated / ".done")  # fmt: skip
    # model → (run, frames it learnt from); each data set's frames counted once
    expert_frames, frames = frames_in([expert]), frames_in(data)
    models = {"IL": (il, expert_frames), "imitated": (imitated, frames)}
    for arm, advantage in ARMS.items() if sigma == 0 else [("outcomes", ARMS["outcomes"])]:
        run = runs / arm
        step(f"train-{tag}-{arm}", iterate_cmd(study, data, run, "--seed", str(seed), "--init",
             str(imitated), *arm_flags(cfg, advantage)), run / ".done")  # fmt: skip
        models[arm] = (run, frames)
    previous, k = runs / "outcomes", cfg.outcome_iterations
    for i in range(2, k + 1):
        new = iteration_drives(study, step, tag, sigma, i, previous)
        data, frames = [*data, *new], frames + frames_in(new)  # the new episodes counted once
        run = runs / outcomes_model(i)
        step(f"train-{tag}-{run.name}", iterate_cmd(study, data, run, "--seed", str(seed),
             "--init", str(previous), *arm_flags(cfg, "true")), run / ".done")  # fmt: skip
        models[run.name], previous = (run, frames), run
    if cfg.il_equal:
        extra = Path(cfg.out) / "data" / f"extra-noise{sigma:g}"
        equal = il_equal_data(expert, extra, expert_frames, frames)
        il_eq = runs / f"il-equal{k}"
        step(f"train-{tag}-il-equal{k}", iterate_cmd(study, equal, il_eq, *imitation),
             il_eq / ".done")  # fmt: skip
        models[f"IL-equal{k}"] = (il_eq, frames_in(equal))
    for model, (run, learnt_from) in models.items():
        result = run / f"eval{suffix(cfg)}.json"
        out = evaluate(study, step, f"{tag}-{model}{suffix(cfg)}", run / "policy.onnx", result)
        diagnostics = run / "outcomes.json"
        rows.append({"model": model, "demo_noise": sigma, "seed": seed, "run": str(run),
                     "frames": learnt_from,
                     "runs": out["runs"], "outcomes": json.loads(diagnostics.read_text())
                     if diagnostics.is_file() else None})  # fmt: skip


def outcomes_model(k: int) -> str:
    """The outcomes arm's name at iteration k: "outcomes", "outcomes2", …"""
    return "outcomes" if k == 1 else f"outcomes{k}"


def outcome_pairs(rows: list[dict]) -> list[tuple[str, str]]:
    """The (model, against) differences the outcome check reports, of the models in `rows`."""
    names = {r["model"] for r in rows}
    later = sorted(m for m in names if m.startswith("outcomes") and m != "outcomes")
    pairs = [("outcomes", "imitated"), ("uniform", "imitated"), ("outcomes", "uniform"),
             ("imitated", "IL"), ("outcomes", "IL")]  # fmt: skip
    pairs += [(m, b) for m in later for b in ("outcomes", "imitated", "IL")]
    equal = sorted(m for m in names if m.startswith("IL-equal"))
    return pairs + [(outcomes_model(int(m.removeprefix("IL-equal"))), m) for m in equal]


def report(rows: list[dict], pairs: list[tuple[str, str]] | None = None) -> str:
    """check_steps.report with the outcome check's pairs (outcome_pairs) by default."""
    return paired_report(rows, outcome_pairs(rows) if pairs is None else pairs)


def parse(argv: list[str] | None) -> CheckConfig:
    p, cfg = read_sets(argv, CheckConfig(), "research.outcome_check", __doc__, "CheckConfig")
    if cfg.outcome_iterations < 1:
        p.error(f"outcome_iterations: {cfg.outcome_iterations} (1 or more)")
    return dataclasses.replace(cfg, study=study_for(p, cfg))


def main(argv: list[str] | None = None) -> int:
    cfg = parse(argv)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    noises, k = len(cfg.demo_noise), cfg.outcome_iterations
    n, control = noises * len(cfg.seeds), len(cfg.seeds) * (0.0 in cfg.demo_noise)
    kinds = {"demos": noises * (1 + cfg.il_equal), "train il": n,
             "train il-equal": n * cfg.il_equal, "drive": k * n, "takeovers": k * n,
             "train imitated": n, "train outcomes": k * n, "train uniform": control,
             "eval": (2 + k + cfg.il_equal) * n + control}  # fmt: skip
    rows = run_check(cfg, kinds, chain, extra=cfg.il_equal)
    text = write_results(cfg, rows, started, suffix(cfg), outcome_pairs)
    print("\n" + text + f"\n\nwritten: {out}/results{suffix(cfg)}.json, table{suffix(cfg)}.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
