"""The study's table and figure (research/dirl_sim.py): the paper's metrics, mean ± std.

Driving numbers are pooled over every (seed, held-out placement) run of a model, so the spread
says how much a user's result varies; the world model's counterfactual numbers are the mean over
seeds (one check per trained world model). The comparison table pairs each DIRL row with its
baselines seed by seed, which is the spread the paper's "better than IL" is judged against.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

METRICS = (("completion_ratio", ".2f"), ("collisions_per_min", ".1f"), ("average_speed", ".2f"))
# racing (carrt eval's laps per minute of driving and progress per metre driven): runs written
# before they existed have neither, and their cells say "—"
RACING = (("laps_per_min", ".2f"), ("progress_per_metre", ".2f"))
CHECKS = (("collision_auroc", ".2f"), ("rank_correlation", ".2f"))


def cell(values, fmt: str) -> str:
    """mean ± std of the finite values ("—" when none); a signed format signs the mean only."""
    vals = [float(v) for v in values if v is not None and np.isfinite(v)]
    if not vals:
        return "—"
    if len(vals) == 1:
        return format(vals[0], fmt)
    return f"{format(float(np.mean(vals)), fmt)} ± {format(float(np.std(vals)), fmt.lstrip('+'))}"


def groups(rows: list[dict]) -> dict[tuple, list[dict]]:
    """(demo noise, model) → its rows, in the order the study ran them."""
    out: dict[tuple, list[dict]] = {}
    for r in rows:
        out.setdefault((r["demo_noise"], r["model"]), []).append(r)
    return out


def table(rows: list[dict]) -> str:
    lines = [
        "| demo noise σ | model | seeds | frames | completion | collisions / min | avg m/s "
        "| laps / min | progress / m "
        "| WM collision AUROC | WM rank corr. | WM speed MAE (const.) | chosen by driving |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for (sigma, model), rs in groups(rows).items():
        runs = [run for r in rs for run in r["runs"]]
        checks = [r["counterfactual"] or {} for r in rs]
        driving = " | ".join(cell([run.get(k) for run in runs], f) for k, f in METRICS + RACING)
        world = " | ".join(cell([c.get(k) for c in checks], f) for k, f in CHECKS)
        mae = cell([c.get("speed_mae") for c in checks], ".2f")
        const = cell([c.get("speed_mae_constant") for c in checks], ".2f")
        speed = "—" if mae == "—" else f"{mae} ({const})"
        # which candidate each seed's selection kept (start: refinement rejected)
        chosen = ", ".join(r["chosen"] for r in rs if r.get("chosen")) or "—"
        lines.append(
            f"| {sigma:g} | {model} | {len(rs)} | {cell([r['frames'] for r in rs], '.0f')} "
            f"| {driving} | {world} | {speed} | {chosen} |"
        )
    return "\n".join(lines)


def il_at_frames_of(k: int | str) -> str:
    """The row name of imitation trained on as many frames as DIRL iteration k had (the study
    names its rows with it; the comparison finds them by it)."""
    return f"IL, frames of iter {k}"


BEFORE_REFINEMENT = " before refinement"
SEARCH_ROW = "DIRL search iter 1"  # iteration 1 refined by search (refine_search), not gradient


def before_refinement(k: int | str) -> str:
    """The row name of DIRL iteration k's policy after its imitation on the take-overs and
    before refinement (the study's ablation: what refinement adds beyond the take-overs)."""
    return f"DIRL iter {k}{BEFORE_REFINEMENT}"


def baselines(model: str) -> list[str]:
    """What a model is compared with, seed by seed: the paper's questions."""
    if model == SEARCH_ROW:  # does search beat the gradient, the start, more data?
        return ["DIRL iter 1", before_refinement(1), "IL", il_at_frames_of(1)]
    if model.startswith("DIRL -unc iter "):
        return [model.replace("DIRL -unc", "DIRL")]  # does the uncertainty term matter?
    if model.startswith("DIRL iter ") and model.endswith(BEFORE_REFINEMENT):
        k = model.removeprefix("DIRL iter ").removesuffix(BEFORE_REFINEMENT)
        return ["IL", il_at_frames_of(k)]  # do the take-overs alone beat more demonstrations?
    if model.startswith("DIRL iter "):
        k = model.removeprefix("DIRL iter ")
        # better than its start; than more data; than the take-overs without refinement?
        return ["IL", il_at_frames_of(k), before_refinement(k)]
    return []


def seed_means(rs: list[dict], key: str) -> dict[int, float]:
    """Each seed's mean of `key` over its runs; seeds whose runs lack it are left out."""
    return {
        r["seed"]: float(np.mean([run[key] for run in r["runs"]]))
        for r in rs
        if all(run.get(key) is not None for run in r["runs"])
    }


def comparison(rows: list[dict]) -> str:
    """Paired differences, model − baseline, per seed (mean over the same held-out placements),
    then mean ± std over seeds: the "by more than the seed spread" the paper's claim needs,
    without the placements' own spread (how hard each placement is) in it."""
    lines = [
        "| demo noise σ | model | against | seeds | Δ completion per seed | Δ completion "
        "| Δ collisions / min | Δ laps / min |",
        "|---|---|---|---|---|---|---|---|",
    ]
    by_key = groups(rows)
    for (sigma, model), rs in by_key.items():
        for base in baselines(model):
            if (sigma, base) not in by_key:
                continue
            deltas = {}
            for key in ("completion_ratio", "collisions_per_min", "laps_per_min"):
                mine, theirs = seed_means(rs, key), seed_means(by_key[(sigma, base)], key)
                deltas[key] = [mine[s] - theirs[s] for s in sorted(mine) if s in theirs]
            if not deltas["completion_ratio"]:
                continue
            per_seed = ", ".join(f"{d:+.2f}" for d in deltas["completion_ratio"])
            lines.append(
                f"| {sigma:g} | {model} | {base} | {len(deltas['completion_ratio'])} "
                f"| {per_seed} | {cell(deltas['completion_ratio'], '+.2f')} "
                f"| {cell(deltas['collisions_per_min'], '+.1f')} "
                f"| {cell(deltas['laps_per_min'], '+.2f')} |"
            )
    return "\n".join(lines)


def plot(rows: list[dict], path: Path,
         title: str = "IL and DIRL iterations, mean ± std over seeds") -> None:  # fmt: skip
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9.0, 4.2))
    for (sigma, model), rs in groups(rows).items():
        frames = [r["frames"] for r in rs]
        completion = [r["aggregate"]["completion_ratio"]["mean"] for r in rs]
        marker = "s" if model.startswith("IL") else ("x" if "-unc" in model else "o")
        marker = "^" if model.endswith(BEFORE_REFINEMENT) else marker
        marker = "d" if model == SEARCH_ROW else marker
        ax.errorbar(np.mean(frames), np.mean(completion), yerr=np.std(completion), fmt=marker,
                    capsize=3, label=f"σ {sigma:g} {model}")  # fmt: skip
    ax.set_xlabel("frames of data")
    ax.set_ylabel("completion ratio (held-out placements)")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    if rows:  # a --report before any model finished has nothing to label
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # off the points
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
