"""Choose among policies by driving them on validation placements (simulator only).

    python -m research.variants.select_by_driving --out runs/iter2/selected \
        --candidates start=runs/iter1/policy.pt runs/iter2/candidates/refine*.pt \
        --episodes data/ --tracks 200-219 --keep runs/iter2/world_model.pt

Why: refinement optimises the world model's imagined objective, which agrees only loosely with
driving (its rank correlation with the true objective is ~0.3, counterfactual.py here), and
past some number of steps it makes the policy drive worse (the study: iterations 2-3 lost
completion to the policy they started from). So the refinement's candidates (the policy every
`refine_candidates_every` steps, and the policy it started from) are each exported and driven
by `carrt eval` on VALIDATION placements. The score is completion − `collision_cost` ×
collisions per minute (one collision a minute costs as much as 5 % of a lap at the default).

The INCUMBENT (--incumbent: the policy the iteration's data made, "imitated"; by default the
first candidate) is kept unless another candidate beats it on the same placements by more than
--margin-z standard errors of the per-placement score difference (paired: both drove the same
placements with the same simulator seed); of those that do, the best score wins, a tie the
earlier one. Why not simply the best score: 20 validation placements measure a candidate's
completion to about ±0.05, as much as candidates differ, so the maximum of five picks the
luckiest one (the winner's curse); in the 2026-11-24 study the plain maximum chose a policy
that drove worse on the held-out placements than the one imitation made, on every seed at
iteration 1. --margin-z 0 is the plain maximum (ties: the incumbent). On a real car the same
choice is a person driving the candidates; here the simulator does it on placements that are
neither trained on nor the evaluation ones (the `hard` layout's 100-199 are refused).

OUT gets policy.pt and policy.onnx of the chosen candidate (plus each --keep file, so OUT is a
run directory the next iteration's `--init` reads), candidates/<name>.onnx, selection.json with
every candidate's driving numbers, and nothing at all when something fails.

--reuse takes earlier selection.json files: a candidate whose checkpoint is byte-identical
(sha256) to one already driven there on the same layout, placements and seconds takes those
numbers instead of being driven again (driving is deterministic: the same weights drive the same
laps). Beware: the next iteration's "start" is this iteration's choice, and its numbers on the
placements that chose it are biased upwards by the choice itself; the study therefore gives
each iteration its own validation placements (bench/dirl_sim.py `select_tracks`).
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

if __package__ in (None, ""):  # run as a script: make `research` and `training` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from carrt.errors import EXIT_USAGE, UserError
from carrt.policy import file_sha256
from training.sim_data import parse_tracks

COLLISION_COST = 0.05  # completion given up per collision/min in the score
# A challenger must beat the incumbent by this many standard errors of the paired difference
# (one-sided, ~2.3 % chance for a candidate that is no better; four challengers: ~9 %).
MARGIN_Z = 2.0


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
    """{checkpoint sha256: (driven, where)} of every candidate in earlier selection.json files
    driven on the same layout, placements and seconds (`driven`: its aggregate and per-placement
    numbers; older files without sha256 or per-placement numbers give none)."""
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
            if "sha256" in c and "placements" in c:
                numbers = {"aggregate": c["aggregate"], "placements": c["placements"]}
                known.setdefault(c["sha256"], (numbers, f"{path}:{c['name']}"))
    return known


def drive_score(completion: float, collisions_per_min: float, collision_cost: float) -> float:
    """Higher is better: completion less the price of the collisions."""
    return completion - collision_cost * collisions_per_min


def score(aggregate: dict, collision_cost: float = COLLISION_COST) -> float:
    """The score of the mean completion and collisions over the placements."""
    means = (aggregate["completion_ratio"]["mean"], aggregate["collisions_per_min"]["mean"])
    return drive_score(*means, collision_cost)


def placement_scores(placements: list[dict], collision_cost: float) -> dict[tuple, float]:
    """{(track, seed): that drive's score}."""
    return {
        (r["track"], r["seed"]): drive_score(
            r["completion_ratio"], r["collisions_per_min"], collision_cost
        )
        for r in placements
    }


def paired_advantage(
    challenger: dict, incumbent: dict, collision_cost: float
) -> tuple[float, float]:
    """Mean and standard error of challenger − incumbent score over the placements both drove
    (standard error inf below two placements: no evidence either way)."""
    a = placement_scores(challenger["placements"], collision_cost)
    b = placement_scores(incumbent["placements"], collision_cost)
    diffs = [a[key] - b[key] for key in a if key in b]
    n = len(diffs)
    if n == 0:
        raise UserError(f"{challenger['name']} and {incumbent['name']} share no placement")
    mean = sum(diffs) / n
    if n < 2:
        return mean, math.inf
    var = sum((d - mean) ** 2 for d in diffs) / (n - 1)
    return mean, math.sqrt(var / n)


def choose(
    driven: list[dict],
    collision_cost: float = COLLISION_COST,
    incumbent: str | None = None,
    margin_z: float = MARGIN_Z,
) -> dict:
    """The incumbent (by name; None: the first candidate) unless others beat it by more than
    `margin_z` standard errors of the paired difference: then the best-scoring of those, the
    earlier one on a tie. Each candidate gets its "advantage" and "standard_error" against
    the incumbent (0 and 0 for the incumbent itself; None: one placement, no spread)."""
    base = next(c for c in driven if c["name"] == incumbent) if incumbent else driven[0]
    winners = []
    for c in driven:
        mean, se = (0.0, 0.0) if c is base else paired_advantage(c, base, collision_cost)
        # JSON has no infinity: "no standard error" (one placement) is written as null
        c["advantage"], c["standard_error"] = mean, se if math.isfinite(se) else None
        if c is not base and mean > 0 and (margin_z == 0 or mean > margin_z * se):
            winners.append(c)
    if not winners:
        return base
    return max(
        winners, key=lambda c: (round(score(c["aggregate"], collision_cost), 9), -c["order"])
    )


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
    incumbent: str | None = None,
    margin_z: float = MARGIN_Z,
    keep: tuple[Path, ...] = (),
    reuse: tuple[Path, ...] = (),
) -> dict:
    from carrt.sim.evaluate import evaluate
    from export import export_policy

    incumbent = incumbent or candidates[0][0]
    if incumbent not in {name for name, _ in candidates}:  # before any candidate is driven
        raise UserError(f"--incumbent: no candidate is named {incumbent!r}")
    with staged_folder(out) as staging:
        work = staging / "candidates"
        work.mkdir(parents=True)
        driven = []
        known = driven_before(list(reuse), layout, tracks, seconds)
        for order, (name, path) in enumerate(candidates):
            onnx = work / f"{name}.onnx"
            export_policy(path, onnx, episodes)
            digest = file_sha256(path)
            numbers, reused = known.get(digest, (None, None))
            if numbers is None:
                result = evaluate(onnx, layout, tracks, seconds, (0,), jobs)
                numbers = {"aggregate": result["aggregate"], "placements": result["runs"]}
            agg = numbers["aggregate"]
            driven.append({"name": name, "order": order, "checkpoint": str(path),
                           "sha256": digest, "onnx": str(out / "candidates" / onnx.name),
                           **numbers, "score": score(agg, collision_cost),
                           "reused_from": reused})  # fmt: skip
            completion, per_min = agg["completion_ratio"]["mean"], agg["collisions_per_min"]["mean"]
            how = f" (same weights as {reused})" if reused else ""
            print(f"  {name}: completion {completion:.2f}, {per_min:.1f} collisions/min{how}",
                  flush=True)  # fmt: skip
        best = choose(driven, collision_cost, incumbent, margin_z)
        for c in driven:
            if c["name"] != incumbent:
                gain, se = c["advantage"], c["standard_error"]
                spread = "?" if se is None else f"{se:.3f}"  # one placement: no spread
                print(f"  {c['name']} − {incumbent}: {gain:+.3f} ± {spread} (paired score; "
                      f"{margin_z:g} standard errors needed)", flush=True)  # fmt: skip
        for extra in keep:
            shutil.copy2(extra, staging / extra.name)
        shutil.copy2(best["checkpoint"], staging / "policy.pt")
        shutil.copy2(work / f"{best['name']}.onnx", staging / "policy.onnx")
        selection = {
            "chosen": best["name"], "candidates": driven, "layout": layout, "tracks": tracks,
            "seconds": seconds, "collision_cost": collision_cost,
            "incumbent": incumbent, "margin_z": margin_z,
            "rule": "score = completion − collision_cost × collisions/min; the incumbent unless "
            "a candidate's paired advantage > margin_z standard errors: then the best such score",
        }  # fmt: skip
        (staging / "selection.json").write_text(json.dumps(selection, indent=2) + "\n")
    return selection


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m research.variants.select_by_driving", description=__doc__
    )
    p.add_argument("--candidates", nargs="+", required=True, metavar="[NAME=]CKPT")
    p.add_argument("--out", required=True, help="where the chosen policy goes")
    p.add_argument("--episodes", nargs="+", required=True, help="frames for the export's check")
    p.add_argument("--layout", default="hard")
    p.add_argument("--tracks", default="200-219", help="validation placements (never 100-199)")
    p.add_argument("--seconds", type=float, default=30.0, help="simulated s per placement")
    p.add_argument("--jobs", type=int, default=2, help="simulator processes")
    p.add_argument("--collision-cost", type=float, default=COLLISION_COST)
    p.add_argument("--incumbent", metavar="NAME", help="kept unless beaten (default: the first)")
    p.add_argument("--margin-z", type=float, default=MARGIN_Z,
                   help="standard errors a challenger must win by (0: the best score)")  # fmt: skip
    p.add_argument("--keep", nargs="*", default=[], help="files copied beside the choice")
    p.add_argument("--reuse", nargs="*", default=[], metavar="SELECTION_JSON",
                   help="earlier selections: identical checkpoints take their numbers")  # fmt: skip
    a = p.parse_args(argv)
    try:
        finite = all(map(math.isfinite, (a.seconds, a.collision_cost, a.margin_z)))
        if not (finite and a.seconds > 0 and a.collision_cost >= 0 and a.margin_z >= 0):
            raise UserError(
                "--seconds must be > 0, --collision-cost and --margin-z >= 0 (finite numbers)"
            )
        keep = tuple(Path(k) for k in a.keep)
        missing = [str(k) for k in keep if not k.is_file()]
        if missing:
            raise UserError(f"--keep: no such file: {missing[0]}")
        out = Path(a.out)
        selection = select(
            named_candidates(a.candidates), out, a.episodes, layout=a.layout,
            tracks=parse_tracks(a.tracks), seconds=a.seconds, jobs=max(1, a.jobs),
            collision_cost=a.collision_cost,
            incumbent=a.incumbent, margin_z=a.margin_z, keep=keep,
            reuse=tuple(Path(r) for r in a.reuse),
        )  # fmt: skip
    except UserError as exc:
        print(f"select_by_driving: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return EXIT_USAGE
    print(f"{out}: chose {selection['chosen']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
