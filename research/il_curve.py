"""How driving improves with demonstrations: imitation on a quarter, a half and all of the
shipped policy's expert data, and the take-over iteration on top, judged by driving.

    python -m research.il_curve --work demo-policy-work      # after training/demo_policy.py

Each point trains imitation exactly as `training/demo_policy.py` does (same steps, batch,
profile and seed) on the first k placements of its demonstrations (whole placements, so a
smaller set is fewer placements, not thinner ones), and is evaluated like every policy here:
`carrt eval` on the held-out placements 100-104 of the `hard` layout, 60 simulated seconds each,
seeds 0 and 1, auto-reset after collisions. The full-data imitation (il1) and the take-over
iteration (il2) are the demo pipeline's own runs. Writes curve.json, curve.md and curve.png
into the work directory; every trained point is kept and skipped when run again.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a file, from any directory: the repository on the path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.provenance import environment
from carrt.episodes.reader import list_episodes, read_episode
from research.paths import at_root
from training import demo_policy

FRACTIONS = (0.25, 0.5)
EVAL = {"layout": "hard", "tracks": (100, 101, 102, 103, 104), "seconds": 60.0, "seeds": (0, 1)}


def subset(expert: Path, fraction: float, out: Path) -> int:
    """Symlinks to the episodes of the first `fraction` of the placements; returns frames."""
    episodes = [read_episode(p) for p in list_episodes([str(expert)])]
    seeds = sorted({ep.meta["sim"]["track_seed"] for ep in episodes})
    keep = set(seeds[: max(1, round(len(seeds) * fraction))])
    out.mkdir(parents=True, exist_ok=True)
    frames = 0
    for ep in episodes:
        if ep.meta["sim"]["track_seed"] in keep:
            link = out / ep.path.name
            if not link.exists():
                link.symlink_to(ep.path.resolve(), target_is_directory=True)
            frames += ep.n
    return frames


def judge(model: Path, jobs: int) -> dict:
    from carrt.sim.evaluate import evaluate

    return evaluate(model, jobs=jobs, **EVAL)["aggregate"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m research.il_curve", description=__doc__)
    p.add_argument("--work", default="demo-policy-work",
                   help="training/demo_policy.py's --work (relative: the repo's)")  # fmt: skip
    p.add_argument("--steps", type=int, default=8000)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    work, py = Path(at_root(a.work)).resolve(), sys.executable
    expert = work / "expert"
    rows = []
    for fraction in FRACTIONS:
        data, run = work / f"expert-{fraction:g}", work / f"il-{fraction:g}"
        frames = subset(expert, fraction, data)
        demo_policy.run(demo_policy.imitation(py, [data], run, a, a.steps), run / ".done")
        rows.append({"model": f"imitation, {fraction:.0%} of placements", "frames": frames,
                     **judge(run / "policy.onnx", a.jobs)})  # fmt: skip
    full = sum(read_episode(p).n for p in list_episodes([str(expert)]))
    rows.append({"model": "imitation, all placements", "frames": full,
                 **judge(work / "il1" / "policy.onnx", a.jobs)})  # fmt: skip
    takeovers = sum(read_episode(p).n for p in list_episodes([str(work / "takeovers")]))
    rows.append({"model": "imitation + take-overs", "frames": full + takeovers,
                 **judge(work / "il2" / "policy.onnx", a.jobs)})  # fmt: skip
    curve = {"eval": EVAL, "rows": rows, "environment": environment()}
    (work / "curve.json").write_text(json.dumps(curve, indent=2) + "\n")
    lines = ["| model | frames | completion | collisions / min | avg m/s | laps |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for r in rows:
        cells = [f"{r[k]['mean']:.2f} ± {r[k]['std']:.2f}" for k in
                 ("completion_ratio", "collisions_per_min", "average_speed", "laps")]  # fmt: skip
        lines.append(f"| {r['model']} | {r['frames']:,} | " + " | ".join(cells) + " |")
    (work / "curve.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    plot(rows, work / "curve.png")
    return 0


def plot(rows: list[dict], path: Path) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 3.2), layout="constrained")
    left, right = fig.subplots(1, 2)
    imitation = [r for r in rows if r["model"].startswith("imitation,")]
    for ax, key, title in ((left, "completion_ratio", "completion ratio"),
                           (right, "collisions_per_min", "collisions / min")):  # fmt: skip
        xs = [r["frames"] / 1000 for r in imitation]
        ax.errorbar(xs, [r[key]["mean"] for r in imitation], [r[key]["std"] for r in imitation],
                    marker="o", capsize=3, label="imitation")  # fmt: skip
        last = rows[-1]
        ax.errorbar([last["frames"] / 1000], [last[key]["mean"]], [last[key]["std"]], marker="s",
                    capsize=3, label="+ take-overs")  # fmt: skip
        ax.set_xlabel("training frames (thousands)")
        ax.set_title(title)
        ax.grid(alpha=0.3)
    left.legend()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    raise SystemExit(main())
