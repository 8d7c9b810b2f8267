"""What the checks share (research/outcome_check.py, research/takeover_check.py): their command
line, their steps run side by side with progress and an ETA, the study's settings they run with, and
the paired table and results file they write.

Split from outcome_check.py, where it grew first, so that each check reads as its config, its
chain and its main, and neither imports the other.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from bench.provenance import environment, recorded
from carrt.errors import UserError
from carrt.settings import apply_sets
from research.dirl_steps import ROOT, every_noise_demonstrations
from research.dirl_table import RACING, cell
from research.paths import outs_at_root
from research.study_config import StudyConfig, range_problems, usable_cores
from research.study_steps import StudyStep, finished_steps, run_chains

# the driving columns of the first table and their formats
METRICS = (("completion_ratio", ".2f"), ("collisions_per_min", ".1f"), ("average_speed", ".2f"))


def imitation_flags(study: StudyConfig, seed: int) -> list[str]:
    """iterate.py flags of imitation alone (IL, IL at equal frames): no world model, no
    refinement."""
    return ["--seed", str(seed), "--set", f"imitation_steps={study.imitation_steps}",
            "--set", "world_model_steps=0", "--set", "refine_steps=0"]  # fmt: skip


def suffix(cfg) -> str:
    """Nothing for the test placements; "-<tracks>" for others (their results kept apart)."""
    return "" if cfg.eval_tracks == StudyConfig.eval_tracks else f"-{cfg.eval_tracks}"


def paired(rows: list[dict], model: str, base: str, key: str) -> list[tuple[int, float, float]]:
    """(seed, mean difference, its paired standard error) over the placements both drove."""
    out = []
    for r in (r for r in rows if r["model"] == model):
        b = next((x for x in rows if x["model"] == base and x["seed"] == r["seed"]), None)
        if b is None:
            continue
        mine = {run["track"]: run.get(key) for run in r["runs"]}
        theirs = {run["track"]: run.get(key) for run in b["runs"]}
        both = [t for t in mine if t in theirs and None not in (mine[t], theirs[t])]
        if not both:  # a file written before the metric existed
            continue
        d = np.array([mine[t] - theirs[t] for t in both], dtype=float)
        se = float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("nan")
        out.append((r["seed"], float(d.mean()), se))
    return out


def report(rows: list[dict], pairs: list[tuple[str, str]]) -> str:
    """Each model's driving (mean ± std over placements and seeds) and the paired differences
    `pairs` (model, against), seed by seed; the racing columns say "—" for runs that predate
    them."""
    lines = ["| model | seeds | frames | completion | collisions / min | avg m/s | laps / min "
             "| progress / m |", "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for model in dict.fromkeys(r["model"] for r in rows):
        mine = [r for r in rows if r["model"] == model]
        runs = [run for r in mine for run in r["runs"]]
        frames = [r["frames"] for r in mine if "frames" in r]
        shown = f"{np.mean(frames):,.0f}" if frames else "–"
        driving = " | ".join(cell([run.get(k) for run in runs], f) for k, f in METRICS + RACING)
        lines.append(f"| {model} | {len(mine)} | {shown} | {driving} |")
    lines += [
        "",
        "| model | against | Δ completion, mean ± std over seeds | per seed (± paired SE) "
        "| Δ collisions / min | per seed | Δ laps / min |",
        "|---|---|---|---|---|---|---|",
    ]
    for model, base in pairs:
        comp = paired(rows, model, base, "completion_ratio")
        coll = paired(rows, model, base, "collisions_per_min")
        laps = paired(rows, model, base, "laps_per_min")
        if not comp:
            continue
        each = ", ".join(f"{d:+.2f} ± {se:.2f}" for _, d, se in comp)
        each_c = ", ".join(f"{d:+.1f} ± {se:.1f}" for _, d, se in coll)
        mean_comp, mean_coll, mean_laps = (
            cell([d for _, d, _ in comp], "+.3f"),
            cell([d for _, d, _ in coll], "+.2f"),
            cell([d for _, d, _ in laps], "+.2f"),
        )
        lines.append(
            f"| {model} | {base} | {mean_comp} | {each} | {mean_coll} | {each_c} | {mean_laps} |"
        )
    return "\n".join(lines)


# the study fields a check sets from its own (study_for): `--set study.<one of these>` refused
CHECK_OWNS = ("out", "seeds", "demo_noise", "parallel", "threads", "jobs", "eval_tracks")


def read_sets(argv: list[str] | None, cfg, module: str, doc: str, name: str):
    """A check's command line: `--set FIELD=VALUE` on its config dataclass `cfg` (named `name`
    in `module`), and `--set study.FIELD=VALUE` on the study's settings it runs with (the
    profile, steps, placements: e.g. `study.profile=paper` on a GPU). Returns the parser (for
    one-line errors, exit code 2) and the config."""
    p = argparse.ArgumentParser(prog=f"python -m {module}", description=doc.split("\n")[0])
    where = f"{name} in {type(cfg).__module__.replace('.', '/')}.py"
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help=f"a {where} field, or study.FIELD for a StudyConfig one in "
                   "research/study_config.py; tuples comma-separated")  # fmt: skip
    items = p.parse_args(argv).set
    study = [item.removeprefix("study.") for item in items if item.startswith("study.")]
    own = [item for item in items if not item.startswith("study.")]
    try:
        cfg = apply_sets(cfg, own, where)
        where = (
            f"StudyConfig in research/study_config.py; {', '.join(CHECK_OWNS)} are the check's own"
        )
        studied = apply_sets(cfg.study, study, where, frozen=CHECK_OWNS)
        return p, outs_at_root(dataclasses.replace(cfg, study=studied))
    except UserError as exc:
        p.error(str(exc))


def run_check(cfg, kinds: dict[str, int], chain_fn, extra: bool = True,
              also: tuple[float, ...] = ()) -> list[dict]:  # fmt: skip
    """A check's steps: each σ's demonstrations (and the second pool with `extra`; `also`: more
    σs' demonstrations, every_noise_demonstrations'), then
    `chain_fn(cfg, step, σ, seed, rows)` for every σ and seed side by side. The steps an earlier
    invocation finished are counted first (the chains walked with nothing run, as the study
    does), so the ETA leaves them out instead of guessing them at a typical time."""

    def walk(step: StudyStep) -> list[dict]:
        every_noise_demonstrations(cfg.study, step, extra, also)  # passed while counting
        return run_chains([functools.partial(chain_fn, cfg, step, sigma, s)
                           for sigma in cfg.demo_noise for s in cfg.seeds])[0]  # fmt: skip

    finished = finished_steps(Path(cfg.out), kinds, walk)
    return walk(StudyStep(Path(cfg.out), kinds, parallel=cfg.parallel, cwd=ROOT,
                          finished_before=finished))  # fmt: skip


def write_results(cfg, rows: list[dict], started: float, name: str,
                  pairs_of: Callable[[list[dict]], list[tuple[str, str]]]) -> str:  # fmt: skip
    """OUT/results<name>.json (config, rows, wall time) and OUT/table<name>.md (one table per
    demonstration noise, `report` with the pairs `pairs_of` gives for its rows); returns the
    tables' text."""
    text = "\n\n".join(
        f"Demonstration noise σ {sigma:g}:\n\n" + report(mine, pairs_of(mine))
        for sigma in cfg.demo_noise
        for mine in [[r for r in rows if r["demo_noise"] == sigma]]
    )
    out = Path(cfg.out)
    results = {"config": dataclasses.asdict(cfg), "rows": rows,
               "wall_s": time.monotonic() - started, "environment": environment(),
               "recorded": recorded(out / "data")}  # fmt: skip
    (out / f"results{name}.json").write_text(json.dumps(results, indent=1) + "\n")
    (out / f"table{name}.md").write_text(text + "\n")
    return text


def study_for(p: argparse.ArgumentParser, cfg) -> StudyConfig:
    """The study's settings with a check's out, seeds, σs, placements and parallelism (every
    core shared between its steps); a bad one ends in one line through `p`."""
    cores = usable_cores()
    study = dataclasses.replace(cfg.study, out=cfg.out, seeds=cfg.seeds,
                                demo_noise=cfg.demo_noise, parallel=cfg.parallel,
                                threads=cores, jobs=cores, eval_tracks=cfg.eval_tracks)  # fmt: skip
    for problem in range_problems(study, lambda f: f if f in CHECK_OWNS else f"study.{f}"):
        p.error(problem)
    return study
