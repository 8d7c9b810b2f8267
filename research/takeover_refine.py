"""The take-over check's `refine` steps: world models of the rounds' frames, and the last round's
policy refined in each (the study's safeguards, the paper's form, p̂ corrected; each ± unc).

Split from research/takeover_check.py so that file reads as the rounds, their pairs and its main;
this one says which world models refinement runs in (`sources`), which forms each gets
(`forms`) and the commands that make them. TakeoverConfig's fields document each option.
"""

from __future__ import annotations

from pathlib import Path

from research.dirl_steps import exploration_drives, frames_in, iterate_cmd, run_settings
from research.drift_steps import drift, member_runs
from research.study_config import StudyConfig
from research.study_steps import StudyStep
from research.takeover_config import TakeoverConfig

# iterate.py settings of the paper's refinement: every safeguard of training/config.py off
PAPER_FORM = [
    *("--set", "refine_w_anchor=0", "--set", "refine_w_imitation=0"),
    *("--set", "refine_center_gradient=false", "--set", "collision_prior_correction=false"),
]
# the paper's form with the one safeguard that is a correction, not a constraint: p̂ as a
# probability (the class weight the world model trained with divided out); later --set wins
PAPER_CORRECTED = [*PAPER_FORM, "--set", "collision_prior_correction=true"]


def world_model_run(cfg: TakeoverConfig, tag: str, source: str = "") -> Path:
    """The run whose world model learnt every frame up to the last round (`refine`), the
    demonstrations alone with source "demos" (`refine_in_demos`), and the last round's
    exploration drives too with "drives" (`refine_with_drives`), without the take-over labels
    with "drives-crashes-only" (`refine_crashes_only`)."""
    name = "-".join(x for x in (start_of(cfg.rounds).lower(), source, "world-model") if x)
    return Path(cfg.out) / "runs" / tag / name


def start_of(rounds: int) -> str:
    """The row refinement starts from: the last round's ("takeovers<k>"), or "IL" with no
    rounds (`rounds=0`: IL refined in a world model of its own demonstrations, on the same
    frames — the DIRL iteration at exactly IL's data)."""
    return f"takeovers{rounds}" if rounds else "IL"


def refined(cfg: TakeoverConfig, step: StudyStep, tag: str, seed: int, data: list[Path],
            last: Path, frames: int, world_demos: Path,
            more: int) -> dict[str, tuple[Path, int]]:  # fmt: skip
    """The last round's policy refined in a world model of every frame so far, with and
    without the uncertainty term (and in the paper's form): {row: (run, frames)}; with
    `refine_in_demos`, the same in a world model of the demonstrations `world_demos` alone
    (`more` frames beyond `data`'s: another σ's); with `refine_with_drives`, in a world model
    that also learnt the last policy's exploration drives."""
    out = refinements(cfg, step, tag, seed, data, last, frames, "")
    if cfg.refine_in_demos:
        out |= refinements(cfg, step, tag, seed, data, last, frames + more, "demos",
                           world_data=[world_demos])  # fmt: skip
    if not cfg.refine_with_drives:
        return out
    drives = exploration_drives(cfg.study, step, tag, cfg.rounds, last, kind="round-drives")
    more, more_frames = [*data, drives], frames + frames_in([drives])
    for source in ("drives", "drives-crashes-only")[: 1 + cfg.refine_crashes_only]:
        out |= refinements(cfg, step, tag, seed, more, last, more_frames, source)
    if cfg.more_drive_tracks:
        extra = exploration_drives(cfg.study, step, tag, cfg.rounds, last, kind="more-drives",
                                   tracks=cfg.more_drive_tracks)  # fmt: skip
        most, most_frames = [*more, extra], more_frames + frames_in([extra])
        out |= refinements(cfg, step, tag, seed, most, last, most_frames,
                           "more-drives-crashes-only")  # fmt: skip
        # the world model on the exploration drives alone; refinement still on every frame
        out |= refinements(cfg, step, tag, seed, most, last, most_frames, "drives-only",
                           world_data=[drives, extra])  # fmt: skip
    return out


def refinements(cfg: TakeoverConfig, step: StudyStep, tag: str, seed: int, data: list[Path],
                last: Path, frames: int, source: str,
                world_data: list[Path] | None = None) -> dict[str, tuple[Path, int]]:  # fmt: skip
    """One world model on `world_data` (default `data`) from the last round's policy (its
    counterfactual check in its run's metrics.json), then each refinement variant from it, on
    `data`."""
    study, start = cfg.study, start_of(cfg.rounds)
    runs, world = Path(cfg.out) / "runs" / tag, world_model_run(cfg, tag, source)
    prefix = f"{start.lower()}-{source}-" if source else f"{start.lower()}-"
    labels = collision_labels(cfg.takeovers_as_collisions and source in ("", "demos", "drives"))

    def learn(run: Path, extra: list[str]) -> list[str]:
        return world_model_cmd(study, world_data or data, run, last, seed, labels, extra)

    step(f"train-{tag}-{world.name}", learn(world, []), world / ".done")
    members = []
    if cfg.drift_members and source == "drives-crashes-only":
        members = member_runs(step, tag, world, seed, cfg.drift_members, learn)
    out, unc = {}, ["--no-uncertainty"]
    for name in forms(cfg, source):
        paper = PAPER_CORRECTED if name.startswith("paper-corrected") else PAPER_FORM
        flags = [*(paper if name.startswith("paper") else []),
                 *(unc if name.endswith("-unc") else [])]  # fmt: skip
        run = runs / f"{prefix}{name}"
        step(f"train-{tag}-{run.name}", refine_cmd(study, data, run, world, seed, labels, flags),
             run / ".done")  # fmt: skip
        if cfg.refine_drift:
            drift(step, tag, run, world, members)
        out[f"{start}+{source + '+' if source else ''}{name}"] = (run, frames)
    return out


def collision_labels(takeovers: bool) -> str:
    """The iterate.py setting saying whether the 0.5 s before each take-over is labelled a
    collision (TrainingConfig.takeovers_as_collisions) in a world model's or refinement's frames."""
    return f"takeovers_as_collisions={str(takeovers).lower()}"


def world_model_cmd(study: StudyConfig, data: list[Path], run: Path, last: Path, seed: int,
                    labels: str, extra: list[str] | tuple[str, ...] = ()) -> list[str]:  # fmt: skip
    """iterate.py: a world model learns `data`'s frames for the study's world_model_steps,
    starting from `last` (a round's run: its policy, kept as it is, and the world model it
    carries), its counterfactual check in the run's metrics.json."""
    return iterate_cmd(study, data, run, "--init", str(last), *run_settings(study, seed, every=0),
                       "--set", f"world_model_steps={study.world_model_steps}", "--set",
                       "refine_steps=0", "--set", labels, *extra)  # fmt: skip


def refine_cmd(study: StudyConfig, data: list[Path], run: Path, init: Path, seed: int,
               labels: str, flags: list[str] | tuple[str, ...] = ()) -> list[str]:  # fmt: skip
    """iterate.py: the policy of `init` (a run directory: policy.pt, world_model.pt) refined
    for the study's refine_steps in `init`'s world model, frozen, from `data`'s frames, with
    the study's safeguards unless `flags` turn them off (PAPER_FORM, --no-uncertainty)."""
    return iterate_cmd(study, data, run, "--init", str(init), *run_settings(study, seed, every=0),
                       "--set", "world_model_steps=0", "--set",
                       f"refine_steps={study.refine_steps}", "--set", "counterfactual_starts=0",
                       "--set", labels, *flags)  # fmt: skip


def forms(cfg: TakeoverConfig, source: str) -> list[str]:
    """The refinement variants the world model of `source` gets: the study's, the paper's, the
    paper's with p̂ corrected where `paper_corrected_in` names it, each -unc."""
    bases = ["refined", *(["paper"] if cfg.refine_paper_form else [])]
    bases += ["paper-corrected"] if name_of(source) in cfg.paper_corrected_in else []
    return [x for base in bases for x in (base, f"{base}-unc")]


def name_of(source: str) -> str:
    """A world model's name in `paper_corrected_in`: its source, "rounds" for the rounds' frames."""
    return source or "rounds"


def sources(cfg: TakeoverConfig) -> list[str]:
    """The world models refinement runs in: "" (the rounds' frames), "demos" (the
    demonstrations alone, `refine_in_demos`), "drives" (+ drives),
    "drives-crashes-only" (+ drives, take-overs not labelled collisions),
    "more-drives-crashes-only" (+ drives on `more_drive_tracks` too, crashes alone),
    "drives-only" (the exploration drives alone: measured on seed 0, the demonstrations' and
    take-overs' frames, where the action is a function of the image, taught the others to
    predict from the frame and ignore the steering)."""
    more = ["drives", *(["drives-crashes-only"] if cfg.refine_crashes_only else [])]
    more += ["more-drives-crashes-only", "drives-only"] if cfg.more_drive_tracks else []
    first = ["", *(["demos"] if cfg.refine_in_demos else [])]
    return [*first, *more] if cfg.refine_with_drives else first
