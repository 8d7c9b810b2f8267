"""The end of an iteration on rank 0, after its export: held-out metrics, figures, report.md.

report.md is what a person reads before putting the policy on the car: which data, how far
each stage got, whether the world model beats the trivial baselines on episodes it never saw,
and whether the export (training/export_step.py) passed its parity check. metrics.json holds
the same numbers for tools.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from training.export_step import Exported
from training.figures import loss_curves, reveries, uncertainty_vs_error
from training.report_metrics import held_out_metrics


def _fmt(x, digits: int = 4) -> str:
    if x is None:
        return "—"
    if isinstance(x, float):
        return "n/a" if not math.isfinite(x) else f"{x:.{digits}g}"
    return str(x)


def report_run(
    cfg, out: Path, exported: Exported, *, policy, world_model, norm, train_eps, val_eps,
    episodes, digest, results, iteration, device, writer=None, world_size=1, world=None,
    extras=(),
) -> dict:  # fmt: skip
    """Metrics, figures and report of a finished, exported iteration; `extras` are research
    variants' report sections (training.training_run.Variants.report), called after the export."""
    from training.data import WindowDataset, placement_key, takeover_labels

    held_out = bool(val_eps)
    eval_eps = val_eps if held_out else train_eps
    profile = cfg.profile_obj
    metrics, arrays = held_out_metrics(
        policy, world_model, eval_eps, profile, device, limit=cfg.eval_windows,
        takeovers_as_collisions=cfg.takeovers_as_collisions,
    )  # fmt: skip
    metrics["held_out"] = held_out
    if writer is not None:
        for k, v in metrics.items():
            if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
                writer.add_scalar(f"held_out/{k}", v, iteration)

    figures: dict[str, str] = {}
    # the held-out windows, decoded once for the reveries figure and the research extras
    windows = None
    if (cfg.figures and world_model is not None) or extras:
        windows = WindowDataset(
            eval_eps, profile.horizon, predict_size=profile.predict_size,
            takeovers_as_collisions=cfg.takeovers_as_collisions,
        )  # fmt: skip
    if cfg.figures:
        fig_dir = out / "figures"
        histories = {name: r.history for name, r in results.items()}
        loss_curves(histories, fig_dir / "loss_curves.png")
        figures = {"Loss curves": "figures/loss_curves.png"}
        if world_model is not None:
            uncertainty_vs_error(arrays, fig_dir / "uncertainty_vs_error.png")
            reveries(world_model, windows, device, fig_dir / "reveries.png")
            figures |= {
                "Uncertainty against error (held-out)": "figures/uncertainty_vs_error.png",
                "Reveries: real future, predicted, uncertainty": "figures/reveries.png",
            }

    sections: dict[str, tuple] = {}
    for extra in extras:
        found = extra(cfg, out, policy=policy, world_model=world_model, windows=windows,
                      device=device)  # fmt: skip
        if found is not None:
            sections[found[0]] = found[1:]
    stages = {
        name: {
            "steps": r.steps,
            "final": r.final(),
            "samples_per_s": r.samples_per_s if r.seconds > 0 else None,
            "seconds_this_invocation": r.seconds,
        }
        for name, r in results.items()
    }
    data = {
        "episodes": len(episodes),
        "frames": int(sum(ep.n for ep in episodes)),
        "train_episodes": [ep.name for ep in train_eps],
        "held_out_episodes": [ep.name for ep in val_eps],
        "train_placements": len({placement_key(ep) for ep in train_eps}),
        "held_out_placements": sorted({placement_key(ep) for ep in val_eps}),
        "train_frames": int(sum(ep.n for ep in train_eps)),
        "held_out_frames": int(sum(ep.n for ep in val_eps)),
        "collision_frames": int(sum(int(ep.collision.sum()) for ep in episodes)),
        "takeover_frames": int(sum(int(takeover_labels(ep).sum()) for ep in episodes)),
        "train_digest": digest,
        "world_model_episodes": None if world is None else _world_data(world),
    }
    record = {
        "iteration": iteration, "profile": cfg.profile, "world_size": world_size,
        "device": str(device), "data": data, "stages": stages,
        "metrics": metrics, "figures": figures, "export": exported.info,
        "normalisation": norm.to_dict(),
        **{key: value for key, (value, _lines) in sections.items()},
    }  # fmt: skip
    (out / "metrics.json").write_text(json.dumps(_finite(record), indent=2, default=str) + "\n")
    extra_md = [line for _value, lines in sections.values() for line in lines]
    (out / "report.md").write_text(render(cfg, record, exported.lines, extra_md))
    lines = [f"wrote {out / 'report.md'}", *exported.lines]
    return {"metrics": metrics, "record": record, "lines": lines}


def _world_line(w: dict | None) -> list[str]:
    if w is None:
        return []
    return [
        f"- the world model learnt other episodes (--world-episodes): {w['episodes']} "
        f"({w['frames']} frames, {w['collision_frames']} labelled collision; "
        f"{w['train_frames']} trained on, {w['held_out_frames']} held out); its held-out "
        "metrics below are on the policy's held-out episodes"
    ]


def _world_data(world) -> dict:
    """What the world model learnt when it was not the policy's episodes (--world-episodes)."""
    return {
        "episodes": len(world.all),
        "frames": int(sum(ep.n for ep in world.all)),
        "train_frames": int(sum(ep.n for ep in world.train)),
        "held_out_frames": int(sum(ep.n for ep in world.val)),
        "collision_frames": int(sum(int(ep.collision.sum()) for ep in world.all)),
    }


def render(cfg, r: dict, export_lines: list[str], extra_md: list[str] = ()) -> str:
    d, m = r["data"], r["metrics"]
    src = "held-out episodes" if m.get("held_out") else "TRAINING episodes (no held-out split)"
    if cfg.dirl:
        title = f"# carrt DIRL iteration {r['iteration']} — `{cfg.out}`"
        unc = f", uncertainty term {'off (-unc ablation)' if cfg.no_uncertainty else 'on'}"
    else:
        title, unc = f"# carrt iteration {r['iteration']}: imitation — `{cfg.out}`", ""
    labels = " (collisions for the world model)" if cfg.dirl and cfg.takeovers_as_collisions else ""
    md = [
        title,
        "",
        f"Profile `{cfg.profile}`, {r['world_size']} process(es) on {r['device']}, "
        f"seed {cfg.seed}, init `{cfg.init or '—'}`{unc}.",
        "",
        "## Data",
        "",
        f"- episodes: {d['episodes']} ({d['frames']} frames; {d['collision_frames']} frames "
        f"labelled collision, {d['takeover_frames']} in the 0.5 s before a take-over"
        f"{labels})",
        f"- split by placement: {len(d['train_episodes'])} train episodes "
        f"({d.get('train_placements', '?')} placements, {d['train_frames']} frames), "
        f"{len(d['held_out_episodes'])} held out ({d['held_out_frames']} frames) on "
        f"{', '.join(d.get('held_out_placements', [])) or '—'}",
        *_world_line(d.get("world_model_episodes")),
        f"- training data digest: `{d['train_digest']}`",
        "",
        "## Stages",
        "",
        "| stage | steps | samples/s | final loss | final parts (mean of last logged steps) |",
        "|---|---|---|---|---|",
    ]
    for name, s in r["stages"].items():
        final = dict(s["final"])
        loss = final.pop("loss", None)
        parts = ", ".join(f"{k} {_fmt(v, 3)}" for k, v in final.items() if k != "grad_norm")
        md.append(
            f"| {name} | {s['steps']} | {_fmt(s['samples_per_s'], 3)} | {_fmt(loss)} | {parts} |"
        )
    if not cfg.dirl:
        md += [
            "",
            f"## Held-out metrics ({src})",
            "",
            "| metric | value |",
            "|---|---|",
            f"| imitation L1 of μ vs a* ({m.get('imitation_windows', 0)} collision-free windows) "
            f"| {_fmt(m.get('imitation_l1'))} |",
            f"| … of the steering | {_fmt(m.get('imitation_l1_steering'))} |",
            f"| … of the throttle | {_fmt(m.get('imitation_l1_throttle'))} |",
            "",
        ]
    else:
        md += _world_model_metrics(m, src)
    md += list(extra_md)
    if r["figures"]:
        md += ["## Figures", ""]
        md += [f"### {title}\n\n![{title}]({p})\n" for title, p in r["figures"].items()]
    md += ["## Export", "", *[f"    {line}" for line in export_lines], ""]
    md += ["## Config", "", "```json", json.dumps(_config(cfg), indent=2, default=str), "```"]
    if not cfg.dirl:
        md += ["", "The settings of the stages `carrt-train --dirl` adds are left out: this run "
               "did not use them."]  # fmt: skip
    md.append("")
    return "\n".join(md)


def _world_model_metrics(m: dict, src: str) -> list[str]:
    """The held-out table of a run with a world model, beside the baselines that give it meaning."""
    md = [
        "",
        f"## Held-out metrics ({src}: {m.get('windows', 0)} windows)",
        "",
        "| metric | value | baseline |",
        "|---|---|---|",
        f"| world model speed MAE (m/s, all H steps) | {_fmt(m.get('speed_mae_mps'))} | "
        f"{_fmt(m.get('baseline_speed_mae_mps'))} (constant speed) |",
        f"| speed MAE / baseline | {_fmt(m.get('speed_mae_over_baseline'), 3)} | < 1 beats it |",
        f"| collision AUROC of p̂ ({m.get('collision_steps', 0)} collision steps) | "
        f"{_fmt(m.get('collision_auroc'), 3)} | 0.5 (chance) |",
        f"| imitation L1 of μ vs a* ({m.get('imitation_windows', 0)} collision-free windows) | "
        f"{_fmt(m.get('imitation_l1'))} | — |",
        f"| Spearman(u_speed, speed error) | {_fmt(m.get('spearman_u_speed_vs_error'), 3)} | 0 |",
        f"| Spearman(u_image, image error) | {_fmt(m.get('spearman_u_image_vs_error'), 3)} | 0 |",
        f"| response of max p̂(collision) to steering ±0.6 | "
        f"{_fmt(m.get('response_steering_risk'), 3)} | 0: blind to steering |",
        f"| response of the predicted images to steering ±0.6 (their error: "
        f"{_fmt(m.get('response_image_error'), 3)}) | {_fmt(m.get('response_steering_image'), 3)} "
        f"| 0: blind to steering |",
        f"| response of the speed to full throttle against braking (m/s) | "
        f"{_fmt(m.get('response_throttle_speed'), 3)} | 0: blind to throttle |",
        "",
    ]
    if m.get("speed_mae_per_step"):
        ks = range(1, len(m["speed_mae_per_step"]) + 1)
        md += [
            "Speed MAE per step ahead (m/s):",
            "",
            "| | " + " | ".join(f"t+{k}" for k in ks) + " |",
        ]
        md.append("|---" * (len(ks) + 1) + "|")
        md.append(
            "| world model | " + " | ".join(_fmt(v, 3) for v in m["speed_mae_per_step"]) + " |"
        )
        md.append(
            "| constant speed | "
            + " | ".join(_fmt(v, 3) for v in m["baseline_mae_per_step"])
            + " |"
        )
        md.append("")
    return md


def _finite(x):
    """NaN/inf → null: metrics.json stays standard JSON for tools other than Python's."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


def _config(cfg) -> dict:
    """The run's settings; without `dirl`, less those only the world model and refinement read."""
    from dataclasses import asdict

    from training.config import dirl_fields

    config = asdict(cfg)
    if not cfg.dirl:
        for name in dirl_fields():
            config.pop(name, None)
    return config


def add_section(out: Path, key: str, value, lines: list[str]) -> None:
    """A finished run's report gains a section from a later step (what refinement changed, the
    driven comparison): `value` under `key` in metrics.json, `lines` (a `## ` heading first) in
    report.md before its figures and export. A section with the same heading is replaced, so a
    step run again leaves one."""
    metrics = out / "metrics.json"
    record = json.loads(metrics.read_text())
    record[key] = _finite(value)
    metrics.write_text(json.dumps(record, indent=2, default=str) + "\n")
    report = out / "report.md"
    text = report.read_text()
    heading = lines[0]
    body = "\n".join(lines).rstrip("\n") + "\n\n"
    if f"\n{heading}\n" in text:  # replace: up to the next heading of the same level
        before, rest = text.split(f"\n{heading}\n", 1)
        after = rest.split("\n## ", 1)
        tail = "## " + after[1] if len(after) > 1 else ""
        report.write_text(before + "\n" + body + tail)
        return
    for anchor in ("\n## Figures\n", "\n## Export\n"):
        if anchor in text:
            before, after = text.split(anchor, 1)
            report.write_text(before + "\n" + body + anchor.lstrip("\n") + after)
            return
    report.write_text(text.rstrip("\n") + "\n\n" + body)
