"""The study's steps (research/dirl_sim.py): each one of the project's own commands, run through
StudyStep (skipped when its marker exists, so the study resumes), and the plumbing they share.

Split from dirl_sim.py so that the study file reads as its config, its chain and its main.
"""

from __future__ import annotations

import shutil
import sys
from collections import Counter
from pathlib import Path

from research.dirl_table import SEARCH_ROW
from research.study_config import StudyConfig
from research.study_steps import NotRun, StudyStep, output_of

ROOT = Path(__file__).resolve().parents[1]
DRIVE_SEED_STRIDE = 100_000  # iteration k drives with simulator seeds placement + stride·(k−1)


# ------------------------------------------------------------------------------- plumbing
def py(*args: str) -> list[str]:
    return [sys.executable, *args]


def iterate_cmd(cfg: StudyConfig, episodes: list[Path], out: Path, *extra: str) -> list[str]:
    sets = [arg for item in cfg.iterate_overrides() for arg in ("--set", item)]
    return py(str(ROOT / "research/variants/train.py"), "--episodes", *map(str, episodes),
              "--out", str(out), "--profile", cfg.profile, *sets, *extra)  # fmt: skip


def explore_args(cfg: StudyConfig) -> list[str]:
    """`carrt-sim-data drives` arguments for the exploration noise (none when it is off)."""
    if not cfg.drive_explore:
        return []
    lo, hi = cfg.explore_hold_s
    sets = (f"noise.fraction={cfg.explore_fraction}", f"noise.amplitude={cfg.explore_amplitude}",
            f"noise.hold_min_s={lo}", f"noise.hold_max_s={hi}")  # fmt: skip
    return ["--explore", *(arg for item in sets for arg in ("--set", item))]


def frames_in(paths: list[Path]) -> int:
    from training.sim_data import count_frames

    return count_frames(*paths)


def top_up(pool: Path, frames: int) -> list[Path]:
    """Whole episodes from `pool`, in name order, until they hold at least `frames` frames."""
    from carrt.episodes.reader import list_episodes, read_episode

    picked, total = [], 0
    for path in list_episodes([str(pool)]):
        if total >= frames:
            break
        picked.append(Path(path))
        total += read_episode(path).n
    if total < frames:
        raise SystemExit(f"dirl_sim: {pool} holds {total} frames, {frames} needed: more tracks")
    return picked


def searches(cfg: StudyConfig, iteration: int) -> bool:
    """Whether DIRL iteration `iteration` refines by search (else by the gradient)."""
    return cfg.refine_search and iteration >= cfg.search_from


def refinement_method(cfg: StudyConfig, iteration: int) -> str:
    """ "search" or "gradient": how DIRL iteration `iteration` refines (a row's `refinement`)."""
    return "search" if searches(cfg, iteration) else "gradient"


def run_settings(cfg: StudyConfig, seed: int, every: int, iteration: int = 1) -> list[str]:
    """The iterate.py arguments every run of a chain shares: its seed, the refinement
    safeguards and method (iteration `iteration`'s), the check, and how often refinement keeps
    a candidate (`every`)."""
    return ["--seed", str(seed), "--set", f"refine_w_anchor={cfg.refine_w_anchor}",
           "--set", f"refine_w_imitation={cfg.refine_w_imitation}",
           "--set", f"refine_center_gradient={str(cfg.refine_center_gradient).lower()}",
           "--set", "collision_prior_correction="
                    f"{str(cfg.collision_prior_correction).lower()}",
           "--set", f"refine_search={str(searches(cfg, iteration)).lower()}",
           "--set", f"refine_search_margin={cfg.refine_search_margin}",
           "--set", f"counterfactual_starts={cfg.counterfactual_starts}",
           "--set", f"counterfactual_tracks={cfg.counterfactual_tracks}",
           "--set", f"counterfactual_layout={cfg.layout}",
           "--set", f"w_image={cfg.w_image}",
           "--set", f"refine_candidates_every={every}"]  # fmt: skip


def ablations(cfg: StudyConfig, k: int) -> list[tuple[str, str, list[str], str]]:
    """σ 0 iteration k's variants of its refinement, each from the same world model and start
    policy with one thing changed: (run name, row, iterate.py flags, refinement method). The
    paper's -unc (no uncertainty term) at iteration 1, or every iteration with
    unc_every_iteration; at iteration 1, with compare_search, search in place of the gradient."""
    method = refinement_method(cfg, k)
    variants = []
    if k == 1 and cfg.compare_search and not searches(cfg, 1):
        variants.append(("search1", SEARCH_ROW, ["--set", "refine_search=true"], "search"))
    if k == 1 or cfg.unc_every_iteration:
        variants.append((f"unc{k}", f"DIRL -unc iter {k}", ["--no-uncertainty"], method))
    return variants


def plan(cfg: StudyConfig) -> Counter[str]:
    """Every step the study will run (or find finished), counted by kind (study_steps.step_kind
    of its name): the progress count and the ETA's weights. A chain: IL (train, eval), then per
    DIRL iteration its drives (and take-overs), training, selection, evaluation (and the row
    before refinement's), IL at its frames (train, eval); at σ 0, -unc (iteration 1's, or every
    iteration's) and iteration 1's search row, with their selections and evaluations."""
    kinds: Counter[str] = Counter(demos=2 * len(cfg.demo_noise))
    chains = [(0.0, cfg.iterations) for _ in cfg.seeds if 0.0 in cfg.demo_noise]
    chains += [(x, cfg.robustness_iterations) for x in cfg.demo_noise if x
               for _ in cfg.robustness_seeds]  # fmt: skip
    selects = cfg.select_by_driving
    for sigma, iterations in chains:
        kinds.update({"train il": 1, "eval": 1})
        for k in range(1, iterations + 1):
            kinds.update({"drive": 1, "train dirl1" if k == 1 else "train dirl": 1, "eval": 1,
                          "train il-equal": 1})  # fmt: skip
            kinds["eval"] += 1  # IL at its frames
            kinds["takeovers"] += 1 if cfg.takeover_seconds else 0
            kinds["select"] += 1 if selects else 0
            kinds["eval"] += 1 if cfg.reimitate_steps and selects else 0  # before refinement
        if sigma == 0:
            uncs = iterations if cfg.unc_every_iteration else min(iterations, 1)
            alternatives = ["unc"] * uncs + (["search"] if cfg.compare_search
                                             and not searches(cfg, 1) else [])  # fmt: skip
            for name in alternatives:
                kinds.update({f"train {name}": 1, "eval": 1, "select": 1 if selects else 0})
    return +kinds  # kinds with no step left out


# ------------------------------------------------------------------------------- the steps
def demonstrations(cfg: StudyConfig, step: StudyStep, sigma: float, tracks: str, tag: str) -> Path:
    data = Path(cfg.out) / "data" / f"{tag}-noise{sigma:g}"
    step(f"{tag}-noise{sigma:g}", py("-m", "training.sim_data", "demos", "--out", str(data),
         "--tracks", tracks, "--layouts", cfg.layout, "--episodes", str(cfg.expert_episodes),
         "--noise", str(sigma), "--noise-tau", str(cfg.demo_noise_tau),
         "--jobs", str(cfg.all_jobs())), data / ".done")  # fmt: skip
    return data


def every_noise_demonstrations(cfg: StudyConfig, step: StudyStep, extra: bool = True,
                               also: tuple[float, ...] = ()) -> list[str]:  # fmt: skip
    """Each σ's demonstrations on the training placements (and, with `extra`, the second pool
    IL at equal frames draws from): first, each with all `jobs`, since every chain needs them;
    `also`: more σs recorded on the training placements alone (a world model's, no chain's).
    Returns the steps not finished when only counting or reporting (NotRun)."""
    missing = []
    for sigma in (*cfg.demo_noise, *also):
        try:
            demonstrations(cfg, step, sigma, cfg.train_tracks, "expert")
            if extra and sigma in cfg.demo_noise:
                demonstrations(cfg, step, sigma, cfg.extra_tracks, "extra")
        except NotRun as exc:
            missing.append(str(exc))
    return missing


def evaluate(cfg: StudyConfig, step: StudyStep, name: str, onnx: Path, result: Path,
             same_as: Path | None = None) -> dict:  # fmt: skip
    """`carrt eval` of a policy (a run's own, the one chosen by driving, or a candidate) on the
    held-out placements (one simulator seed), into `result`. `same_as`: the result of an
    evaluated policy with byte-identical weights (an iteration that kept its start), whose laps
    these are: driving is deterministic, so they are copied, not driven again."""
    marker = result.with_name(f".done-{result.stem}")
    if same_as is not None and not marker.exists() and not step.report_only:
        shutil.copy2(same_as, result)
        marker.touch()
        step.reuse(
            f"eval-{name}", f"the laps of {same_as.parent.name}/{same_as.name} (same weights)"
        )
    else:
        step(f"eval-{name}", py("-m", "carrt", "eval", "--model", str(onnx),
             "--layout", cfg.layout, "--tracks", cfg.eval_tracks, "--seconds",
             str(cfg.eval_seconds), "--seeds", "0", "--jobs", str(cfg.step_jobs()), "--json",
             str(result)), marker)  # fmt: skip
    return output_of(step, result) or {"runs": [], "aggregate": {}}


def select(cfg: StudyConfig, step: StudyStep, name: str, k: int, run: Path, start: Path,
           data: list[Path], imitated: Path | None = None) -> Path:  # fmt: skip
    """Iteration k's policy: with select_by_driving, the policy its imitation made (`imitated`,
    with reimitate; else the policy it started from) unless the start or one of refinement's
    candidates drives better by select_margin_z standard errors on iteration k's validation
    placements (OUT run/selected, a run directory the next --init reads); else the run's own last
    policy. Earlier selections are reused where they drove the same placements."""
    if not cfg.select_by_driving:
        return run
    chosen = run / "selected"
    kept = run.glob("candidates/refine*.pt")  # refine<step>.pt, in step order
    candidates = sorted(kept, key=lambda p: int(p.stem.removeprefix("refine")))
    earlier = sorted(run.parent.glob("*/selected/selection.json"))
    tracks = cfg.select_tracks[min(k, len(cfg.select_tracks)) - 1]
    incumbent = ["--incumbent", "imitated"] if imitated else []
    select = str(ROOT / "research/variants/select_by_driving.py")
    step(f"select-{name}", py(select, "--out", str(chosen),
         "--candidates", f"start={start / 'policy.pt'}",
         *([f"imitated={imitated}"] if imitated else []), *map(str, candidates),
         *incumbent, "--margin-z", str(cfg.select_margin_z),
         "--episodes", *map(str, data), "--layout", cfg.layout, "--tracks", tracks,
         "--seconds", str(cfg.select_seconds), "--jobs", str(cfg.step_jobs()),
         "--keep", str(run / "world_model.pt"), "--reuse", *map(str, earlier)),
         chosen / ".done")  # fmt: skip
    return chosen


def iteration_drives(
    cfg: StudyConfig, step: StudyStep, tag: str, sigma: float, k: int, previous: Path
) -> list[Path]:
    """Iteration k's new episodes: the previous policy drives the training placements (or
    iteration_tracks' k-th entry) alone with exploration noise (every crash labelled: the
    world model's examples) and, with takeover_seconds, again with the expert taking over
    before a crash (labelled states the policy reached, with the demonstrations' σ). Each
    iteration drives with its own simulator seeds: an iteration that kept its start would
    otherwise record the same episodes again."""
    drives = exploration_drives(cfg, step, tag, k, previous)
    if not cfg.takeover_seconds:
        return [drives]
    return [drives, takeover_drives(cfg, step, tag, sigma, k, previous, cfg.takeover_seconds)]


def exploration_drives(cfg: StudyConfig, step: StudyStep, tag: str, k: int, previous: Path,
                       kind: str = "drives", tracks: str | None = None) -> Path:  # fmt: skip
    """The previous policy drives iteration k's placements (or `tracks`) alone, drive_seconds
    each, with exploration noise (every crash labelled and followed by the auto-reset), into
    OUT/data/<kind>-<tag>-iter<k>: the crashes from varied actions a world model learns from."""
    model = str(previous / "policy.onnx")
    drives = Path(cfg.out) / "data" / f"{kind}-{tag}-iter{k}"
    label = step_label(kind, "drives", k)
    step(f"drive-{tag}-{label}", py("-m", "training.sim_data", "drives", "--model", model,
         "--out", str(drives), "--tracks", tracks or iteration_tracks(cfg, k), "--layouts",
         cfg.layout, "--seconds", str(cfg.drive_seconds), "--jobs", str(cfg.step_jobs()),
         *drive_seeds(k), *explore_args(cfg)), drives / ".done")  # fmt: skip
    return drives


def takeover_drives(cfg: StudyConfig, step: StudyStep, tag: str, sigma: float, k: int,
                    previous: Path, seconds: float, kind: str = "takeovers") -> Path:  # fmt: skip
    """The previous policy drives iteration k's placements `seconds` each with the expert
    taking over before a crash (`sim_data interventions`, the demonstrations' σ on the
    expert's commands), into OUT/data/<kind>-<tag>-iter<k>: the labels in states the policy
    reached that every real-car drive with an override records."""
    takeovers = Path(cfg.out) / "data" / f"{kind}-{tag}-iter{k}"
    label = step_label(kind, "takeovers", k)
    model = str(previous / "policy.onnx")
    step(f"takeovers-{tag}-{label}", py("-m", "training.sim_data", "interventions",
         "--model", model, "--out", str(takeovers), "--tracks", iteration_tracks(cfg, k),
         "--layouts", cfg.layout, "--seconds", str(seconds), "--noise", str(sigma),
         "--noise-tau", str(cfg.demo_noise_tau), "--jobs", str(cfg.step_jobs()),
         *drive_seeds(k)), takeovers / ".done")  # fmt: skip
    return takeovers


def step_label(kind: str, study_kind: str, k: int) -> str:
    """The end of a drive step's (and log's) name: "iter<k>" for the study's own kind of data,
    so its steps keep their names; "<kind><k>" for a check's other kinds."""
    return f"iter{k}" if kind == study_kind else f"{kind}{k}"


def iteration_tracks(cfg: StudyConfig, k: int) -> str:
    """Where iteration k drives: iteration_tracks' k-th entry, else the training placements."""
    return cfg.iteration_tracks[k - 1] if cfg.iteration_tracks else cfg.train_tracks


def drive_seeds(k: int) -> tuple[str, str]:
    """Iteration k's simulator seeds (iteration 1: each placement's own)."""
    return ("--seed-offset", str(DRIVE_SEED_STRIDE * (k - 1)))


def reimitate_flags(cfg: StudyConfig) -> list[str]:
    """iterate.py flags for imitation again from the previous policy on every labelled frame
    (reimitate_steps at reimitate_lr; none when reimitate_steps is 0)."""
    if not cfg.reimitate_steps:
        return []
    return ["--set", "reimitate=true", "--set", f"imitation_steps={cfg.reimitate_steps}",
            "--set", f"imitation_lr={cfg.reimitate_lr}"]  # fmt: skip


def il_equal_data(expert: Path, extra: Path, expert_frames: int, frames: int) -> list[Path]:
    """IL at `frames`: the demonstrations plus whole episodes of the second pool `extra`, in
    name order (so a larger count extends a smaller one's set), to at least `frames`."""
    return [expert, *top_up(extra, frames - expert_frames)]
