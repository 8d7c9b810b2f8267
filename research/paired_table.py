"""A check's paired table again, from its results file: model against model, seed by seed.

    python -m research.paired_table research/results/takeover_5seeds_rerun.json.gz \
        --pair takeovers3:IL-equal-takeovers3
    python -m research.paired_table research/results/dirl_loop_closed_sigma1.json.gz \
        --sigma 1.0 --pair loop3:IL

Why: a check runs for an hour or more and its table is computed from the rows it writes (each
model's laps per seed and placement), so the claims in research/README.md that rest on a
results file reproduce from it in seconds, with the same code the check's own report uses
(check_steps.report: the driving of each model, then each pair's Δ, mean ± std over seeds and
per seed ± its paired standard error). Files of take-over checks, the loop closed and the
outcome check hold such rows; `--sigma` picks the demonstrations' noise when a file holds
several.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a file, from any directory: the repository on the path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from carrt.errors import EXIT_USAGE, UserError
from research.check_steps import report
from research.json_file import read_json


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, exit 2: not argparse's usage block
        print(f"paired_table: error: {message}", file=sys.stderr)
        raise SystemExit(EXIT_USAGE)


def pair(text: str) -> tuple[str, str]:
    model, sep, base = text.partition(":")
    if not (sep and model and base):
        raise argparse.ArgumentTypeError(f"{text!r} is not MODEL:AGAINST")
    return model, base


def rows_at(path: str, sigma: float) -> list[dict]:
    """The file's rows at demonstration noise `sigma`; a file without rows is a UserError."""
    data = read_json(path, "results file")
    rows = data.get("rows") if isinstance(data, dict) else None
    if not isinstance(rows, list) or not all(isinstance(r, dict) and "runs" in r for r in rows):
        raise UserError(f"{path}: not a check's results file (no rows of runs)")
    mine = [r for r in rows if float(r.get("demo_noise", 0.0)) == sigma]
    if not mine:
        held = sorted({float(r.get("demo_noise", 0.0)) for r in rows})
        raise UserError(f"{path}: no rows at σ {sigma:g} (it holds σ {', '.join(map(str, held))})")
    return mine


def main(argv: list[str] | None = None) -> int:
    p = _Parser(prog="python -m research.paired_table", description=__doc__.split("\n")[0])
    p.add_argument("results", help="a check's results file (.json or .json.gz)")
    p.add_argument("--pair", type=pair, action="append", required=True, metavar="MODEL:AGAINST",
                   help="a model and the model it is compared with; repeatable")  # fmt: skip
    p.add_argument("--sigma", type=float, default=0.0, help="demonstration noise σ (0)")
    a = p.parse_args(argv)
    try:
        rows = rows_at(a.results, a.sigma)
        models = list(dict.fromkeys(r["model"] for r in rows))
        for name in {m for both in a.pair for m in both} - set(models):
            raise UserError(f"no model {name!r} at σ {a.sigma:g} in {a.results} "
                            f"(it holds: {', '.join(models)})")  # fmt: skip
    except UserError as exc:
        print(f"paired_table: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    print(report(rows, a.pair))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
