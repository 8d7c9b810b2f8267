"""What an iteration changed, measured: how far refinement moved the plan on held-out frames,
and a policy against the one before it, driven on the simulator's validation placements.

`carrt-train --dirl` writes the refined policy beside the imitated one; `plan_change` says how
far it moved μ from the imitated policy's on the held-out frames (|Δμ|). That is not whether it
drives better: the loop (training/iterate.py, `--drive sim`) drives each iteration's policy and
the one before it, and each refined policy and its start, on validation placements 200-259 with
`carrt eval`'s own function (carrt.sim.evaluate, its runs in worker processes: the simulator
never runs in the process that holds torch), and puts the paper's metrics, mean ± std over the
runs, and their paired differences in the iteration's report.md. The test placements, 100-199,
are never driven here.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

from carrt.arg_types import parse_int_list
from carrt.errors import UserError

VALIDATION_TRACKS = range(200, 260)  # validation placements: chosen on, never the test 100-199
LAYOUT = "hard"  # the evaluation's layout (`carrt eval`'s default)
# (eval JSON key, column, digits): the paper's completion and collisions, and the racing number
METRICS = (
    ("completion_ratio", "completion", 2),
    ("collisions_per_min", "collisions / min", 1),
    ("laps_per_min", "laps / min", 2),
)
VALIDATION_FILE = "validation.json"  # in a run directory: its policy driven on DriveSpec's runs


class DriveFailed(RuntimeError):
    """The validation drives did not finish; the message says why in one line."""


@dataclass(frozen=True)
class DriveSpec:
    """Where the loop drives its comparisons: validation placements × seeds, seconds each."""

    tracks: str = "200-219"
    seconds: float = 30.0
    seeds: str = "0,1"
    jobs: int = 2

    def check(self) -> None:
        """Bad input as UserErrors: placements outside 200-259, no seeds, seconds ≤ 0."""
        tracks = parse_int_list(self.tracks, "compare-tracks")
        outside = sorted(set(tracks) - set(VALIDATION_TRACKS))
        if outside:
            raise UserError(
                f"--compare-tracks {self.tracks}: {outside[0]} is not a validation placement "
                "(200-259; 100-199 are the test placements, never chosen on)"
            )
        parse_int_list(self.seeds, "compare-seeds")
        if not (math.isfinite(self.seconds) and self.seconds > 0):
            raise UserError(f"--compare-seconds must be > 0, got {self.seconds}")

    def config(self) -> dict:
        """`carrt eval --json`'s config of these runs (a kept file must match it)."""
        return {
            "layout": LAYOUT,
            "tracks": parse_int_list(self.tracks, "tracks"),
            "seeds": parse_int_list(self.seeds, "seeds"),
            "seconds": float(self.seconds),
            "intervene": False,
        }

    def where(self) -> str:
        return (f"validation placements {self.tracks} (`{LAYOUT}`, {self.seconds:g} simulated s, "
                f"seeds {self.seeds})")  # fmt: skip

    def command(self, model: Path | str) -> list[str]:
        return ["carrt", "eval", "--model", str(model), "--layout", LAYOUT, "--tracks",
                self.tracks, "--seconds", f"{self.seconds:g}", "--seeds", self.seeds]  # fmt: skip


# ---------------------------------------------------------------- what refinement changed
def plan_change(cfg, before: Path, after: Path) -> dict:
    """|Δμ| between two policy checkpoints on the run's held-out frames (the training frames when
    nothing is held out), every step of the plan: mean and max per channel."""
    import torch

    from training import checkpoint as ck
    from training.data import WindowDataset, take
    from training.report_metrics import spread_indices
    from training.stage_data import read_episodes

    _all, train_eps, val_eps = read_episodes(cfg)
    episodes = val_eps or train_eps
    (old, _), (new, _) = ck.load_policy(before), ck.load_policy(after)
    profile = cfg.profile_obj
    windows = WindowDataset(episodes, profile.horizon, predict_size=profile.predict_size)
    idx = [int(i) for i in spread_indices(len(windows), cfg.eval_windows)]
    deltas = []
    with torch.no_grad():
        for start in range(0, len(idx), 64):
            batch = take(windows, idx[start : start + 64])
            mu_old, _ = old(batch["image"], batch["speed"])
            mu_new, _ = new(batch["image"], batch["speed"])
            deltas.append((mu_new - mu_old).abs())
    d = torch.cat(deltas) if deltas else torch.zeros(0, profile.horizon, 2)
    out = {"frames": len(idx), "held_out": bool(val_eps)}
    for c, name in enumerate(("steering", "throttle")):
        values = d[..., c]
        out[name] = {
            "mean_abs": float(values.mean()) if len(idx) else None,
            "max_abs": float(values.max()) if len(idx) else None,
            "first_step_mean_abs": float(values[:, 0].mean()) if len(idx) else None,
        }
    return out


def change_line(change: dict) -> str:
    """One sentence of `plan_change`'s numbers."""
    if not change["frames"]:
        return "no frames to compare the plans on"
    where = "held-out" if change["held_out"] else "training (nothing held out)"
    s, t = change["steering"], change["throttle"]
    return (
        f"|Δμ| on {change['frames']} {where} frames, every step of the plan: steering mean "
        f"{s['mean_abs']:.3g} (max {s['max_abs']:.3g}), throttle mean {t['mean_abs']:.3g} "
        f"(max {t['max_abs']:.3g})"
    )


# ------------------------------------------------------------------------ driving them
def drive_validation(model: Path, run: Path, spec: DriveSpec) -> dict:
    """`carrt eval` of `model` on `spec`'s runs, kept in run/validation.json: a file already
    there for the same runs is read, not driven again (the loop resumes)."""
    result = run / VALIDATION_FILE
    if result.is_file():
        cached = json.loads(result.read_text())
        if {k: cached.get("config", {}).get(k) for k in spec.config()} == spec.config():
            return cached
    from carrt.episodes.format import write_json_atomic
    from carrt.sim.evaluate import evaluate

    config = spec.config()
    try:  # the drives in worker processes: this one holds torch
        done = evaluate(str(model), LAYOUT, config["tracks"], spec.seconds, config["seeds"],
                        max(1, spec.jobs), isolated=True)  # fmt: skip
    except Exception as exc:  # a bad model, a broken worker: the loop ends in one line
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DriveFailed(f"carrt eval --model {model}: {why}") from exc
    write_json_atomic(result, done)
    return done


def _mean_std(values: list[float]) -> tuple[float, float]:
    n = len(values)
    mean = sum(values) / n
    return mean, math.sqrt(sum((v - mean) ** 2 for v in values) / n)


def paired(new: dict, old: dict) -> dict:
    """Per metric: each policy's mean ± std over the runs both drove, and new − old per run
    (same placement, same seed), mean ± std, with how many runs it was ahead and behind."""
    key = lambda r: (r["track"], r["seed"])  # noqa: E731
    theirs = {key(r): r for r in old["runs"]}
    both = [(r, theirs[key(r)]) for r in new["runs"] if key(r) in theirs]
    out: dict = {"runs": len(both)}
    for name, _column, _digits in METRICS:
        if not both:
            out[name] = None
            continue
        mine = [float(a[name]) for a, _ in both]
        base = [float(b[name]) for _, b in both]
        diff = [x - y for x, y in zip(mine, base, strict=True)]
        out[name] = {
            "new": _mean_std(mine), "old": _mean_std(base), "difference": _mean_std(diff),
            "ahead": sum(d > 0 for d in diff), "behind": sum(d < 0 for d in diff),
        }  # fmt: skip
    return out


def _pm(pair: tuple[float, float], digits: int, sign: bool = False) -> str:
    fmt = f"{'+' if sign else ''}.{digits}f"
    return f"{pair[0]:{fmt}} ± {pair[1]:.{digits}f}"


def summary(new_name: str, old_name: str, p: dict, spec: DriveSpec) -> str:
    """One line: new − old per metric, paired over the runs."""
    if not p["runs"]:
        return f"{new_name} against {old_name}: no runs in common"
    parts = ", ".join(f"{column} {_pm(p[name]['difference'], digits, sign=True)}"
                      for name, column, digits in METRICS)  # fmt: skip
    return (f"{new_name} against {old_name} on {spec.where()}: {parts} (paired over "
            f"{p['runs']} runs; mean ± std: a difference inside its std is none)")  # fmt: skip


def table(new_name: str, old_name: str, p: dict) -> list[str]:
    """The paper's metrics of both policies and their paired difference, as a markdown table."""
    if not p["runs"]:
        return []
    head = " | ".join(column for _name, column, _digits in METRICS)
    rows = [f"| policy | runs | {head} |", "|---|---|" + "---|" * len(METRICS)]
    for label, which in ((old_name, "old"), (new_name, "new")):
        cells = " | ".join(_pm(p[name][which], digits) for name, _c, digits in METRICS)
        rows.append(f"| {label} | {p['runs']} | {cells} |")
    cells = " | ".join(
        f"{_pm(p[name]['difference'], digits, sign=True)} ({p[name]['ahead']} up, "
        f"{p[name]['behind']} down)" for name, _c, digits in METRICS
    )  # fmt: skip
    rows.append(f"| {new_name} − {old_name}, per run | {p['runs']} | {cells} |")
    return rows
