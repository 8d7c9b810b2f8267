"""The paper's simulation study on carrt's simulator: imitation learning against DIRL.

    python -m bench.dirl_sim                       # the cpu-profile study (about 45 min on 2 cores)
    python -m bench.dirl_sim --quick               # the whole pipeline in minutes (tiny profile)
    python -m bench.dirl_sim --set seeds=0,1,2 --set iterations=3

Top to bottom, every step a real carrt / iterate.py command (logged under OUT/logs):

1. Demonstrations. The scripted expert drives the `hard` layout on TRAINING obstacle placements,
   recording through the real loop with the paper's noise injection (half of the time, the
   expert must recover), every episode starting from rest at a random place. The robustness
   setting records the same again with Gaussian noise of σ 0.5 and 1.0 on every expert command.
2. IL: iterate.py with the world model and refinement switched off (imitation only).
3. DIRL iteration 1: from IL, the world model on the same data, then refinement in imagination.
   DIRL -unc: the same world model, refinement without the uncertainty term.
4. DIRL iteration k > 1: the previous policy drives the training placements (auto-reset after
   every collision, the crashes recorded), the new episodes join the data, and iterate.py --init
   continues the world model on all of it and refines again.
5. Evaluation of every policy on HELD-OUT placements the training never saw: from the start line,
   `carrt drive --sim --autopilot`, the paper's metrics from the run (completion ratio = safe
   distance before the first collision / track length, capped at 1).

Output: OUT/results.json (every run), OUT/table.md (the paper's table, mean ± std over seeds)
and OUT/completion_vs_frames.png. Every step is skipped when its result exists, so running the
same command again after an interruption continues where it stopped.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@dataclass
class StudyConfig:
    """Every number of the study. The defaults are what the README's table was measured with."""

    out: str = "bench/results/dirl_sim"
    profile: str = "cpu"  # model sizes (training/profiles.py)
    seeds: tuple[int, ...] = (0, 1)  # training seeds: model init, batch order, DIRL drives
    layout: str = "hard"  # 8 obstacles
    train_tracks: tuple[int, ...] = (0, 1, 2, 3, 4)  # obstacle placements for data
    eval_tracks: tuple[int, ...] = (100, 101, 102, 103, 104)  # held out: never trained on
    expert_episodes: int = 6  # per training placement, one lap each from a random place
    demo_noise: tuple[float, ...] = (0.0, 0.5, 1.0)  # σ on the expert's commands (robustness)
    iterations: int = 2  # DIRL iterations (seed chains at σ = 0)
    robustness_iterations: int = 1  # DIRL iterations for σ > 0 (first seed only)
    drive_episodes: int = 2  # per training placement per DIRL iteration (a crash ends one)
    imitation_steps: int = 1200
    world_model_steps: int = 1200  # iteration 1 (from scratch)
    world_model_steps_next: int = 500  # later iterations continue the previous world model
    refine_steps: int = 200
    eval_seconds: float = 30.0  # simulated seconds per held-out placement (a lap is ~7 s)
    threads: int = 1  # torch threads per training process
    jobs: int = 2  # seed chains trained side by side

    def iterate_overrides(self) -> list[str]:
        return [f"threads={self.threads}", "progress=false", "figures=false"]


QUICK = dict(
    out="bench/results/dirl_sim_quick", profile="tiny", seeds=(0,), train_tracks=(0,),
    eval_tracks=(100,), expert_episodes=2, demo_noise=(0.0, 0.5), iterations=2,
    drive_episodes=1, imitation_steps=30, world_model_steps=30, world_model_steps_next=10,
    refine_steps=10, eval_seconds=10.0,
)  # fmt: skip


# ------------------------------------------------------------------------------- plumbing
class Step:
    """Runs one command with its output in a log file; a failed command stops the study."""

    def __init__(self, cfg: StudyConfig) -> None:
        self.out = Path(cfg.out)
        self.logs = self.out / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)

    def __call__(self, name: str, argv: list[str]) -> None:
        log = self.logs / f"{name}.log"
        started = time.monotonic()
        with log.open("w") as fh:
            fh.write("$ " + " ".join(argv) + "\n")
            fh.flush()
            code = subprocess.call(argv, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT)
        took = time.monotonic() - started
        print(f"  {name}: exit {code} in {took:.0f} s", flush=True)
        if code != 0:
            raise SystemExit(f"dirl_sim: {name} failed (exit {code}); see {log}")


def carrt_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "carrt", *args]


def iterate_cmd(cfg: StudyConfig, episodes: list[Path], out: Path, *extra: str) -> list[str]:
    sets = [arg for item in cfg.iterate_overrides() for arg in ("--set", item)]
    return [
        sys.executable, str(ROOT / "training" / "iterate.py"), "--episodes",
        *map(str, episodes), "--out", str(out), *sets, *extra,
    ]  # fmt: skip


def count_frames(dirs: list[Path]) -> int:
    from carrt.episodes.reader import iter_episodes

    return sum(ep.n for d in dirs for ep in iter_episodes(d))


# ------------------------------------------------------------------------------- the steps
def record_per_track(cfg: StudyConfig, step: Step, name: str, data: Path, argv_for) -> None:
    """One recording command per training placement into `data`, with a marker per finished
    placement, so a rerun records only the placements it had not finished."""
    for track in cfg.train_tracks:
        done = data / f".done-{track}"
        if not done.exists():
            step(f"{name}-track{track}", argv_for(track))
            done.touch()


def demonstrations(cfg: StudyConfig, step: Step, sigma: float) -> Path:
    """Expert episodes on every training placement; σ > 0: the imperfect demonstrator."""
    data = Path(cfg.out) / "data" / f"expert-noise{sigma:g}"
    record_per_track(cfg, step, f"expert-noise{sigma:g}", data, lambda track: carrt_cmd(
        "teleop", "--sim", "--expert", "auto", "--record", "--random-start",
        "--expert-noise", str(sigma), "--seed", str(track), "--layout", cfg.layout,
        "--track-seed", str(track), "--episodes", str(cfg.expert_episodes),
        "--laps", "1", "--out", str(data), "--duration", "100000",
    ))  # fmt: skip
    return data


def train(cfg: StudyConfig, step: Step, name: str, run: Path, argv: list[str]) -> Path:
    if not (run / "policy.onnx").is_file():
        step(name, argv)
    return run


def drive_episodes(cfg: StudyConfig, step: Step, name: str, model: Path, data: Path, seed: int):
    """The current policy drives the training placements, crashes and resets recorded."""
    record_per_track(cfg, step, name, data, lambda track: carrt_cmd(
        "drive", "--sim", "--autopilot", "--model", str(model), "--record",
        "--random-start", "--seed", str(seed * 1000 + track), "--layout", cfg.layout,
        "--track-seed", str(track), "--episodes", str(cfg.drive_episodes), "--laps", "1",
        "--out", str(data), "--duration", "100000",
    ))  # fmt: skip


def evaluate(cfg: StudyConfig, step: Step, name: str, model: Path) -> dict:
    """The paper's metrics on the held-out placements, averaged over them."""
    where = Path(cfg.out) / "eval" / name
    runs = []
    for track in cfg.eval_tracks:
        metrics = where / f"track{track}" / "sim_metrics.json"
        if not metrics.is_file():
            step(
                f"eval-{name}-track{track}",
                carrt_cmd(
                    "drive", "--sim", "--autopilot", "--model", str(model), "--layout",
                    cfg.layout, "--track-seed", str(track), "--duration", str(cfg.eval_seconds),
                    "--out", str(metrics.parent),
                ),
            )  # fmt: skip
        runs.append(json.loads(metrics.read_text()))
    laps = [t for r in runs for t in r["lap_times"]]
    minutes = sum(r["driving_time"] for r in runs) / 60.0
    return {
        "average_speed": _mean([r["average_speed"] for r in runs]),
        "top_speed": _mean([r["top_speed"] for r in runs]),
        "completion_ratio": _mean([r["completion_ratio"] for r in runs]),
        "lap_time": _mean(laps) if laps else None,
        "clean_laps": len(laps),
        "collisions_per_min": sum(r["collisions"] for r in runs) / minutes if minutes else None,
        "runs": len(runs),
    }


def action_sensitivity(run: Path, start_policy: Path, data: Path, shift: float = 0.3) -> dict:
    """What `run`'s world model imagines when the start policy's steering is moved by ±shift.

    Refinement can only improve on imitation where the world model's speed, collision and
    uncertainty depend on the actions the right way round; this probe says whether they do.
    Returns per quantity the mean over up to 64 expert windows at (−shift, 0, +shift).
    """
    import torch

    from training import checkpoint as ck
    from training.data import Normalisation, WindowDataset, load_episodes
    from training.models import PolicyNet, WorldModel
    from training.profiles import get_profile
    from training.refine import imagine
    from training.world_training import Targets

    c = ck.load_checkpoint(run / "world_model.pt")
    profile, norm = get_profile(c["profile"]), Normalisation.from_dict(c["normalisation"])
    world_model = WorldModel(profile)
    world_model.set_normalisation(norm)
    world_model.load_state_dict(c["world_model"])
    world_model.freeze()
    policy = PolicyNet(profile)
    policy.set_normalisation(norm)
    policy.load_state_dict(ck.load_checkpoint(start_policy)["policy"])
    policy.eval()
    episodes = load_episodes([str(data)])
    windows = WindowDataset(episodes, profile.horizon, predict_size=profile.predict_size)
    picks = range(0, len(windows), max(1, len(windows) // 64))
    batch = torch.utils.data.default_collate([windows[i] for i in list(picks)[:64]])
    out: dict[str, list[float]] = {"speed": [], "p_collision": [], "uncertainty": []}
    with torch.no_grad():
        mu, _ = policy(batch["image"], batch["speed"])
        for delta in (-shift, 0.0, shift):
            actions = mu.clone()
            actions[..., 0] = (actions[..., 0] + delta).clamp(-1.0, 1.0)
            seen = imagine(
                world_model, Targets(norm), batch["image"], batch["speed"], actions, 10.0
            )
            out["speed"].append(float(seen["speed"].mean()))
            out["p_collision"].append(float(seen["p_collision"].mean()))
            u = seen["u_image"] + seen["u_speed"] + seen["u_collision"]
            out["uncertainty"].append(float(u.mean()))
    return out


def _mean(values: list[float]) -> float:
    return float(sum(values) / len(values)) if values else 0.0


def chain(cfg: StudyConfig, sigma: float, seed: int, iterations: int, ablation: bool) -> list:
    """IL → DIRL 1 (→ -unc) → DIRL 2 … for one demonstration noise and one seed."""
    step = Step(cfg)
    tag = f"noise{sigma:g}-seed{seed}"
    runs = Path(cfg.out) / "runs" / tag
    expert = Path(cfg.out) / "data" / f"expert-noise{sigma:g}"
    rows = []

    def row(model: str, iteration: int, run: Path, data: list[Path]) -> None:
        result = evaluate(cfg, step, f"{tag}-{model.replace(' ', '')}", run / "policy.onnx")
        rows.append({
            "model": model, "iteration": iteration, "demo_noise": sigma, "seed": seed,
            "frames": count_frames(data), "run": str(run), **result,
        })  # fmt: skip
        print(f"  [{tag}] {model}: completion {result['completion_ratio']:.2f}, "
              f"{result['average_speed']:.2f} m/s", flush=True)  # fmt: skip

    seed_arg = ["--seed", str(seed), "--profile", cfg.profile]
    il = train(cfg, step, f"train-{tag}-il", runs / "il", iterate_cmd(
        cfg, [expert], runs / "il", *seed_arg, "--set", f"imitation_steps={cfg.imitation_steps}",
        "--set", "world_model_steps=0", "--set", "refine_steps=0",
    ))  # fmt: skip
    row("IL", 0, il, [expert])

    data = [expert]
    previous = il
    for k in range(1, iterations + 1):
        if k > 1:
            drives = Path(cfg.out) / "data" / f"drive-{tag}-iter{k - 1}"
            drive_episodes(cfg, step, f"drive-{tag}-iter{k - 1}", previous / "policy.onnx",
                           drives, seed)  # fmt: skip
            data = [*data, drives]
        wm_steps = cfg.world_model_steps if k == 1 else cfg.world_model_steps_next
        run = train(cfg, step, f"train-{tag}-dirl{k}", runs / f"dirl{k}", iterate_cmd(
            cfg, data, runs / f"dirl{k}", *seed_arg, "--init", str(previous),
            "--set", f"world_model_steps={wm_steps}", "--set", f"refine_steps={cfg.refine_steps}",
        ))  # fmt: skip
        row(f"DIRL iter {k}", k, run, data)
        rows[-1]["sensitivity"] = action_sensitivity(run, il / "policy.pt", expert)
        if k == 1 and ablation:
            # The same world model, the same start policy: only the uncertainty term differs.
            unc = train(cfg, step, f"train-{tag}-unc1", runs / "unc1", iterate_cmd(
                cfg, data, runs / "unc1", *seed_arg,
                "--init", str(run / "checkpoints" / "world_model.pt"), "--no-uncertainty",
                "--set", "world_model_steps=0", "--set", f"refine_steps={cfg.refine_steps}",
            ))  # fmt: skip
            row("DIRL -unc iter 1", 1, unc, data)
        previous = run
    return rows


# ------------------------------------------------------------------------------- reporting
def table(rows: list[dict]) -> str:
    """Mean ± std over seeds, grouped by demonstration noise and model, in run order."""
    import numpy as np

    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["demo_noise"], r["model"]), []).append(r)

    def cell(values, fmt):
        vals = [v for v in values if v is not None]
        if not vals:
            return "—"
        if len(vals) == 1:
            return format(vals[0], fmt)
        return f"{format(float(np.mean(vals)), fmt)} ± {format(float(np.std(vals)), fmt)}"

    lines = [
        "| demo noise σ | model | seeds | frames | avg speed (m/s) | top speed (m/s) "
        "| completion ratio | lap time (s) | collisions / min |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for (sigma, model), rs in groups.items():
        lines.append(
            f"| {sigma:g} | {model} | {len(rs)} | {cell([r['frames'] for r in rs], '.0f')} "
            f"| {cell([r['average_speed'] for r in rs], '.2f')} "
            f"| {cell([r['top_speed'] for r in rs], '.2f')} "
            f"| {cell([r['completion_ratio'] for r in rs], '.2f')} "
            f"| {cell([r['lap_time'] for r in rs], '.2f')} "
            f"| {cell([r['collisions_per_min'] for r in rs], '.1f')} |"
        )
    return "\n".join(lines)


def sensitivity_table(rows: list[dict]) -> str:
    """The world models' answers to the steering probe (action_sensitivity), one row each."""
    lines = [
        "| demo noise σ | model | seed | imagined speed (m/s) at steering −0.3 / IL / +0.3 "
        "| p(collision) | uncertainty u_i+u_s+u_c |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        s = r.get("sensitivity")
        if not s:
            continue
        cells = [
            " / ".join(f"{v:.3f}" for v in s[k]) for k in ("speed", "p_collision", "uncertainty")
        ]
        lines.append(
            f"| {r['demo_noise']:g} | {r['model']} | {r['seed']} | " + " | ".join(cells) + " |"
        )
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    lines: dict[tuple, list[dict]] = {}
    for r in rows:
        if r["model"].startswith("DIRL -unc"):
            continue
        lines.setdefault((r["demo_noise"], r["seed"]), []).append(r)
    for (sigma, seed), rs in sorted(lines.items()):
        rs = sorted(rs, key=lambda r: r["iteration"])
        ax.plot([r["frames"] for r in rs], [r["completion_ratio"] for r in rs], "o-",
                label=f"σ {sigma:g}, seed {seed}")  # fmt: skip
    unc = [r for r in rows if r["model"].startswith("DIRL -unc")]
    if unc:
        ax.scatter([r["frames"] for r in unc], [r["completion_ratio"] for r in unc], marker="x",
                   color="k", label="DIRL -unc iter 1", zorder=3)  # fmt: skip
    ax.set_xlabel("frames of data")
    ax.set_ylabel("completion ratio (held-out placements)")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title("IL (first point) then DIRL iterations")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ------------------------------------------------------------------------------- main
def parse(argv: list[str] | None) -> StudyConfig:
    p = argparse.ArgumentParser(prog="python -m bench.dirl_sim", description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="tiny profile, one seed: minutes")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="any StudyConfig field; tuples comma-separated (seeds=0,1,2)")  # fmt: skip
    a = p.parse_args(argv)
    cfg = StudyConfig(**(QUICK if a.quick else {}))
    fields = {f.name: f for f in dataclasses.fields(StudyConfig)}
    for item in a.set:
        name, _, text = item.partition("=")
        if name not in fields:
            p.error(f"--set {name}: unknown field (see StudyConfig in bench/dirl_sim.py)")
        current = getattr(cfg, name)
        try:
            if isinstance(current, tuple):
                kind = float if name == "demo_noise" else int
                value = tuple(kind(v) for v in text.split(",") if v.strip())
            else:
                value = type(current)(text)
        except ValueError:
            p.error(f"--set {item}: not a valid value for {name}")
        cfg = dataclasses.replace(cfg, **{name: value})
    return cfg


def main(argv: list[str] | None = None) -> int:
    cfg = parse(argv)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(json.dumps(dataclasses.asdict(cfg), indent=2) + "\n")
    started = time.monotonic()
    print(f"dirl_sim: profile {cfg.profile}, seeds {list(cfg.seeds)}, out {out}", flush=True)

    step = Step(cfg)
    for sigma in cfg.demo_noise:
        demonstrations(cfg, step, sigma)

    jobs = [(0.0, seed, cfg.iterations, True) for seed in cfg.seeds if 0.0 in cfg.demo_noise]
    jobs += [(s, cfg.seeds[0], cfg.robustness_iterations, False) for s in cfg.demo_noise if s]
    with ThreadPoolExecutor(max_workers=max(1, cfg.jobs)) as pool:
        results = list(pool.map(lambda j: chain(cfg, *j), jobs))
    rows = [r for rs in results for r in rs]

    report = (
        table(rows) + "\n\nSteering probe of each DIRL world model:\n\n" + sensitivity_table(rows)
    )
    (out / "results.json").write_text(json.dumps(
        {"config": dataclasses.asdict(cfg), "rows": rows,
         "wall_s": time.monotonic() - started}, indent=2) + "\n")  # fmt: skip
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
