"""Drive a finished study's policies again on other held-out placements: the same rows, new laps.

    python -m research.redrive research/runs/dirl_s11/results.json --out research/runs/s11_wide
    python -m research.redrive RESULTS.json --out DIR --tracks 100-199 --seconds 30 --models IL,...

Why: a study's table is only as sure as its placements are many. Per-placement completion
differences between two policies are heavy-tailed (a third exactly 0, a third beyond ±0.4), so
25 placements judge a DIRL − IL difference of ±0.05 by the placements' own noise; 100 placements
× 30 s (completion is mostly decided in the first 30 s) resolve about ±0.03 per seed for the same
driving time. Retraining to get there would cost the study's 9 hours again; the policies are on
disk, so this drives each of them on the new placements and writes the study's table from the
new laps, with the same row names, seeds and paired comparison (research/dirl_table.py).

Each distinct policy file (by its sha256) is driven once and its laps kept under OUT/evals, so
rows with identical weights (an iteration whose selection kept the re-imitated policy) share
their laps and an interrupted run continues where it stopped.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # run as a file, from any directory: the repository on the path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.provenance import environment
from carrt.arg_types import parse_int_list
from carrt.errors import EXIT_USAGE, UserError
from carrt.policy import file_sha256
from research.dirl_table import BEFORE_REFINEMENT, comparison, table
from training.sim_data import EVALUATION_TRACKS


def policy_of(row: dict) -> Path:
    """The ONNX file a study row was driven with. Rows written since 2026-11-26 name it; older
    ones are found the way research/dirl_sim.py laid them out: a row "before refinement" is its
    selection's `imitated` candidate, a row whose run has a selection is the selected policy,
    any other the run's own."""
    if row.get("policy"):
        return Path(row["policy"])
    run = Path(row["run"])
    if row["model"].endswith(BEFORE_REFINEMENT):
        return run / "selected" / "candidates" / "imitated.onnx"
    selected = run / "selected" / "policy.onnx"
    return selected if selected.is_file() else run / "policy.onnx"


def held_out_tracks(text: str) -> str:
    """Only evaluation placements: a re-drive on placements training saw would judge nothing."""
    tracks = set(parse_int_list(text, "tracks"))
    if not tracks or not tracks <= EVALUATION_TRACKS:
        outside = sorted(tracks - EVALUATION_TRACKS)[:5]
        raise UserError(
            f"--tracks {text}: {outside} not held out for evaluation "
            f"({min(EVALUATION_TRACKS)}-{max(EVALUATION_TRACKS)})"
        )
    return text


def drive(onnx: Path, out: Path, a: argparse.Namespace) -> dict:
    """`carrt eval` of one policy into `out` (kept: a second call reads it)."""
    if not out.is_file():
        log = out.with_suffix(".log")
        cmd = [sys.executable, "-m", "carrt", "eval", "--model", str(onnx), "--layout", a.layout,
               "--tracks", a.tracks, "--seconds", str(a.seconds), "--seeds", "0",
               "--jobs", str(a.jobs), "--json", str(out) + ".part"]  # fmt: skip
        with log.open("w") as f:
            rc = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT).returncode
        if rc != 0:
            raise UserError(f"carrt eval of {onnx} failed (exit {rc}); its output: {log}")
        Path(str(out) + ".part").replace(out)  # whole or absent: a kill leaves no half file
    return json.loads(out.read_text())


def parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="python -m research.redrive", description=__doc__.split("\n")[0]
    )
    p.add_argument("results", help="a study's results.json (research/dirl_sim.py)")
    p.add_argument("--out", required=True, help="directory for evals/, results.json, table.md")
    p.add_argument("--tracks", default="100-199", help="held-out placements (default 100-199)")
    p.add_argument("--seconds", type=float, default=30.0, help="simulated s per placement")
    p.add_argument("--layout", default="hard")
    p.add_argument("--models", default="", help="comma-separated row names (default: all)")
    p.add_argument("--jobs", type=int, default=2, help="simulator processes")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    a = parse(argv)
    try:
        held_out_tracks(a.tracks)
        study = json.loads(Path(a.results).read_text())
        rows = study["rows"]
        wanted = [m.strip() for m in a.models.split(",") if m.strip()]
        rows = [r for r in rows if not wanted or r["model"] in wanted]
        if not rows:
            raise UserError(f"{a.results}: no rows named {wanted}")
        policies = [policy_of(r) for r in rows]
        missing = [str(p) for p in policies if not p.is_file()]
        if missing:
            raise UserError(f"policy files not found: {', '.join(missing[:3])}")
    except (OSError, KeyError, json.JSONDecodeError) as exc:
        print(f"error: {a.results}: not a study's results.json ({exc})", file=sys.stderr)
        return EXIT_USAGE
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    out = Path(a.out)
    (out / "evals").mkdir(parents=True, exist_ok=True)
    digests = [file_sha256(p)[:16] for p in policies]
    todo = len({d for d in digests if not (out / "evals" / f"{d}.json").is_file()})
    print(f"redrive: {len(rows)} rows, {len(set(digests))} distinct policies ({todo} to drive) "
          f"on {a.tracks} × {a.seconds:g} s", flush=True)  # fmt: skip
    started, driven, new_rows = time.monotonic(), 0, []
    for i, (row, onnx, digest) in enumerate(zip(rows, policies, digests, strict=True), 1):
        target = out / "evals" / f"{digest}.json"
        fresh = not target.is_file()
        try:
            result = drive(onnx, target, a)
        except UserError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return EXIT_USAGE
        driven += fresh
        eta = (time.monotonic() - started) / driven * (todo - driven) if driven else 0.0
        agg = result["aggregate"]
        print(f"  [{i}/{len(rows)}] σ {row['demo_noise']:g} seed {row['seed']} {row['model']}: "
              f"completion {agg['completion_ratio']['mean']:.2f}, "
              f"{agg['collisions_per_min']['mean']:.1f} collisions/min"
              + (f" (ETA {eta / 60:.0f} min)" if fresh else " (kept)"), flush=True)  # fmt: skip
        new_rows.append({**row, "policy": str(onnx), "aggregate": agg, "runs": result["runs"]})
    report = (
        table(new_rows) + "\n\nPaired by seed (model − baseline, each seed's mean over the "
        "held-out placements; mean ± std over seeds):\n\n" + comparison(new_rows)
    )
    redriven = {"from": a.results, "tracks": a.tracks, "seconds": a.seconds, "layout": a.layout}
    payload = {"config": study.get("config"), "redriven": redriven, "rows": new_rows,
               "environment": environment()}  # fmt: skip
    (out / "results.json").write_text(json.dumps(payload, indent=2) + "\n")
    (out / "table.md").write_text(report + "\n")
    print("\n" + report + f"\n\nwritten: {out / 'results.json'}, {out / 'table.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
