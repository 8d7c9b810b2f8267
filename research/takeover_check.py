"""Rounds of take-overs alone, against imitation at equal frames: are labels in states the
policy reached worth more per frame than clean demonstrations?

    python -m research.takeover_check                     # σ 0, two rounds, seeds 0-2
    python -m research.takeover_check --set rounds=3
    python -m research.takeover_check --set demo_noise=0.5,1.0
    python -m research.takeover_check --set refine=true   # + DIRL on the last round, and -unc
    python -m research.takeover_check --set rounds=0 --set refine=true \
        --set demo_noise=0,1.0                         # DIRL at IL's own frames, no take-overs
    python -m research.takeover_check --set rounds=3 --set refine=true \
        --set refine_paper_form=true --set refine_with_drives=true \
        --set refine_crashes_only=true --set refine_drift=true \
        --set drift_members=2                          # + where refinement moved the plan
    python -m research.takeover_check --set study.profile=paper --set il_equal_at=2 \
        --set parallel=3                               # the paper's network, on a GPU

(Here, 2 cores, with the outcome check's demonstrations and IL already made: 23 min for σ 0's
two rounds, 28 more for a third and IL at rounds 1 and 3, 49 for σ 0.5 and 1.0's two rounds.)

Why: the study (research/dirl_sim.py) and the outcome check (research/outcome_check.py) spend each
round's frames on exploration drives (the crashes the world model and refinement learn from)
and on take-overs. Neither refinement beat imitation on as many clean frames, and the one gain
their rounds showed came from the take-overs ("imitated" over IL, +0.01 to +0.03; of seed 0's
2,974 take-over frames, 1,343 are the expert's). Here every frame of a round is a take-over
drive: the policy drives iteration k's placements `round_seconds` each while the expert takes
over before a crash (the person with the override), and the policy imitates again, from
itself, on every labelled frame so far ("takeovers<k>": iterate.py's reimitate with the
study's steps and learning rate). That is the paper's iteration with its intervention data and
without its world model and refinement (which added nothing measurable here).

It shares the outcome check's OUT: the demonstrations and the IL runs are reused (same
commands, same markers). "IL-equal-takeovers<k>" imitates the demonstrations topped up from
the second pool to round k's frames; OUT/completion_vs_frames-takeovers-noise<σs>.png plots
both against frames. `round_seconds` (50) was fixed before any of these
drives so that a round records about what an outcome round does (40 s drives + 21 s
take-overs, less the drives' resets): ~35K frames after two rounds, as outcomes2. Nothing was
tuned on the placements the table judges (the test placements, 100-199).

With `refine`, the last round's policy is also refined the paper's way: a world model learns
from every frame so far (the 0.5 s before each take-over labelled a collision, as the paper
counts its e-stops: TrainingConfig.takeovers_as_collisions) and its check runs on the held-out
placements 200-204; the policy is refined in it with the study's gradient and safeguards
("takeovers<k>+refined") and without the uncertainty term ("takeovers<k>+refined-unc", the
paper's ablation), on the same frames as the round; `refine_paper_form` adds the paper's
form (no safeguards) ± unc, `refine_in_demos` a world model of the demonstrations alone
("takeovers<k>+demos+refined", still refined on every frame; `refine_demos_noise=σ'` another
σ's, paired with "IL-equal-takeovers<k>-demos" at as many frames), `refine_with_drives` a world
model that also learns the last
policy's exploration drives, `refine_crashes_only` one more on those frames without the
take-over labels; `refine_drift` asks of every refined policy how far refinement moved its
plan and whether the world model's uncertainty rose there (research.variants.refine_drift), and
`drift_members=K` trains K more crash-only world models from their own initialisations whose
spread (a deep ensemble's uncertainty) the crash-only rows' drift reports too
(research/drift_steps.py); `paper_corrected_in=drives-only,…` adds, in the world models it names,
the paper's form with p̂ corrected ("paper-corrected" ± unc: the class weight divided out of
the collision probability, every constraint still off). Those steps are
research/takeover_refine.py's.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections import Counter
from pathlib import Path

if __package__ in (None, ""):  # run as a file, from any directory: the repository on the path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from research.check_steps import (
    imitation_flags,
    read_sets,
    run_check,
    study_for,
    suffix,
    write_results,
)
from research.dirl_steps import (
    evaluate,
    frames_in,
    il_equal_data,
    iterate_cmd,
    reimitate_flags,
    takeover_drives,
)
from research.dirl_table import plot
from research.drift_steps import drift_table, read_drift
from research.study_steps import StudyStep, output_of
from research.takeover_config import TakeoverConfig
from research.takeover_refine import forms, name_of, refined, sources, start_of, world_model_run


def chain(cfg: TakeoverConfig, step: StudyStep, sigma: float, seed: int, rows: list[dict]) -> None:
    """IL → round 1's take-overs → imitation again → round 2's …, and IL at each round's
    frames, every policy evaluated, for one demonstration noise and seed."""
    cfg = for_noise(cfg, sigma)
    study = cfg.study
    tag = f"noise{sigma:g}-seed{seed}"
    runs = Path(cfg.out) / "runs" / tag
    expert = Path(cfg.out) / "data" / f"expert-noise{sigma:g}"
    il = runs / "il"
    step(f"train-{tag}-il", iterate_cmd(study, [expert], il, *imitation_flags(study, seed)),
         il / ".done")  # fmt: skip
    expert_frames = frames_in([expert])
    models = {"IL": (il, expert_frames)}
    data, frames, previous = [expert], expert_frames, il
    extra = Path(cfg.out) / "data" / f"extra-noise{sigma:g}"

    def il_equal(name: str, at: int) -> None:
        """IL on `at` frames: the demonstrations topped up from the second pool."""
        equal, run = il_equal_data(expert, extra, expert_frames, at), runs / name.lower()
        step(f"train-{tag}-{run.name}", iterate_cmd(study, equal, run,
             *imitation_flags(study, seed)), run / ".done")  # fmt: skip
        models[name] = (run, frames_in(equal))

    for k in range(1, cfg.rounds + 1):
        new = takeover_drives(study, step, tag, sigma, k, previous, cfg.round_seconds,
                              kind="rounds")  # fmt: skip
        data, frames = [*data, new], frames + frames_in([new])  # the new episodes counted once
        run = runs / f"takeovers{k}"
        step(f"train-{tag}-takeovers{k}", iterate_cmd(study, data, run, "--seed", str(seed),
             "--init", str(previous), *reimitate_flags(study), "--set", "world_model_steps=0",
             "--set", "refine_steps=0"), run / ".done")  # fmt: skip
        models[f"takeovers{k}"], previous = (run, frames), run
        if not equal_at(cfg, k):
            continue
        il_equal(f"IL-equal-takeovers{k}", frames)
    if cfg.refine:
        world_demos = expert.with_name(f"expert-noise{demos_noise(cfg, sigma):g}")
        more = frames_in([world_demos]) if in_other_demos(cfg, sigma) else 0
        models.update(refined(cfg, step, tag, seed, data, previous, frames, world_demos, more))
        if more:  # IL on as many frames as the world model's refinement saw: its pair
            il_equal(il_at_frames_of(cfg, sigma, "demos"), frames + more)
    # driven last trained first, so a check stopped part way (a lent GPU's minutes) has its
    # last round and its IL at equal frames; the rows keep the training order
    mine = []
    for model, (run, learnt_from) in reversed(models.items()):
        result = run / f"eval{suffix(cfg)}.json"
        out = evaluate(study, step, f"{tag}-{model}{suffix(cfg)}", run / "policy.onnx", result)
        row = {
            "model": model,
            "demo_noise": sigma,
            "seed": seed,
            "run": str(run),
            "frames": learnt_from,
            "aggregate": out["aggregate"],
            "runs": out["runs"],
        }
        if "+" in model:  # the world model it was refined in, and its check
            source = model.split("+")[1] if model.count("+") == 2 else ""
            world = world_model_run(cfg, tag, source)
            metrics = output_of(step, world / "metrics.json")
            row |= {"world_model": str(world), "counterfactual": metrics.get("counterfactual")}
            row |= {"drift": read_drift(run)} if cfg.refine_drift else {}
        mine.insert(0, row)
    rows.extend(mine)


def for_noise(cfg: TakeoverConfig, sigma: float) -> TakeoverConfig:
    """The settings the chains of demonstration noise `sigma` run with: σ 0's as set; σ > 0's
    with `robustness_rounds` rounds (when set), IL at equal frames at the last, no refinement."""
    if sigma == 0 or not cfg.robustness_rounds:
        return cfg
    k = cfg.robustness_rounds
    return dataclasses.replace(cfg, rounds=k, il_equal_at=(k,), refine=False)


def demos_noise(cfg: TakeoverConfig, sigma: float) -> float:
    """The σ of the demonstrations the demonstrations' world model learns (refine_in_demos)."""
    return sigma if cfg.refine_demos_noise < 0 else cfg.refine_demos_noise


def equal_at(cfg: TakeoverConfig, k: int) -> bool:
    """Whether IL at equal frames trains at round k (`il_equal_at`; empty: every round)."""
    return not cfg.il_equal_at or k in cfg.il_equal_at


def pairs(cfg: TakeoverConfig, sigma: float = 0.0) -> list[tuple[str, str]]:
    """Each round against IL at its frames, IL on the demonstrations and the round before;
    with `refine`, the refined policies of the chains of σ `sigma` against the round they
    started from, IL at as many frames as they saw (il_at_frames_of), the check's own
    refinement (those in the demonstrations' world model) and each other's -unc."""
    out = []
    for k in range(1, cfg.rounds + 1):
        out += [(f"takeovers{k}", f"IL-equal-takeovers{k}")] if equal_at(cfg, k) else []
        out += [(f"takeovers{k}", "IL")]
        out += [(f"takeovers{k}", f"takeovers{k - 1}")] if k > 1 else []
    if cfg.refine:
        start = start_of(cfg.rounds)
        for source in sources(cfg):
            head = f"{start}+{source + '+' if source else ''}"
            il = il_at_frames_of(cfg, sigma, source)
            for name in forms(cfg, source):
                row = head + name
                out += [(row, start), *([(row, il)] if il and il != start else [])]
                out += [(row, f"{start}+{name}")] if source == "demos" else []
            out += [(head + name, f"{head}{name}-unc") for name in forms(cfg, source)[::2]]
    return out


def il_at_frames_of(cfg: TakeoverConfig, sigma: float, source: str) -> str | None:
    """The IL row trained on as many frames as a refinement in `source`'s world model saw, at
    the chains of σ `sigma`: the last round's IL at equal frames when that world model learnt
    only frames of the round (every frame so far, or the chain's own demonstrations), the
    "-demos" one when it also learnt another σ's demonstrations; None when no IL trained at
    that count (a world model with exploration drives, or no IL at the last round)."""
    k = cfg.rounds
    if source == "demos" and demos_noise(cfg, sigma) != sigma:
        return il_equal_demos(k)
    if k == 0:  # refined on the demonstrations alone: IL's own frames
        return "IL"
    return f"IL-equal-takeovers{k}" if source in ("", "demos") and equal_at(cfg, k) else None


def il_equal_demos(rounds: int) -> str:
    """The IL row at as many frames as a refinement in another σ's demonstrations' world model
    saw (`refine_demos_noise`)."""
    return f"IL-equal-takeovers{rounds}-demos" if rounds else "IL-equal-demos"


def parse(argv: list[str] | None) -> TakeoverConfig:
    p, cfg = read_sets(argv, TakeoverConfig(), "research.takeover_check", __doc__, "TakeoverConfig")
    if cfg.rounds < 0 or (cfg.rounds == 0 and not cfg.refine):
        p.error(f"rounds: {cfg.rounds} (1 or more; 0 with refine=true: IL refined at its frames)")
    if cfg.rounds == 0 and cfg.refine_with_drives:
        p.error("refine_with_drives: needs rounds of take-overs (the last round's policy drives)")
    if cfg.rounds == 0 and cfg.refine_in_demos and cfg.refine_demos_noise == -1:
        p.error("refine_in_demos: with rounds=0 the world model already learns the chain's own "
                "demonstrations alone; give refine_demos_noise=σ' for another σ's")  # fmt: skip
    tracks = cfg.study.iteration_tracks
    for option in ("rounds", "robustness_rounds"):
        if tracks and getattr(cfg, option) > len(tracks):
            p.error(f"{option}: {getattr(cfg, option)} (StudyConfig.iteration_tracks has "
                    f"placements for {len(tracks)})")  # fmt: skip
    if cfg.robustness_rounds < 0:
        p.error(f"robustness_rounds: {cfg.robustness_rounds} (0: as rounds, or 1 or more)")
    needs = [("refine_paper_form", "refine"), ("refine_with_drives", "refine"),
             ("refine_in_demos", "refine"),
             ("refine_crashes_only", "refine_with_drives"), ("refine_drift", "refine"),
             ("drift_members", "refine_drift"), ("drift_members", "refine_crashes_only"),
             ("more_drive_tracks", "refine_crashes_only")]  # fmt: skip
    for option, needed in needs:
        if getattr(cfg, option) and not getattr(cfg, needed):
            p.error(f"{option}: {getattr(cfg, option)} needs {needed}=true")
    names = [name_of(s) for s in sources(cfg)] if cfg.refine else []
    for wanted in cfg.paper_corrected_in:
        if wanted not in names:
            p.error(f"paper_corrected_in: {wanted!r} is not one of this check's world models "
                    f"({', '.join(names) or 'none without refine=true'})")  # fmt: skip
    if cfg.refine_demos_noise != -1 and not cfg.refine_in_demos:
        p.error(f"refine_demos_noise: {cfg.refine_demos_noise:g} needs refine_in_demos=true")
    if cfg.refine_demos_noise != -1 and not 0 <= cfg.refine_demos_noise <= 2:
        p.error(f"refine_demos_noise: {cfg.refine_demos_noise:g} (0 to 2, or -1: the chain's own)")
    if not 0 <= cfg.drift_members <= 16:
        p.error(f"drift_members: {cfg.drift_members} (0 to 16)")
    if any(not 1 <= k <= cfg.rounds for k in cfg.il_equal_at):
        p.error(f"il_equal_at: {cfg.il_equal_at} (rounds 1 to {cfg.rounds})")
    if not 0 < cfg.round_seconds < 1e5:
        p.error(f"round_seconds: {cfg.round_seconds} (more than 0)")
    return dataclasses.replace(cfg, study=study_for(p, cfg))


def world_demos_only(cfg: TakeoverConfig) -> tuple[float, ...]:
    """The σs whose demonstrations only a world model learns (refine_demos_noise), recorded too."""
    wanted = {demos_noise(for_noise(cfg, s), s) for s in cfg.demo_noise
              if for_noise(cfg, s).refine and cfg.refine_in_demos}  # fmt: skip
    return tuple(sorted(wanted - set(cfg.demo_noise)))


def needs_second_pool(cfg: TakeoverConfig) -> bool:
    """Whether any chain trains IL at equal frames (the second demonstration pool's use): not
    when none has rounds (`rounds=0`: refinement's pair is IL itself) unless a world model
    learns another σ's demonstrations too (its pair: IL at as many frames)."""
    return any(for_noise(cfg, s).rounds or in_other_demos(for_noise(cfg, s), s)
               for s in cfg.demo_noise)  # fmt: skip


def in_other_demos(cfg: TakeoverConfig, sigma: float) -> bool:
    """Whether σ's chains also refine in a world model of another σ's demonstrations
    (`refine_demos_noise`): their frames count, and IL trains at as many (il_equal_demos)."""
    return cfg.refine and cfg.refine_in_demos and demos_noise(cfg, sigma) != sigma


def plan(cfg: TakeoverConfig) -> Counter[str]:
    """The check's steps by kind (the progress count and the ETA's weights)."""
    pools = 1 + needs_second_pool(cfg)
    kinds = Counter({"demos": pools * len(cfg.demo_noise) + len(world_demos_only(cfg))})
    for sigma in cfg.demo_noise:
        mine, n = for_noise(cfg, sigma), len(cfg.seeds)
        r = mine.rounds
        equal = sum(equal_at(mine, k) for k in range(1, r + 1))
        refined_rows = mine.refine * sum(len(forms(mine, s)) for s in sources(mine))
        kinds += {"train il": n, "takeovers": r * n, "train takeovers": r * n,
                  "train il-equal-takeovers": equal * n,
                  "eval": (1 + r + equal + refined_rows) * n}  # fmt: skip
        if not mine.refine:
            continue
        for source in sources(mine):
            head = f"train {start_of(r).lower()}-{source + '-' if source else ''}"
            kinds += {head + name: n for name in ["world-model", *forms(mine, source)]}
        kinds += (
            {"drive": n * (1 + bool(mine.more_drive_tracks))} if mine.refine_with_drives else {}
        )
        kinds += {"drift": refined_rows * n} if mine.refine_drift else {}
        if in_other_demos(mine, sigma):
            kinds += {f"train {il_equal_demos(r).lower()}": n, "eval": n}
        if mine.drift_members:
            kinds += {f"train takeovers{r}-drives-crashes-only-member": mine.drift_members * n}
    return +kinds


def main(argv: list[str] | None = None) -> int:
    cfg = parse(argv)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    rows = run_check(
        cfg, dict(plan(cfg)), chain, extra=needs_second_pool(cfg), also=world_demos_only(cfg)
    )
    name = f"takeovers{suffix(cfg)}-noise{'_'.join(f'{x:g}' for x in cfg.demo_noise)}"
    figure = out / f"completion_vs_frames-{name}.png"
    refined = ", the last refined in world models" if cfg.refine else ""
    plot(rows, figure, f"IL and rounds of take-overs{refined}, mean ± std over seeds")

    def pairs_of(mine: list[dict]) -> list[tuple[str, str]]:
        sigma = mine[0]["demo_noise"] if mine else 0.0
        return pairs(for_noise(cfg, sigma), sigma) if mine else []

    text = write_results(cfg, rows, started, f"-{name}", pairs_of)
    moves = drift_table(rows)
    if moves:
        text += "\n\nWhere refinement moved the plan (research.variants.refine_drift):\n\n" + moves
        (out / f"table-{name}.md").write_text(text + "\n")
    print("\n" + text + f"\n\nwritten: {out}/results-{name}.json, table-{name}.md, {figure}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
