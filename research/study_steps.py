"""How the study (research/dirl_sim.py) runs its steps: one command each, logged, skipped when
finished, `parallel` of them at once, with progress and an ETA.

Why parallel: on the 2-core machine one training at 2 torch threads uses the cores less well than
two trainings at 1 thread side by side (measured in the full study of 2026-11-24: 1.10× the
imitation samples per second; evaluations at one process each, two at once, 1.14×), and
single-threaded start-up and export overlap. The study's chains (one per demonstration noise
and seed) are independent of each other, so every chain runs in its own thread and a step waits
for one of `parallel` slots; each step is given its share of the threads and simulator
processes (StudyConfig.step_threads/step_jobs). A chain's own steps stay in order, so its
results do not depend on how the chains interleave.

The ETA weighs the steps left by their kind (a world model's training takes 20 times a drive):
each kind at the mean of its steps run so far, a kind not run yet at its typical time scaled by
how this run's steps of the same family compare with theirs: trainings (torch, bound by the
cores' arithmetic) and drives (the simulator's processes) scale apart, because one family's
speed says little of the other's. Until 2026-11-27 one scale served both, from stale typical
times: the one-command study of 2026-11-26 made its demonstrations 5 times faster than their
typical time, the scale took every training down by as much, and the ETA said 48 min after
them for 93 min of work. A plain mean over the steps run (before
2026-11-25) jumped with the order of the steps: the study of 2026-11-24 said 275 min at its 5th
step, 60 at its 13th and 153 at its 14th; and it counted the laps copied for a same-weights
evaluation as steps run. A resumed study first walks its chains without running anything
(`finished_steps`) to count the steps already finished, by kind: they take no time when the
chains reach them, so they are not in the ETA (before, a resumed study counted them as left
until its chains reached them). That walk goes on past a step that has not run (`counting`),
so the finished steps behind it count too (until 2026-11-26 it stopped at the first, as
--report does, and a check resumed with refinements added priced its finished evaluations as
left: "ETA ~140 min" with ~40 left); a chain stops only where it needs files a step that has
not run would write (an episode count). Still inexact: a step resumed from its own checkpoint
reports only its remaining time, and time a study stood paused (SIGSTOP) counts in the step it
paused.
"""

from __future__ import annotations

import contextlib
import io
import json
import re
import subprocess
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

# Seconds a step of each kind took, two steps at once on the 2-core EPYC with one torch thread and
# one simulator process each: the ETA's guess for a kind until a step of it has run here. The
# one-command study of 2026-11-26 (research/LOG.md; research.takeover_check, the `cpu` profile):
# demonstrations (one pool), imitation and IL at equal frames (the same 3000 steps), a round's
# take-over drives and its re-imitation, world models, refinements, evaluations of 100
# placements × 30 simulated s (that run's 50 took 47-65 s). The full study's kinds of
# 2026-11-24/25 (research/dirl_sim.py: "train dirl1" trains its world model from scratch and
# refines, later iterations continue it; -unc, the step search, selection by driving,
# exploration drives) are from those runs, before imitation was made faster.
TYPICAL_S = {"demos": 44, "train il": 270, "train il-equal": 270, "takeovers": 35,
             "train takeovers": 105, "train il-equal-takeovers": 270, "train world-model": 390,
             "train refine": 48, "eval": 110, "train dirl1": 1400, "train dirl": 890,
             "train unc": 150, "train search": 215, "select": 260, "drive": 70}  # fmt: skip
# The kinds that drive the simulator; every other kind trains or runs a network (torch).
SIMULATOR_KINDS = frozenset({"demos", "takeovers", "eval", "select", "drive"})
ANY = "step"  # the one kind of a plan given as a plain count


def step_kind(name: str) -> str:
    """What a study step's name says it does: "eval-noise0-seed1-dirl2-imitated" → "eval",
    "train-noise0-seed1-il-equal2" → "train il-equal", "train-noise1-seed0-dirl1" → "train
    dirl1", "expert-noise0" → "demos"."""
    head, _, rest = name.partition("-")
    if head in ("expert", "extra"):
        return "demos"
    if head != "train":
        return head
    model = re.sub(r"^noise[^-]*-seed\d+-", "", rest)
    return "train dirl1" if model == "dirl1" else "train " + re.sub(r"\d+$", "", model)


def is_simulator(kind: str) -> bool:
    """Whether a step of this kind drives the simulator (its time is the simulator's), not torch."""
    return kind in SIMULATOR_KINDS


def typical_s(kind: str) -> float | None:
    """TYPICAL_S of a kind, a check's world models and refinements by what they do
    ("train takeovers3-drives-world-model" → "train world-model", "train
    takeovers3-refined-unc" → "train refine"); None for a kind with no typical time."""
    if kind in TYPICAL_S:
        return TYPICAL_S[kind]
    if kind.startswith("train ") and kind.endswith(("world-model", "-member")):
        return TYPICAL_S["train world-model"]
    if kind.startswith("train ") and re.search(r"-(refined|paper)", kind):
        return TYPICAL_S["train refine"]
    if kind.startswith("train il-equal"):  # "train il-equal-demos": IL at as many frames
        return TYPICAL_S["train il-equal"]
    return None


class NotRun(Exception):
    """A step has not run yet and the study only reports (--report): its rows are left out."""


class Stopped(Exception):
    """Another chain's step failed: this chain stops before its next step."""


class StudyStep:
    """Runs one command with its output in OUT/logs/NAME.log; a failed command stops the study
    (the other chains stop before their next step). Counts finished steps against the plan
    (steps by kind, research/dirl_steps.plan; or a plain count) and prints an ETA. With
    `report_only`, nothing runs: a step that has not finished raises NotRun."""

    def __init__(
        self,
        out: Path,
        plan: Mapping[str, int] | int,
        *,
        report_only: bool = False,
        parallel: int = 1,
        cwd: Path | None = None,
        finished_before: Mapping[str, int] | None = None,
        counting: bool = False,
    ) -> None:
        self.logs = Path(out) / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        self.plan = Counter(plan) if isinstance(plan, Mapping) else Counter({ANY: plan})
        self.planned, self.done = sum(self.plan.values()), 0
        self.done_by_kind: Counter[str] = Counter()
        # Steps finished by an earlier invocation (finished_steps), and those of them reached.
        self.finished_before: Counter[str] = Counter(finished_before or {})
        self.found_done: Counter[str] = Counter()
        self.seconds: defaultdict[str, list[float]] = defaultdict(list)  # steps run, by kind
        # Steps running now: name → (kind, monotonic start). A step counts as done when it has
        # finished, not when its chain reaches it: until 2026-11-27 a step waiting for a slot
        # counted as done, so with five chains and two slots the ETA left out three world
        # models' trainings (~14 min said for ~24).
        self.running: dict[str, tuple[str, float]] = {}
        self.report_only, self.cwd, self.parallel = report_only or counting, cwd, max(1, parallel)
        # A walk that only counts (finished_steps): a step that has not run is passed, not
        # raised, so the finished steps behind it are found too.
        self.counting = counting
        self.slots = threading.BoundedSemaphore(self.parallel)
        self.lock = threading.Lock()
        self.failed = threading.Event()

    def kind(self, name: str) -> str:
        return ANY if ANY in self.plan else step_kind(name)

    def __call__(self, name: str, argv: list[str], marker: Path) -> None:
        """Run unless `marker` exists; touch it when the command succeeded."""
        kind, finished = self.kind(name), marker.exists()
        if finished or self.counting:
            with self.lock:
                self.done += 1
                self.done_by_kind[kind] += 1
                if finished:
                    self.found_done[kind] += 1
            return
        if self.report_only:
            raise NotRun(name)
        with self.slots:
            if self.failed.is_set():
                raise Stopped(name)
            log = self.logs / f"{name}.log"
            started = time.monotonic()
            with self.lock:
                self.running[name] = (kind, started)
            try:
                with log.open("w") as fh:
                    fh.write("$ " + " ".join(argv) + "\n")
                    fh.flush()
                    code = subprocess.call(argv, cwd=self.cwd, stdout=fh, stderr=subprocess.STDOUT)
            finally:
                with self.lock:
                    del self.running[name]
        took = time.monotonic() - started
        if code != 0:
            self.failed.set()
            raise SystemExit(f"dirl_sim: {name} failed (exit {code}); see {log}")
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.touch()
        with self.lock:
            self.done += 1
            self.done_by_kind[kind] += 1
            self.seconds[kind].append(took)
        self._progress(name, f"{took:.0f} s")

    def reuse(self, name: str, why: str) -> None:
        """A step whose result was taken from an identical earlier one: counted, not run."""
        with self.lock:
            self.done += 1
            self.done_by_kind[self.kind(name)] += 1
        self._progress(name, why)

    def eta_s(self) -> float:
        """Wall seconds the planned steps not yet counted will take, `parallel` at a time; steps
        an earlier invocation finished and the chains have not reached yet take none."""
        with self.lock:
            mean = {k: sum(v) / len(v) for k, v in self.seconds.items() if v}
            now, left = time.monotonic(), 0.0
            for kind, n in self.plan.items():
                each = mean.get(kind)
                if each is None:
                    each = self._guess(kind, mean)
                # finished, not reached yet; never negative: the walk stops a chain at its first
                # unfinished step, so finished steps after it are found only when reached
                ahead = max(self.finished_before[kind] - self.found_done[kind], 0)
                running = [now - t for k, t in self.running.values() if k == kind]
                waiting = max(n - self.done_by_kind[kind] - ahead - len(running), 0)
                left += waiting * each + sum(max(each - elapsed, 0.0) for elapsed in running)
        return left / self.parallel

    def _guess(self, kind: str, mean: Mapping[str, float]) -> float:
        """A kind not run yet: its typical time scaled as this run's steps of its family compare
        with theirs (1 while none has run); a kind with no typical time at the mean of its
        family's steps run so far (of every step while none has)."""
        family = {k: m for k, m in mean.items() if is_simulator(k) == is_simulator(kind)}
        typical = typical_s(kind)
        if typical is not None:
            known = [(typical_s(k), m) for k, m in family.items() if typical_s(k) is not None]
            scale = sum(m for _, m in known) / sum(t for t, _ in known) if known else 1.0
            return typical * scale
        ran = [t for k, v in self.seconds.items() if k in (family or mean) for t in v]
        return sum(ran) / len(ran) if ran else 0.0

    def _progress(self, name: str, what: str) -> None:
        eta = self.eta_s() / 60
        with self.lock:
            print(f"  [{self.done}/{self.planned}] {name}: {what} (ETA ~{eta:.0f} min)", flush=True)


def finished_steps(out: Path, plan: Mapping[str, int] | int,
                   run: Callable[[StudyStep], object]) -> Counter[str]:  # fmt: skip
    """The steps of a study (`run` walks them all with the given StudyStep) that an earlier
    invocation finished, by kind: `run` is walked once, nothing run, past the steps that have
    not run, its printing swallowed, so a resumed study's ETA leaves them out."""
    probe = StudyStep(out, plan, counting=True)
    # A chain that needs what a step that has not run would write (its episodes' frames) stops
    # there; what the walk counted so far stands.
    with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(Exception, SystemExit):
        run(probe)
    return probe.found_done


def output_of(step: Callable, path: Path) -> dict:
    """A finished step's JSON output (its evaluation, its run's metrics); {} while a counting
    walk passes a step that has not run (the walk's rows are thrown away). `step` is the walk's
    StudyStep or any callable that runs steps (one without `counting` never counts)."""
    if getattr(step, "counting", False) and not path.is_file():
        return {}
    return json.loads(path.read_text())


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
