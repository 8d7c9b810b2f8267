"""Where refinement moved the plan, as steps of a check (research/takeover_check.py): the drift of
every refined policy (research/variants/refine_drift.py) and the ensemble members whose spread it
reports beside the evidential uncertainty.

Why a check needs it: -unc ended level with DIRL in every setting measured (research/LOG.md,
"Refinement on top of the take-over rounds, and -unc"). The paper's uncertainty term can only
change what refinement does if the uncertainty rises where refinement moves the plan; these
steps measure that for the evidential uncertainty of the world model refinement ran in and,
with members, for a deep ensemble (world models trained apart on the same frames from their
own initialisations), the estimator usually trusted to grow off the data.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from research.dirl_steps import ROOT, py
from research.dirl_table import cell
from research.study_steps import StudyStep

MEMBER_SEED_STRIDE = 100  # member m of the chain with seed s trains with seed s + stride·m


def member_runs(step: StudyStep, tag: str, world: Path, seed: int, count: int,
                command: Callable[[Path, list[str]], list[str]]) -> list[Path]:  # fmt: skip
    """`count` more world models beside `world` (its name's "world-model" → "member<m>"):
    `command(out, extra)` is the command that trained `world`, with its seed changed and the
    world model started from its own initialisation (TrainingConfig.world_model_fresh)."""
    out = []
    for m in range(1, count + 1):
        run = world.with_name(world.name.replace("world-model", f"member{m}"))
        extra = ["--seed", str(seed + MEMBER_SEED_STRIDE * m), "--set", "world_model_fresh=true"]
        step(f"train-{tag}-{run.name}", command(run, extra), run / ".done")
        out.append(run)
    return out


def drift(step: StudyStep, tag: str, run: Path, start: Path, members: list[Path]) -> None:
    """research.variants.refine_drift of the refined `run` against `start` (the run
    refinement started from: its policy, and its counterfactual set's frames) into
    RUN/drift.json."""
    argv = py(str(ROOT / "research/variants/refine_drift.py"), "--run", str(run),
              "--start", str(start),
              "--json", str(run / "drift.json"))  # fmt: skip
    if members:
        argv += ["--members", *map(str, members)]
    step(f"drift-{tag}-{run.name}", argv, run / "drift.json")


def read_drift(run: Path) -> dict | None:
    path = run / "drift.json"
    return json.loads(path.read_text()) if path.is_file() else None


def drift_table(rows: list[dict]) -> str:
    """Markdown: per refined model (mean ± std over its rows' seeds), how far the plan moved and
    how the imagined terms and uncertainties changed; "" when no row has a drift."""
    models: dict[str, list[dict]] = {}
    for row in rows:
        if row.get("drift"):
            models.setdefault(row["model"], []).append(row["drift"])
    if not models:
        return ""

    lines = ["| refined model | seeds | \\|Δ steering\\| | \\|Δ throttle\\| | Δ Σ imagined speed | "
             "Δ Σ p(collision) | Δ Σ uncertainty (of) | members' spread of Σ speed, start → "
             "refined | of Σ p(collision) |",
             "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for model, drifts in models.items():
        moved = [[d["moved"][k] for d in drifts] for k in ("steering_abs", "throttle_abs")]
        change = [[d["change"][k] for d in drifts] for k in ("speed", "p_collision", "u_total")]
        of = np.mean([d["start"]["u_total"] for d in drifts])
        spread = ["—", "—"]
        if all("speed_spread" in d["start"] for d in drifts):
            spread = [
                f"{np.mean([d['start'][k] for d in drifts]):.2f} → "
                f"{np.mean([d['refined'][k] for d in drifts]):.2f}"
                for k in ("speed_spread", "p_collision_spread")
            ]
        lines.append(
            f"| {model} | {len(drifts)} | {cell(moved[0], '.3f')} | {cell(moved[1], '.3f')} | "
            f"{cell(change[0], '+.2f')} | {cell(change[1], '+.3f')} | {cell(change[2], '+.2f')} "
            f"({of:.1f}) | "
            f"{spread[0]} | {spread[1]} |"
        )
    return "\n".join(lines)
