"""`make bench`: run every bench/bench_*.py, print its table, write bench/results/*.json.

Each module exposes ``run() -> dict``. Results carry the machine and date so the README's
table can say where its numbers came from.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
from pathlib import Path

if __package__ in (None, ""):  # run as a file, from any directory: the repository on the path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.provenance import environment

HERE = Path(__file__).parent
RESULTS = HERE / "results"


def main(argv: list[str] | None = None) -> int:
    names = sorted(p.stem for p in HERE.glob("bench_*.py"))
    parser = argparse.ArgumentParser(prog="python -m bench")
    parser.add_argument("only", nargs="*", help=f"subset of {', '.join(names)}")
    args = parser.parse_args(argv)
    unknown = [name for name in args.only if name not in names]
    if unknown:
        print(f"bench: error: no benchmark {unknown[0]!r} (one of: {', '.join(names)})",
              file=sys.stderr)  # fmt: skip
        return 2
    RESULTS.mkdir(exist_ok=True)
    for name in args.only or names:
        module = importlib.import_module(f"bench.{name}")
        print(f"== {name}", flush=True)
        result = {"machine": environment(), **module.run()}
        path = RESULTS / f"{name}.json"
        path.write_text(json.dumps(result, indent=2) + "\n")
        print(f"   -> {path}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
