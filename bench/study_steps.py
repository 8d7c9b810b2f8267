"""How the study (bench/dirl_sim.py) runs its steps: one command each, logged, skipped when
finished, `parallel` of them at once, with progress and an ETA.

Why parallel: on the 2-core machine one training at 2 torch threads uses the cores less well than
two trainings at 1 thread side by side (measured in the full study of 2026-11-24: 1.10× the
imitation samples per second; evaluations at one process each, two at once, 1.14×), and
single-threaded start-up and export overlap. The study's chains (one per demonstration noise
and seed) are independent of each other, so every chain runs in its own thread and a step waits
for one of `parallel` slots; each step is given its share of the threads and simulator
processes (StudyConfig.step_threads/step_jobs). A chain's own steps stay in order, so its
results do not depend on how the chains interleave.
"""

from __future__ import annotations

import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path


class NotRun(Exception):
    """A step has not run yet and the study only reports (--report): its rows are left out."""


class Stopped(Exception):
    """Another chain's step failed: this chain stops before its next step."""


class StudyStep:
    """Runs one command with its output in OUT/logs/NAME.log; a failed command stops the study
    (the other chains stop before their next step). Counts finished steps against the planned
    number and prints an ETA from the wall time spent so far. With `report_only`, nothing runs:
    a step that has not finished raises NotRun."""

    def __init__(
        self,
        out: Path,
        planned: int,
        *,
        report_only: bool = False,
        parallel: int = 1,
        cwd: Path | None = None,
    ) -> None:
        self.logs = Path(out) / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        self.planned, self.done, self.ran = planned, 0, 0
        self.report_only, self.cwd = report_only, cwd
        self.slots = threading.BoundedSemaphore(max(1, parallel))
        self.lock = threading.Lock()
        self.failed = threading.Event()
        self.first_start: float | None = None

    def __call__(self, name: str, argv: list[str], marker: Path) -> None:
        """Run unless `marker` exists; touch it when the command succeeded."""
        with self.lock:
            self.done += 1
        if marker.exists():
            return
        if self.report_only:
            raise NotRun(name)
        with self.slots:
            if self.failed.is_set():
                raise Stopped(name)
            log = self.logs / f"{name}.log"
            started = time.monotonic()
            with self.lock:
                self.first_start = self.first_start or started
            with log.open("w") as fh:
                fh.write("$ " + " ".join(argv) + "\n")
                fh.flush()
                code = subprocess.call(argv, cwd=self.cwd, stdout=fh, stderr=subprocess.STDOUT)
        took = time.monotonic() - started
        if code != 0:
            self.failed.set()
            raise SystemExit(f"dirl_sim: {name} failed (exit {code}); see {log}")
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.touch()
        self._progress(name, f"{took:.0f} s")

    def reuse(self, name: str, why: str) -> None:
        """A step whose result was taken from an identical earlier one: counted, not run."""
        with self.lock:
            self.done += 1
        self._progress(name, why)

    def _progress(self, name: str, what: str) -> None:
        with self.lock:
            self.ran += 1
            left = max(self.planned - self.done, 0)
            elapsed = time.monotonic() - (self.first_start or time.monotonic())
            eta = elapsed / self.ran * left / 60
            print(f"  [{self.done}/{self.planned}] {name}: {what} (ETA ~{eta:.0f} min)", flush=True)


def run_chains(chains: Sequence[Callable[[list], None]]) -> tuple[list, list[str]]:
    """Run every chain in its own thread (their steps share one StudyStep's slots); each appends its
    rows to a list of its own. Return the rows in chain order (not finishing order) and the names
    of the steps that stopped a chain with NotRun (--report; the rows before them are kept). A
    failed step's SystemExit is raised once every chain has stopped."""
    lists: list[list] = [[] for _ in chains]
    with ThreadPoolExecutor(max_workers=max(1, len(chains))) as pool:
        futures = [pool.submit(chain, rows) for chain, rows in zip(chains, lists, strict=True)]
    missing: list[str] = []
    failure: BaseException | None = None
    for future in futures:
        try:
            future.result()
        except NotRun as exc:
            missing.append(str(exc))
        except Stopped:
            pass
        except BaseException as exc:  # re-raised below, once every chain has ended
            failure = failure or exc
    if failure is not None:
        raise failure
    return [row for rows in lists for row in rows], missing
