"""How long training will take on this machine, said up front, and a warning when it runs slow.

A person who starts `carrt-train` on a laptop should know whether to wait or come back after
lunch, and should hear about it when another job is eating the cores. Step rates are measured,
not guessed: every stage times its steps after a short warm-up and keeps its rate (steps/s) in
a small file in the user's cache (`$XDG_CACHE_HOME/carrt/step_rates.json`), keyed by what sets
the rate (profile, stage, batch size, device, threads). A run then prints, before its first
step, "expected ~6 min on this machine" from those rates; a stage this machine has not run yet
says its own expectation after its first steps. When a stage then runs more than SLOWER times
slower than expected over a window of WINDOW_S seconds, it warns once.

Only rank 0 speaks, and only with progress on (the default; the tests and `make demo-policy`
run quiet). Nothing here changes what is trained.
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

WARMUP = 3  # steps not timed: the first ones build caches and allocate
MEASURE = 10  # steps timed after the warm-up before a first-time stage states its expectation
WINDOW_S = 20.0  # seconds over which the rate is compared with the expected one
SLOWER = 2.0  # this many times slower than expected: warn (once per stage)


def cache_file() -> Path:
    root = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(root) / "carrt" / "step_rates.json"


def minutes(seconds: float) -> str:
    return f"~{max(1, round(seconds / 60))} min" if seconds >= 60 else f"~{seconds:.0f} s"


class Pace:
    """Expected durations and the slow-run warning for one training process (rank 0)."""

    def __init__(
        self, machine: str, *, path: Path | None = None, clock: Callable | None = None,
        say: Callable[[str], None] | None = None,
    ) -> None:  # fmt: skip
        self.machine = machine  # device and threads: what else sets the rate
        self.path = path or cache_file()
        self.clock = clock or time.perf_counter
        self.say = say or (lambda line: print(line, file=sys.stderr, flush=True))
        self.rates = self._read()
        self._stage: dict = {}

    def key(self, profile: str, stage: str, batch: int) -> str:
        return f"{profile}/{stage}/batch{batch}/{self.machine}"

    def announce(self, profile: str, stages: list[tuple[str, int, int]]) -> None:
        """Before the first step: (stage, steps still to take, batch size) of each stage."""
        todo = [(name, steps, batch) for name, steps, batch in stages if steps > 0]
        if not todo:
            return
        known = [self.rates.get(self.key(profile, n, b)) for n, _steps, b in todo]
        parts = ", ".join(f"{n} {s}" for n, s, _b in todo)
        if all(known):
            total = sum(s / r for (_n, s, _b), r in zip(todo, known, strict=True))
            self.say(f"carrt-train: {parts} steps: expected {minutes(total)} on this machine "
                     "(its step rates measured before)")  # fmt: skip
        else:
            self.say(f"carrt-train: {parts} steps; each stage says its expected time after its "
                     "first steps (this machine has not run them yet)")  # fmt: skip

    def begin(self, profile: str, stage: str, batch: int, start: int, steps: int) -> None:
        key = self.key(profile, stage, batch)
        self._stage = {"key": key, "name": stage, "left": steps - start, "n": 0,
                       "expected": self.rates.get(key), "t_warm": None, "window": None,
                       "warned": False}  # fmt: skip

    def step(self) -> None:
        """After every optimizer step."""
        s = self._stage
        if not s:
            return
        s["n"] += 1
        now = self.clock()
        if s["n"] == WARMUP:
            s["t_warm"], s["window"] = now, (now, s["n"])
            return
        if s["t_warm"] is None:
            return
        if s["expected"] is None and s["n"] == WARMUP + MEASURE:
            rate = MEASURE / max(now - s["t_warm"], 1e-9)
            s["expected"] = rate
            self.say(f"carrt-train: {s['name']}: expected {minutes(s['left'] / rate)} on this "
                     f"machine ({s['left']} steps at {rate:.3g} steps/s)")  # fmt: skip
        t0, n0 = s["window"]
        if now - t0 >= WINDOW_S:
            rate = (s["n"] - n0) / (now - t0)
            s["window"] = (now, s["n"])
            if s["expected"] and rate * SLOWER < s["expected"] and not s["warned"]:
                s["warned"] = True
                self.say(f"carrt-train: {s['name']} runs {s['expected'] / rate:.1f}x slower "
                         f"than expected ({rate:.3g} against {s['expected']:.3g} steps/s): "
                         "another job is using the cores?")  # fmt: skip

    def end(self) -> None:
        """After the stage: its measured rate, kept for the next run's expectation."""
        s, self._stage = self._stage, {}
        if not s or s["t_warm"] is None or s["n"] < WARMUP + MEASURE:
            return
        self.rates[s["key"]] = (s["n"] - WARMUP) / max(self.clock() - s["t_warm"], 1e-9)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.path.with_suffix(".tmp")
            tmp.write_text(json.dumps(self.rates, indent=1, sort_keys=True) + "\n")
            tmp.replace(self.path)
        except OSError:  # a read-only home: the expectation is a courtesy, not a must
            pass

    def _read(self) -> dict[str, float]:
        try:
            rates = json.loads(self.path.read_text())
            return {k: float(v) for k, v in rates.items() if float(v) > 0}
        except (OSError, ValueError, TypeError, AttributeError):
            return {}
