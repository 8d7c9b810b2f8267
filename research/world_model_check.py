"""Which world model knows what the actions do? Each form trained on the same drives, each scored
on the same held-out starts by the counterfactual check (issue 59, item 3).

    python -m research.world_model_check                                  # ~45 min, 1 core
    python -m research.world_model_check --set world_model_steps=1500 --set seeds=0

Why: refinement and planning trust the world model's answer to "what if the car did this
instead?". The check (research/variants/counterfactual.py) measured the paper's Reveries-net
failing it: the steering gradient's sign agreed with the truth 38-50 % of the time. One cause the
code shows is structural: the actions enter only the first GRU layer and every head reads states
the image set (training/models.WorldModel). `world_action_inputs=all` feeds them to every layer
and every head; this check says whether that, on the same data, steps and seed, meets the
issue's targets. The data are what a real car records, on TRAINING placements only:

    demos     the scripted expert as a sloppy person (σ demo_noise, an error that lasts
              demo_noise_tau s) on train_tracks: crashes from the person's own errors
    weak      a weak imitation policy (weak_steps of imitation on the first weak_frames of them)
    drives    that policy driving train_tracks alone with the study's exploration noise (every
              crash labelled, auto-reset): crashes from varied actions
    set       the held-out starts (`carrt.sim.counterfactual`, VALIDATION placements
              counterfactual_tracks, never trained on): the plans of a fixed policy
              (counterfactual_policy, the shipped one) and eight alternatives, with what each
              really did
    <form>    per form and seed, a world model of demos + drives (world_model_steps, one
              torch thread), scored on the set

Every step leaves a marker in OUT and is skipped when run again (a training stopped midway
resumes from its checkpoint). The table and `json` (date, machine, data, steps, every number of
the check per form and seed) are written at the end; `--report` writes them from what finished.
The go/no-go rule (TARGETS) is the issue's; "first" (the paper's) is always trained and reported.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

if __package__ in (None, ""):  # run as a file, from any directory: the repository on the path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from carrt.errors import EXIT_USAGE, UserError
from carrt.settings import apply_sets
from research.check_summary import NEAR, TARGETS, summary
from research.dirl_steps import ROOT, py, top_up
from research.paths import at_root
from research.study_steps import NotRun, StudyStep

FORMS = ("first", "all", "ground")
# "ground" is 3b (research/ground_model.py): exact motion, a hazard map on the floor; the others
# are training/config.py's world_action_inputs of the Reveries-net.
GROUND = "ground"
# Not a candidate: the ground model's motion (each ground run's speed response) with the
# placement's true hazard map, a ceiling for what any learnt map could reach with that motion.
PERFECT = "ground-perfect-map"
SHORT = {"steering_sign_agreement": "sign", "ordered_right": "order", "collision_auroc": "AUROC",
         "rank_correlation": "ρ"}  # fmt: skip
STOP = "no world model passes: by the issue's stop rule the full study does not run"


@dataclass
class WorldModelCheckConfig:
    """Every number of the check (`--set FIELD=VALUE`; tuples comma-separated)."""

    out: str = "research/runs/world_model_check"  # steps, logs, runs (not in git)
    json: str = "research/results/world_model_check.json"  # the results ("" : OUT's only)
    forms: tuple[str, ...] = FORMS  # "first" always (the paper's)
    seeds: tuple[int, ...] = (0, 1, 2, 3, 4)  # training seeds (model init, batch order)
    profile: str = "cpu"
    layout: str = "hard"
    train_tracks: str = "1000-1039"  # every recording (training placements)
    demo_episodes: int = 6  # per placement
    demo_noise: float = 0.5  # σ on the expert's commands: a sloppy person, who crashes
    demo_noise_tau: float = 0.5  # s the error lasts
    weak_frames: int = 1500  # the weak policy's demonstrations (whole episodes, in name order)
    weak_steps: int = 600  # its imitation steps
    drive_seconds: float = 40.0  # simulated s per placement of the weak policy's drives
    explore_fraction: float = 0.8  # the study's exploration noise (research/study_config.py)
    explore_amplitude: float = 0.8
    explore_hold_s: tuple[float, ...] = (0.5, 1.5)
    world_model_steps: int = 3000
    ground_steps: int = 3000  # the ground model's hazard-map steps (research/ground_model.py)
    counterfactual_tracks: str = "200-219"  # validation placements: never trained on
    counterfactual_starts: int = 5  # per placement
    counterfactual_policy: str = "carrt/assets/demo_policy.onnx"  # whose plans start the sets
    threads: int = 1  # torch threads of each training and of the scoring
    jobs: int = 1  # simulator processes


def problems(cfg: WorldModelCheckConfig) -> list[str]:
    """What is out of range, one line each."""
    out = []
    if not cfg.forms or any(f not in FORMS for f in cfg.forms):
        out.append(f"forms: {cfg.forms} (each one of {', '.join(FORMS)})")
    if not cfg.seeds:
        out.append("seeds: at least one")
    for name in ("demo_episodes", "weak_frames", "weak_steps", "world_model_steps", "ground_steps",
                 "counterfactual_starts", "threads", "jobs"):  # fmt: skip
        if getattr(cfg, name) < 1:
            out.append(f"{name}: {getattr(cfg, name)} (1 or more)")
    if not cfg.drive_seconds > 0 or len(cfg.explore_hold_s) != 2:
        out.append("drive_seconds > 0 and explore_hold_s=MIN,MAX")
    if not (ROOT / cfg.counterfactual_policy).is_file():
        out.append(f"counterfactual_policy: {cfg.counterfactual_policy}: no such file")
    return out


def train_cmd(cfg: WorldModelCheckConfig, episodes: list[Path], out: Path, seed: int,
              *sets: str) -> list[str]:  # fmt: skip
    """research/variants/train.py (carrt-train with the research variants): one run, one thread."""
    common = (f"threads={cfg.threads}", "progress=false", "figures=false", "eval_every=0",
              "counterfactual_starts=0", *sets)  # fmt: skip
    return py(str(ROOT / "research/variants/train.py"), "--episodes", *map(str, episodes),
              "--out", str(out), "--profile", cfg.profile, "--seed", str(seed),
              *(arg for item in common for arg in ("--set", item)))  # fmt: skip


def paths_of(cfg: WorldModelCheckConfig) -> dict[str, Path]:
    """Where each step writes: the recordings, the held-out set, the weak policy, each run."""
    out = Path(cfg.out)
    paths = {"demos": out / "data/demos", "drives": out / "data/drives", "weak": out / "runs/weak",
             "set": out / "data/counterfactual.npz"}  # fmt: skip
    for seed in cfg.seeds:
        for form in cfg.forms:
            paths[f"{form}-seed{seed}"] = out / "runs" / f"{form}-seed{seed}"
    return paths


def run_steps(cfg: WorldModelCheckConfig, step, paths: dict[str, Path]) -> None:
    """Every step in order, each skipped when its marker exists."""
    out = Path(cfg.out)
    demos, drives, weak = paths["demos"], paths["drives"], paths["weak"]
    step("demos", py("-m", "training.sim_data", "demos", "--out", str(demos), "--tracks",
         cfg.train_tracks, "--layouts", cfg.layout, "--episodes", str(cfg.demo_episodes),
         "--noise", str(cfg.demo_noise), "--noise-tau", str(cfg.demo_noise_tau),
         "--jobs", str(cfg.jobs)), demos / ".done")  # fmt: skip
    step("weak", train_cmd(cfg, top_up(demos, cfg.weak_frames), weak, cfg.seeds[0],
         f"imitation_steps={cfg.weak_steps}", "world_model_steps=0", "refine_steps=0"),
         weak / ".done")  # fmt: skip
    lo, hi = cfg.explore_hold_s
    noise = (f"noise.fraction={cfg.explore_fraction}", f"noise.amplitude={cfg.explore_amplitude}",
             f"noise.hold_min_s={lo}", f"noise.hold_max_s={hi}")  # fmt: skip
    step("drives", py("-m", "training.sim_data", "drives", "--model", str(weak / "policy.onnx"),
         "--out", str(drives), "--tracks", cfg.train_tracks, "--layouts", cfg.layout,
         "--seconds", str(cfg.drive_seconds), "--jobs", str(cfg.jobs), "--explore",
         *(arg for item in noise for arg in ("--set", item))), drives / ".done")  # fmt: skip
    held_out = paths["set"]
    step("set", py("-m", "carrt.sim.counterfactual", "--model",
         str(ROOT / cfg.counterfactual_policy), "--layout", cfg.layout, "--tracks",
         cfg.counterfactual_tracks, "--starts", str(cfg.counterfactual_starts), "--out",
         str(held_out)), out / "data/.done-counterfactual")  # fmt: skip
    for seed in cfg.seeds:
        for form in cfg.forms:
            run = paths[f"{form}-seed{seed}"]
            if form == GROUND:
                step(f"train-{form}-seed{seed}", py("-m", "research.ground_model", "train",
                     "--episodes", str(demos), str(drives), "--out", str(run), "--seed",
                     str(seed), "--steps", str(cfg.ground_steps), "--threads",
                     str(cfg.threads)), run / ".done")  # fmt: skip
                continue
            step(f"train-{form}-seed{seed}", train_cmd(cfg, [demos, drives], run, seed,
                 "imitation_steps=0", f"world_model_steps={cfg.world_model_steps}",
                 "refine_steps=0", "export=false", f"world_action_inputs={form}"),
                 run / ".done")  # fmt: skip


def score_runs(cfg: WorldModelCheckConfig, paths: dict[str, Path]) -> dict[str, dict]:
    """Each trained world model scored on the held-out set, by form and seed."""
    import torch

    from research import ground_model
    from research.variants.counterfactual import load, score
    from training import checkpoint as ck
    from training.config import TrainingConfig

    torch.set_num_threads(cfg.threads)
    data = load(paths["set"])
    scored = {}
    for seed in cfg.seeds:
        for form in cfg.forms:
            run = paths.get(f"{form}-seed{seed}")
            if form == GROUND and run is not None and (run / ".done").is_file():
                # the refinement weights the Reveries-net runs use (TrainingConfig's defaults)
                model = ground_model.load(run / "ground_model.pt")
                full = score(model, data, TrainingConfig())
                scored[f"{form}-seed{seed}"] = {"form": form, "seed": seed, **summary(full),
                                                "check": full}  # fmt: skip
                if "pose" in data:  # the set knows each start's pose: the ceiling too
                    ceiling = ground_model.PerfectMapModel(model.speed_response, data)
                    top = score(ceiling, data, TrainingConfig())
                    row = {"form": PERFECT, "seed": seed, **summary(top), "check": top}
                    scored[f"{PERFECT}-seed{seed}"] = row
                continue
            elif run is not None and (run / "world_model.pt").is_file():
                world_model, ckpt = ck.load_world_model(run / "world_model.pt")
                full = score(world_model, data, SimpleNamespace(**ckpt["config"]))
            else:
                continue
            scored[f"{form}-seed{seed}"] = {"form": form, "seed": seed, **summary(full),
                                            "check": full}  # fmt: skip
    return scored


def constant_baselines(data: dict) -> dict[str, float]:
    """What a model that ignores the frame scores at best: the same answer at every start (the
    majority sign of the truth), for the two judged numbers where that is possible. A form
    near these has learnt a track-wide rule ("steering one way is safer"), not the place."""
    import numpy as np

    from research.variants.counterfactual import GRADIENT_PAIRS, true_objective
    from training.config import TrainingConfig

    names, weights = list(data["meta"]["sequences"]), TrainingConfig()
    truth = true_objective(data, weights.refine_w_speed, weights.refine_w_collision)

    def best_constant(diff) -> float | None:  # None where the truth ties everywhere
        decided = diff[np.abs(diff) > 1e-6]
        return float(max((decided > 0).mean(), (decided < 0).mean())) if len(decided) else None

    up, down = GRADIENT_PAIRS["steering"]
    near = [best_constant(truth[:, names.index(n)] - truth[:, 0]) for n in NEAR if n in names]
    near = [x for x in near if x is not None]  # left out as the check leaves them out
    return {
        "steering_sign_agreement": best_constant(
            truth[:, names.index(up)] - truth[:, names.index(down)]
        ),
        "ordered_right": sum(near) / len(near) if near else None,
    }


def data_summary(paths: dict[str, Path]) -> dict:
    """Episodes, frames and collision-labelled frames of each recording; the set's size."""
    import numpy as np

    from carrt.episodes.reader import list_episodes, read_episode

    out = {}
    for name in ("demos", "drives"):
        if not paths[name].is_dir():
            continue
        eps = [read_episode(p) for p in list_episodes([str(paths[name])])]
        out[name] = {"episodes": len(eps), "frames": sum(e.n for e in eps),
                     "collision_frames": int(sum(int(e.collision.sum()) for e in eps))}  # fmt: skip
    if paths["set"].is_file():
        with np.load(paths["set"]) as d:
            hit = d["true_collision"].max(axis=2)
            out["set"] = {"starts": int(hit.shape[0]), "sequences": int(hit.shape[1]),
                          "collide": float(hit.mean())}  # fmt: skip
    return out


def shown(cfg: WorldModelCheckConfig) -> tuple[str, ...]:
    """The forms in the table: the candidates, and the ground model's perfect-map ceiling."""
    return (*cfg.forms, PERFECT) if GROUND in cfg.forms else cfg.forms


def by_form(cfg: WorldModelCheckConfig, scored: dict[str, dict]) -> dict[str, dict]:
    """Per form: each judged number's mean over the seeds, and the rule's verdict on the means
    (a form passes when its means meet all four targets)."""
    out = {}
    for form in shown(cfg):
        rows = [r for r in scored.values() if r["form"] == form]
        if not rows:
            continue
        means = {}
        for key in TARGETS:
            values = [r[key] for r in rows if r[key] is not None and r[key] == r[key]]
            means[key] = sum(values) / len(values) if values else None
        meets = {k: v is not None and v >= TARGETS[k] for k, v in means.items()}
        out[form] = {"seeds": [r["seed"] for r in rows], "mean": means, "meets": meets,
                     "passes": all(meets.values())}  # fmt: skip
    return out


def cell(values: list) -> str:
    values = [v for v in values if v is not None]
    if not values:
        return "—"
    mean = sum(values) / len(values)
    if len(values) == 1:
        return f"{mean:.2f}"
    spread = (sum((v - mean) ** 2 for v in values) / (len(values) - 1)) ** 0.5
    return f"{mean:.2f} ± {spread:.2f}"


def table(cfg: WorldModelCheckConfig, scored: dict[str, dict]) -> str:
    """Markdown: per form, the four judged numbers (mean ± std over seeds) and whether it passes."""
    forms = by_form(cfg, scored)
    lines = ["| world model | seeds | steering sign agreement (≥ 0.8) | alternatives ordered right "
             "(≥ 0.8) | collision AUROC (≥ 0.9) | rank correlation ρ (≥ 0.6) | steering sign, "
             "centred | speed error m/s (constant) | imagined risk plan / steer +0.6 (true) | "
             "passes (means over seeds) |",
             "|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for form in shown(cfg):
        rows = [r for r in scored.values() if r["form"] == form]
        if not rows:
            continue

        def col(key: str, rows=rows) -> str:
            return cell([r[key] for r in rows])

        risk = [r["risk_plan_vs_steer+0.6"] for r in rows]
        imagined = " / ".join(cell([x["imagined_risk"][i] for x in risk]) for i in (0, 1))
        true = " / ".join(cell([x["true_collision"][i] for x in risk]) for i in (0, 1))
        verdict = "yes" if forms[form]["passes"] else "no"
        missed = [k for k, ok in forms[form]["meets"].items() if not ok]
        verdict += f" (misses {', '.join(SHORT[k] for k in missed)})" if missed else ""
        verdict = "ceiling, not a candidate: " + verdict if form == PERFECT else verdict
        lines.append(
            f"| {form} | {len(rows)} | {col('steering_sign_agreement')} | {col('ordered_right')} "
            f"| {col('collision_auroc')} | {col('rank_correlation')} | "
            f"{col('steering_sign_agreement_centred')} | {col('speed_mae')} "
            f"({col('speed_mae_constant')}) | {imagined} ({true}) | {verdict} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m research.world_model_check",
                                description=__doc__.split("\n")[0])  # fmt: skip
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="a WorldModelCheckConfig field (research/world_model_check.py)",
    )
    p.add_argument("--report", action="store_true", help="the table from what finished; no run")
    a = p.parse_args(argv)
    try:
        where = "WorldModelCheckConfig in research/world_model_check.py"
        cfg = apply_sets(WorldModelCheckConfig(), a.set, where)
    except UserError as exc:
        p.error(str(exc))
    if "first" not in cfg.forms:  # the paper's is always reported
        cfg = dataclasses.replace(cfg, forms=("first", *cfg.forms))
    for problem in problems(cfg):
        print(f"world_model_check: error: {problem}", file=sys.stderr)
        return EXIT_USAGE
    cfg = dataclasses.replace(cfg, out=at_root(cfg.out))
    started = time.monotonic()
    plan = 4 + len(cfg.seeds) * len(cfg.forms)
    step = StudyStep(Path(cfg.out), plan, report_only=a.report, cwd=ROOT)
    paths = paths_of(cfg)
    try:
        run_steps(cfg, step, paths)
    except NotRun as exc:  # --report: the table from the steps that finished
        print(f"world_model_check: not run yet from {exc} on", file=sys.stderr)
    except UserError as exc:
        print(f"world_model_check: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    scored = score_runs(cfg, paths)
    from bench.provenance import environment

    forms = by_form(cfg, scored)
    passing = [form for form, f in forms.items() if f["passes"] and form != PERFECT]
    baselines = {}
    if paths["set"].is_file():
        from research.variants.counterfactual import load

        baselines = constant_baselines(load(paths["set"]))
    results = {
        "config": dataclasses.asdict(cfg), "targets": TARGETS, "near_alternatives": NEAR,
        "environment": environment(), "data": data_summary(paths),
        "wall_s": time.monotonic() - started, "passing_forms": passing, "forms": forms,
        "constant_baselines": baselines, "rows": list(scored.values()),
    }  # fmt: skip
    text = table(cfg, scored)
    if baselines and None not in baselines.values():
        text += ("\n\nThe same answer at every start (the truth's majority sign) scores: steering "
                 f"sign {baselines['steering_sign_agreement']:.2f}, alternatives ordered right "
                 f"{baselines['ordered_right']:.2f}.")  # fmt: skip
    verdict = f"passes: {', '.join(passing)}" if passing else STOP
    Path(cfg.out, "results.json").write_text(json.dumps(results, indent=1) + "\n")
    Path(cfg.out, "table.md").write_text(text + "\n\n" + verdict + "\n")
    if cfg.json:
        Path(at_root(cfg.json)).parent.mkdir(parents=True, exist_ok=True)
        Path(at_root(cfg.json)).write_text(json.dumps(results, indent=1) + "\n")
    print(text)
    print(verdict)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
