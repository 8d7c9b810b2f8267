"""Two policies driven on the same placements, compared run by run: is B better than A?

    carrt eval --model a.onnx --tracks 200-259 --seeds 0,1 --json a.json
    carrt eval --model b.onnx --tracks 200-259 --seeds 0,1 --json b.json
    python -m research.paired_eval a.json b.json [--json delta.json]

Why paired: placements differ from one another by more than two good policies do (one hard
placement costs a lap whoever drives it), so each of B's runs is compared with A's run on the
same placement and seed, and the spread that judges Δ is the paired one. Printed per metric:
mean Δ (B − A) over runs, its standard error, the per-seed means of Δ, and how many runs B
did better / worse. Both files must hold the same layout, seconds and (track, seed) runs. The
racing numbers (laps per minute, progress per metre) are compared where both files have them;
files written before `carrt eval` recorded them show "—" there.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a file, from any directory: the repository on the path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from carrt.errors import EXIT_USAGE, UserError
from research.json_file import read_json

METRICS = ("completion_ratio", "collisions_per_min", "average_speed")
RACING = ("laps_per_min", "progress_per_metre")  # absent from older carrt eval files


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)


def load(path: str) -> dict:
    """A `carrt eval --json` file; a missing or foreign one is a UserError."""
    data = read_json(path, "carrt eval file")
    if not isinstance(data, dict) or not isinstance(data.get("runs"), list) or not data["runs"]:
        raise UserError(f"{path}: not a carrt eval file (no runs)")
    for run in data["runs"]:
        if not all(_finite(run.get(k)) for k in METRICS):
            raise UserError(f"{path}: a run without finite {', '.join(METRICS)}")
    return data


def runs_by_key(data: dict) -> dict[tuple[int, int], dict]:
    return {(int(r["track"]), int(r["seed"])): r for r in data["runs"]}


def compare(a: dict, b: dict) -> dict:
    """{metric: {mean, se, per_seed, better, worse}} for B − A, paired by (track, seed)."""
    for key in ("layout", "seconds"):
        if a["config"].get(key) != b["config"].get(key):
            raise UserError(f"the files differ in {key}: {a['config'].get(key)} against "
                            f"{b['config'].get(key)}")  # fmt: skip
    ra, rb = runs_by_key(a), runs_by_key(b)
    if set(ra) != set(rb):
        raise UserError(f"the files hold different runs ({len(ra)} against {len(rb)} (track, "
                        "seed) pairs): drive both on the same placements and seeds")  # fmt: skip
    keys = sorted(ra)
    n, seeds = len(keys), sorted({seed for _, seed in keys})
    out = {"runs": n}
    for metric in METRICS + RACING:
        if not all(_finite(r[k].get(metric)) for r in (ra, rb) for k in keys):
            continue  # a racing number one of the files predates: rendered as "—"
        deltas = [rb[k][metric] - ra[k][metric] for k in keys]
        sd = statistics.stdev(deltas) if n > 1 else 0.0
        per_seed = {
            seed: statistics.fmean(d for (_, s), d in zip(keys, deltas, strict=True) if s == seed)
            for seed in seeds
        }
        sign = -1.0 if metric == "collisions_per_min" else 1.0
        out[metric] = {
            "a": statistics.fmean(ra[k][metric] for k in keys),
            "b": statistics.fmean(rb[k][metric] for k in keys),
            "delta": statistics.fmean(deltas),
            "se": sd / math.sqrt(n),
            "per_seed": per_seed,
            "better": sum(1 for d in deltas if sign * d > 0),
            "worse": sum(1 for d in deltas if sign * d < 0),
        }
    return out


def render(result: dict, a: str, b: str) -> str:
    lines = [f"B = {b} against A = {a}, {result['runs']} runs paired by placement and seed:"]
    for metric in METRICS + RACING:
        if metric not in result:
            lines.append(f"  {metric}: — (not in both files)")
            continue
        m = result[metric]
        seeds = ", ".join(f"{v:+.3f}" for v in m["per_seed"].values())
        lines.append(
            f"  {metric}: {m['a']:.3f} -> {m['b']:.3f}, delta {m['delta']:+.3f} ± {m['se']:.3f} "
            f"(SE); per seed {seeds}; B better in {m['better']}, worse in {m['worse']}"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m research.paired_eval", description=__doc__.split("\n")[0]
    )
    p.add_argument("a", help="carrt eval --json of the policy compared against")
    p.add_argument("b", help="carrt eval --json of the policy judged")
    p.add_argument("--json", help="also write the comparison here")
    args = p.parse_args(argv)
    try:
        a, b = load(args.a), load(args.b)
        result = compare(a, b)
    except UserError as exc:
        print(f"paired_eval: {exc}", file=sys.stderr)
        return EXIT_USAGE
    print(render(result, args.a, args.b))
    if args.json:
        record = {"a": args.a, "b": args.b, "config": a["config"], **result}
        Path(args.json).write_text(json.dumps(record, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
