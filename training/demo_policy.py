"""Reproduce the policy that `make demo` drives with, from nothing but this repository.

    python training/demo_policy.py                    # → carrt/assets/demo_policy.onnx
    python training/demo_policy.py --work /tmp/dp --threads 2

Why a script and not a download: the demo must show a policy this project trained, and a user
must be able to check that claim. Three of the project's own commands, top to bottom:

1. `carrt teleop --sim --expert auto --record --random-start`: the scripted expert drives the
   `hard` layout (8 obstacles) on five obstacle placements, one lap per episode from a random
   place at rest, with the paper's noise injection half of the time (the expert recovers).
2. `training/iterate.py --profile cpu`, imitation only, 3000 steps, seed 0 (twice the study's
   data and steps: in the study, at our training budget, imitation drove better than every
   DIRL policy, so the demo ships imitation; about 25 minutes on 2 cores).
3. `python -m export --int8`: the int8 file (1.7 MB instead of 6.5) is what ships; its error
   against the float model is checked on recorded frames before it is written (and it drove
   the held-out placements as well as the float model did).

Finally the policy drives a held-out placement (never in the data) and the paper's metrics are
printed. Seeds are fixed; torch and onnxruntime versions decide whether the bytes are identical.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "carrt" / "assets" / "demo_policy.onnx"
TRAIN_TRACKS = (0, 1, 2, 3, 4)
HELD_OUT_TRACK = 101


def run(argv: list[str]) -> None:
    print("$ " + " ".join(argv), flush=True)
    code = subprocess.call(argv, cwd=ROOT)
    if code != 0:
        raise SystemExit(f"demo_policy: command failed with exit {code}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="training/demo_policy.py", description=__doc__.split("\n")[0])
    p.add_argument("--out", default=str(SHIPPED), help=f"default: {SHIPPED.relative_to(ROOT)}")
    p.add_argument("--work", default="demo-policy-work", help="data and training run directory")
    p.add_argument("--episodes", type=int, default=12, help="expert episodes per placement")
    p.add_argument("--steps", type=int, default=3000, help="imitation optimizer steps")
    p.add_argument("--threads", type=int, default=1, help="torch threads")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    work, py = Path(a.work), sys.executable
    data, train = work / "expert", work / "il"

    for track in TRAIN_TRACKS:
        if not (data / f".done-{track}").exists():
            run([py, "-m", "carrt", "teleop", "--sim", "--expert", "auto", "--record",
                 "--random-start", "--seed", str(track), "--layout", "hard", "--track-seed",
                 str(track), "--episodes", str(a.episodes), "--laps", "1", "--out", str(data),
                 "--duration", "100000"])  # fmt: skip
            (data / f".done-{track}").touch()
    run([py, str(ROOT / "training" / "iterate.py"), "--episodes", str(data), "--out", str(train),
         "--profile", "cpu", "--seed", str(a.seed), "--set", f"imitation_steps={a.steps}",
         "--set", "world_model_steps=0", "--set", "refine_steps=0",
         "--set", f"threads={a.threads}", "--set", "progress=false"])  # fmt: skip
    fp32 = work / "demo_policy.onnx"
    run([py, "-m", "export", str(train / "policy.pt"), "-o", str(fp32), "--episodes", str(data),
         "--int8"])  # fmt: skip
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(fp32.with_suffix(".int8.onnx"), out)
    print(f"wrote {out} ({out.stat().st_size:,} bytes)")
    run([py, "-m", "carrt", "drive", "--sim", "--autopilot", "--model", str(out), "--layout",
         "hard", "--track-seed", str(HELD_OUT_TRACK), "--duration", "60"])  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
