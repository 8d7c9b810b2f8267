"""The paper's robustness claim, judged from two results files: does DIRL lose less than IL when
the demonstrations are noisy?

    python -m research.robustness --clean research/results/takeover_5seeds_rerun.json.gz \
        --noisy research/results/takeover_tau05_sigma1_5seeds.json.gz

Why a separate step: the claim compares each method with itself across demonstration noise
(IL at σ 0 against IL at σ 1.0, DIRL at σ 0 against DIRL at σ 1.0), and the σ 0 and σ > 0 chains
may come from different runs of the same check (the σ 0 rounds are an hour of their own). Both
files must name the same held-out placements; only seeds both hold are compared. For each seed
and model the loss is its mean completion at σ 0 minus at σ (and its collisions per minute at
σ minus at σ 0); "DIRL loses less" is the DIRL model's loss minus IL's, paired by seed, below 0
by more than its spread over seeds. (DIRL against IL at equal frames at σ is the check's own
table.)
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a file, from any directory: the repository on the path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.provenance import environment
from carrt.arg_types import finite_positive
from carrt.errors import EXIT_USAGE, UserError
from research.dirl_table import cell
from research.json_file import read_json

KEYS = (("completion_ratio", 1.0), ("collisions_per_min", -1.0))  # (metric, sign of "better")


def load(path: str) -> dict:
    """A check's results file (config and rows); a missing or foreign one is a UserError."""
    data = read_json(path, "results file")
    if not isinstance(data, dict) or not isinstance(data.get("rows"), list):
        raise UserError(f"{path}: not a results file (no rows)")
    return data


def placements(data: dict) -> str:
    config = data.get("config", {})
    return str(config.get("eval_tracks", config.get("study", {}).get("eval_tracks", "")))


def means(data: dict, sigma: float, model: str, key: str) -> dict[int, float]:
    """seed → the model's mean of `key` over its placements, at demonstration noise σ."""
    try:
        return {
            int(r["seed"]): float(r["aggregate"][key]["mean"])
            for r in data["rows"]
            if r["model"] == model and float(r["demo_noise"]) == sigma
        }
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"a row of {model} lacks its {key} ({exc.__class__.__name__})") from None


def losses(clean: dict, noisy: dict, sigma: float, models: list[str]) -> dict:
    """Per model and metric: each seed's value at σ 0 and σ and the loss (worse is positive);
    and each DIRL model's loss minus IL's, paired by seed."""
    out: dict = {"sigma": sigma, "models": {}, "against_il": {}}
    for key, better in KEYS:
        loss_of: dict[str, dict[int, float]] = {}
        for model in models:
            at0, at_sigma = means(clean, 0.0, model, key), means(noisy, sigma, model, key)
            seeds = sorted(set(at0) & set(at_sigma))
            loss_of[model] = {s: better * (at0[s] - at_sigma[s]) for s in seeds}
            out["models"].setdefault(model, {})[key] = {
                "seeds": seeds,
                "clean": [at0[s] for s in seeds],
                "noisy": [at_sigma[s] for s in seeds],
                "loss": [loss_of[model][s] for s in seeds],
            }
        for model in models[1:]:
            seeds = sorted(set(loss_of[model]) & set(loss_of["IL"]))
            out["against_il"].setdefault(model, {})[key] = {
                "seeds": seeds,
                "difference": [loss_of[model][s] - loss_of["IL"][s] for s in seeds],
            }
    return out


def table(result: dict) -> str:
    """Markdown: each model at σ 0 and σ and its loss (mean ± std over seeds), then each DIRL
    model's loss minus IL's."""
    sigma = result["sigma"]
    lines = [f"| model | completion σ 0 | completion σ {sigma:g} | loss | collisions / min σ 0 "
             f"| σ {sigma:g} | rise | seeds |", "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for model, by_key in result["models"].items():
        c, k = by_key["completion_ratio"], by_key["collisions_per_min"]
        lines.append(
            f"| {model} | {cell(c['clean'], '.2f')} | {cell(c['noisy'], '.2f')} "
            f"| {cell(c['loss'], '+.3f')} | {cell(k['clean'], '.1f')} | {cell(k['noisy'], '.1f')} "
            f"| {cell(k['loss'], '+.2f')} | {', '.join(map(str, c['seeds']))} |"
        )
    lines += ["", "| DIRL model | its completion loss − IL's | each seed "
              "| its collisions rise − IL's |", "|---|---|---|---|"]  # fmt: skip
    for model, by_key in result["against_il"].items():
        c, k = by_key["completion_ratio"], by_key["collisions_per_min"]
        each = ", ".join(f"{d:+.2f}" for d in c["difference"])
        lines.append(f"| {model} | {cell(c['difference'], '+.3f')} | {each} "
                     f"| {cell(k['difference'], '+.2f')} |")  # fmt: skip
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m research.robustness", description=__doc__.split("\n")[0]
    )
    p.add_argument("--clean", required=True, help="results file holding the σ 0 rows")
    p.add_argument("--noisy", required=True, help="results file holding the σ > 0 rows")
    p.add_argument("--sigma", type=finite_positive, default=1.0, help="the noisy σ (1.0)")
    p.add_argument("--dirl", default="takeovers2", help="the DIRL model compared (takeovers2)")
    p.add_argument("--json", help="also write the numbers and both files' provenance here")
    a = p.parse_args(argv)
    try:
        clean, noisy = load(a.clean), load(a.noisy)
        if placements(clean) != placements(noisy):
            raise UserError(f"the files drove different placements: {placements(clean)!r} in "
                            f"{a.clean}, {placements(noisy)!r} in {a.noisy}")  # fmt: skip
        for model in ("IL", a.dirl):
            if not set(means(clean, 0.0, model, "completion_ratio")) & set(
                means(noisy, a.sigma, model, "completion_ratio")
            ):
                raise UserError(f"no seed has {model} at σ 0 in {a.clean} and at σ {a.sigma:g} "
                                f"in {a.noisy}")  # fmt: skip
    except UserError as exc:
        print(f"robustness: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    result = losses(clean, noisy, a.sigma, ["IL", a.dirl])
    text = table(result)
    print(text)
    if a.json:
        record = {"files": {"clean": a.clean, "noisy": a.noisy},
                  "placements": placements(noisy), "result": result, "table": text,
                  "environment": environment(),
                  "sources": {"clean": clean.get("environment"),
                              "noisy": noisy.get("environment")}}  # fmt: skip
        Path(a.json).write_text(json.dumps(record, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
