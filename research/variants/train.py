"""carrt-train with the research variants plugged in: what every study command runs.

    python research/variants/train.py --episodes data/ --out runs/r --init runs/iter1 \\
        --set refine_search=true --set counterfactual_starts=6

Same flags as `carrt-train` (its settings: ResearchConfig, research/variants/config.py, which
`--settings` lists), and one run is one DIRL iteration in place (training/training_run.py
with `dirl`: imitation → world model → refinement, OUT/policy.* the last stage's policy, as the
study's chains read it); on top of them:

- refinement by search (`refine_search`, research/variants/refine_search.py) or from the drives'
  recorded outcomes (`refine_outcomes`, research/variants/refine_outcomes.py) in place of the
  paper's gradient in imagination;
- report.md and metrics.json get the counterfactual check (`counterfactual_starts` > 0, the
  simulator only: research/variants/counterfactual.py) and where refinement moved the plan
  (research/variants/refine_drift.py), under the keys "counterfactual" and "refine_drift".

The product never imports this: the variants plug in through training.training_run.Variants.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a script: make `research` and `training` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from carrt.errors import UserError
from research.variants.config import ResearchConfig
from training import training_run
from training.one_run import bad_input, run_iteration
from training.training_args import Parser, add_iteration_args, config_from

PROG = "research/variants/train.py"


def refine(cfg, policy, world_model, data, norm, ctx, resume, demonstrations):
    """The refinement stage of a variant, or None for the paper's (training/refine.py)."""
    if cfg.refine_outcomes:
        from research.variants.refine_outcomes import refine_by_outcomes

        return refine_by_outcomes(cfg, policy, data, ctx, resume, demonstrations)
    if cfg.refine_search:
        from research.variants.refine_search import search_step
        from training.refine import train_refine

        return train_refine(
            cfg, policy, world_model, data.windows, norm, ctx, resume=resume,
            val_dataset=data.val_windows, demonstrations=demonstrations, step_loss=search_step,
        )  # fmt: skip
    return None


def counterfactual_section(cfg, out: Path, **_models):
    """("counterfactual", the check's result or None, report.md lines)."""
    from research.variants.counterfactual import by_sequence_table, check_run, describe

    trained = cfg.world_model_steps > 0 or cfg.init
    if not (cfg.counterfactual_starts > 0 and trained and (out / "policy.onnx").is_file()):
        return "counterfactual", None, []
    c = check_run(out, None, cfg.counterfactual_layout, cfg.counterfactual_tracks,
                  cfg.counterfactual_starts)  # fmt: skip
    lines = [
        f"## Counterfactual check (simulator, placements {cfg.counterfactual_tracks} of "
        f"`{cfg.counterfactual_layout}`)",
        "",
        "Action sequences replayed in the simulator from the same start, imagined by the "
        "world model (research/variants/counterfactual.py):",
        "",
        describe(c),
        "",
        *by_sequence_table(c),
        "",
    ]
    return "counterfactual", c, lines


def drift_section(cfg, out: Path, *, policy, world_model, windows, device):
    """("refine_drift", where refinement moved the plan or None, report.md lines)."""
    from research.variants.refine_drift import describe, report_drift

    d = None if windows is None else report_drift(cfg, out, policy, world_model, windows, device)
    if not d:
        return "refine_drift", d, []
    lines = [
        "## Where refinement moved the plan (held-out frames)",
        "",
        "The plan of the policy refinement started from against the refined one, and what "
        "the world model imagines of each (research/variants/refine_drift.py). A large move the "
        "uncertainty does not rise for is one the uncertainty term could not hold back: "
        "judge it by driving.",
        "",
        describe(d),
        "",
    ]
    return "refine_drift", d, lines


VARIANTS = training_run.Variants(refine=refine, report=[counterfactual_section, drift_section])


def main(argv: list[str] | None = None) -> int:
    """One run, the world model and refinement on (`dirl`: their steps as the study sets them,
    its policy.* the last stage's), as every study command ran before carrt-train made them
    opt-in (--dirl, into OUT/refined/)."""
    try:
        cfg = research_config(argv)
    except UserError as exc:
        return bad_input(exc)
    return run_iteration(cfg, VARIANTS)[0]


def research_config(argv: list[str] | None) -> ResearchConfig:
    """carrt-train's flags of one iteration made into a ResearchConfig, `dirl` on."""
    p = Parser(prog=PROG, description=__doc__.split("\n")[0])
    add_iteration_args(p, ResearchConfig)
    cfg = config_from(p.parse_args(argv), ResearchConfig, PROG)
    return dataclasses.replace(cfg, dirl=True)


if __name__ == "__main__":
    sys.exit(main())
