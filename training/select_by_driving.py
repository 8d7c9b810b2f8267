"""Choose among policies by driving them on validation placements (simulator only).

    python -m training.select_by_driving --out runs/iter2/selected \
        --candidates start=runs/iter1/policy.pt runs/iter2/candidates/refine*.pt \
        --episodes data/ --tracks 200-219 --keep runs/iter2/world_model.pt

Why: refinement optimises the world model's imagined objective, which agrees only loosely with
driving (its rank correlation with the true objective is ~0.3, training/counterfactual.py), and
past some number of steps it makes the policy drive worse (the study: iterations 2-3 lost
completion to the policy they started from). So the refinement's candidates (the policy every
`refine_candidates_every` steps, and the policy it started from) are each exported and driven
by `carrt eval` on VALIDATION placements, and the best one is kept: refinement that does not
drive better is rejected. The score is completion − `collision_cost` × collisions per minute
(one collision a minute costs as much as 5 % of a lap at the default); a tie keeps the earlier
candidate (fewer refinement steps). On a real car the same choice is a person driving the
candidates; here the simulator does it on placements that are neither trained on nor the
evaluation ones (the `hard` layout's 100-124 are refused).

OUT gets policy.pt and policy.onnx of the chosen candidate (plus each --keep file, so OUT is a
run directory the next iteration's `--init` reads), candidates/<name>.onnx, selection.json with
every candidate's driving numbers, and nothing at all when something fails.

--reuse takes earlier selection.json files: a candidate whose checkpoint is byte-identical
(sha256) to one already driven there on the same layout, placements and seconds takes those
numbers instead of being driven again (driving is deterministic: the same weights drive the same
laps). The next iteration's "start" is this iteration's choice, so each selection after the first
drives one candidate fewer.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import shutil
import sys
from collections.abc import Iterator
from pathlib import Path

from carrt.errors import EXIT_USAGE, UserError
from carrt.policy import file_sha256
from training.sim_data import parse_tracks

COLLISION_COST = 0.05  # completion given up per collision/min in the score


def named_candidates(items: list[str]) -> list[tuple[str, Path]]:
    """'NAME=PATH' or 'PATH' (named by the file's stem) → [(name, path)], names unique."""
    out: list[tuple[str, Path]] = []
    for item in items:
        name, sep, path = item.partition("=")
        if not sep:
            name, path = Path(item).stem, item
        if not Path(path).is_file():
            raise UserError(f"--candidates: no such checkpoint: {path}")
        if any(name == seen for seen, _ in out):
            raise UserError(f"--candidates: the name {name!r} is given twice (use NAME=PATH)")
        out.append((name, Path(path)))
    if not out:
        raise UserError("--candidates: nothing to choose from")
    return out


def driven_before(selections: list[Path], layout: str, tracks: list[int], seconds: float) -> dict:
    """{checkpoint sha256: (aggregate, where)} of every candidate in earlier selection.json files
    driven on the same layout, placements and seconds (older files without sha256 give none)."""
    known: dict[str, tuple[dict, str]] = {}
    for path in selections:
        try:
            earlier = json.loads(Path(path).read_text())
        except (OSError, ValueError) as exc:
            raise UserError(f"--reuse: cannot read {path}: {exc}") from exc
        same = (earlier.get("layout"), earlier.get("tracks"), earlier.get("seconds"))
        if same != (layout, list(tracks), seconds):
            continue
        for c in earlier.get("candidates", []):
            if "sha256" in c and "aggregate" in c:
                known.setdefault(c["sha256"], (c["aggregate"], f"{path}:{c['name']}"))
    return known


def score(aggregate: dict, collision_cost: float = COLLISION_COST) -> float:
    """Higher is better: mean completion less the price of the collisions."""
    completion = aggregate["completion_ratio"]["mean"]
    return completion - collision_cost * aggregate["collisions_per_min"]["mean"]


def choose(driven: list[dict], collision_cost: float = COLLISION_COST) -> dict:
    """The candidate with the best score; the first one (fewest refinement steps) on a tie."""
    return max(driven, key=lambda c: (round(score(c["aggregate"], collision_cost), 9), -c["order"]))


@contextlib.contextmanager
def staged_folder(out: Path) -> Iterator[Path]:
    """A fresh folder beside OUT that replaces OUT only when the block finishes; on any error,
    Ctrl-C included, it is removed and OUT stays as it was."""
    staging = out.with_name(f".{out.name}.partial")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    try:
        yield staging
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    shutil.rmtree(out, ignore_errors=True)
    staging.rename(out)


def select(
    candidates: list[tuple[str, Path]],
    out: Path,
    episodes: list[str],
    *,
    layout: str = "hard",
    tracks: list[int],
    seconds: float = 30.0,
    jobs: int = 2,
    collision_cost: float = COLLISION_COST,
    keep: tuple[Path, ...] = (),
    reuse: tuple[Path, ...] = (),
) -> dict:
    from carrt.sim.evaluate import evaluate
    from export import export_policy

    with staged_folder(out) as staging:
        work = staging / "candidates"
        work.mkdir(parents=True)
        driven = []
        known = driven_before(list(reuse), layout, tracks, seconds)
        for order, (name, path) in enumerate(candidates):
            onnx = work / f"{name}.onnx"
            export_policy(path, onnx, episodes)
            digest = file_sha256(path)
            agg, reused = known.get(digest, (None, None))
            if agg is None:
                agg = evaluate(onnx, layout, tracks, seconds, (0,), jobs)["aggregate"]
            driven.append({"name": name, "order": order, "checkpoint": str(path),
                           "sha256": digest, "onnx": str(out / "candidates" / onnx.name),
                           "aggregate": agg, "score": score(agg, collision_cost),
                           "reused_from": reused})  # fmt: skip
            completion, per_min = agg["completion_ratio"]["mean"], agg["collisions_per_min"]["mean"]
            how = f" (same weights as {reused})" if reused else ""
            print(f"  {name}: completion {completion:.2f}, {per_min:.1f} collisions/min{how}",
                  flush=True)  # fmt: skip
        best = choose(driven, collision_cost)
        for extra in keep:
            shutil.copy2(extra, staging / extra.name)
        shutil.copy2(best["checkpoint"], staging / "policy.pt")
        shutil.copy2(work / f"{best['name']}.onnx", staging / "policy.onnx")
        selection = {
            "chosen": best["name"], "candidates": driven, "layout": layout, "tracks": tracks,
            "seconds": seconds, "collision_cost": collision_cost,
            "rule": "max completion − collision_cost × collisions/min; ties: the earlier candidate",
        }  # fmt: skip
        (staging / "selection.json").write_text(json.dumps(selection, indent=2) + "\n")
    return selection


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m training.select_by_driving", description=__doc__)
    p.add_argument("--candidates", nargs="+", required=True, metavar="[NAME=]CKPT")
    p.add_argument("--out", required=True, help="where the chosen policy goes")
    p.add_argument("--episodes", nargs="+", required=True, help="frames for the export's check")
    p.add_argument("--layout", default="hard")
    p.add_argument("--tracks", default="200-219", help="validation placements (never 100-124)")
    p.add_argument("--seconds", type=float, default=30.0, help="simulated s per placement")
    p.add_argument("--jobs", type=int, default=2, help="simulator processes")
    p.add_argument("--collision-cost", type=float, default=COLLISION_COST)
    p.add_argument("--keep", nargs="*", default=[], help="files copied beside the choice")
    p.add_argument("--reuse", nargs="*", default=[], metavar="SELECTION_JSON",
                   help="earlier selections: identical checkpoints take their numbers")  # fmt: skip
    a = p.parse_args(argv)
    try:
        finite = math.isfinite(a.seconds) and math.isfinite(a.collision_cost)
        if not (finite and a.seconds > 0 and a.collision_cost >= 0):
            raise UserError("--seconds must be > 0 and --collision-cost >= 0 (finite numbers)")
        keep = tuple(Path(k) for k in a.keep)
        missing = [str(k) for k in keep if not k.is_file()]
        if missing:
            raise UserError(f"--keep: no such file: {missing[0]}")
        out = Path(a.out)
        selection = select(
            named_candidates(a.candidates), out, a.episodes, layout=a.layout,
            tracks=parse_tracks(a.tracks), seconds=a.seconds, jobs=max(1, a.jobs),
            collision_cost=a.collision_cost, keep=keep, reuse=tuple(Path(r) for r in a.reuse),
        )  # fmt: skip
    except UserError as exc:
        print(f"select_by_driving: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return EXIT_USAGE
    print(f"{out}: chose {selection['chosen']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
