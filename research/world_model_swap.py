"""Which half made refinement work: the policy it started from, or the world model it ran in?

    python -m research.world_model_swap --set out=research/runs/swap-s05-in-s1 \
        --set policy_out=research/runs/tau05 --set policy_noise=0.5 --set policy_rounds=2 \
        --set world_out=research/runs/tau05 --set world_noise=1 --set world_rounds=2

Why: with the lasting-error person (τ 0.5 s) refinement beat the round it started from at
σ 0.5 on five seeds (+0.038 ± 0.009 completion) and did not at σ 0 or σ 1.0 (research/LOG.md,
"the lasting-error person on five seeds"). Each of those refinements changed two things at
once: the policy it started from and the world model it ran in. Here one take-over check's last
round's policy (`policy_out`, `policy_noise`, `policy_rounds`: research/takeover_check.py's OUT
layout) is refined in ANOTHER check's world model of its last round's frames (`world_out`, …),
everything else as that check's `refine` step ran it (research/takeover_refine.refine_cmd: the
study's safeguards, its steps, the same seed, the start policy's own frames for the imitation
term and the start states), and driven on the test placements (other `eval_tracks`, such as
validation placements to choose a setting on, drive the check's own rows here too). With
`world_*` equal to `policy_*` it remakes the check's own refined policy (the same weights).

A world model learns only recorded episodes, so refining a policy in another chain's world
model uses nothing a real car could not record. The rows: the start policy ("takeovers<k>"),
its refinement in its own world model ("takeovers<k>+refined", the check's), and in the other
("takeovers<k>+refined-in-noise<σ'>"), each with how far refinement moved the plan on the
start's recorded frames (mean |Δ steering|, |Δ throttle|, signed Δ throttle;
research.null_candidates' measure), and the swapped rows with what the other world model is (its
run, training frames and collision frames, its counterfactual check and its response to
steering, from its metrics.json). `unc=true` adds the paper's -unc ablation in the other world
model; `world_data=demos` or `rounds` learns the other world model here anew, by the check's own
command from the same round's run (takeover_refine.world_model_cmd), on only the other check's
demonstrations or only its take-over rounds. Written: OUT/results-swap-noise<σ>-refined-in-
noise<σ'>[-<data>][-<eval_tracks>].json and the matching table-….md (a file per swap and set of
placements: one OUT can hold several swaps that share the world models learnt there).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import shutil
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

if __package__ in (None, ""):  # run as a file, from any directory: the repository on the path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.provenance import environment
from research.check_steps import read_sets, report, study_for, suffix
from research.dirl_steps import ROOT, evaluate
from research.study_config import StudyConfig
from research.study_steps import StudyStep, finished_steps, output_of, run_chains, step_kind
from research.takeover_refine import collision_labels, refine_cmd, world_model_cmd


@dataclass
class SwapConfig:
    """Whose policy is refined in whose world model; the study's settings as the checks ran."""

    out: str = "research/runs/swap"
    policy_out: str = "research/runs/tau05"  # the take-over check whose last round is refined
    policy_noise: float = 0.5
    policy_rounds: int = 2
    world_out: str = "research/runs/tau05"  # the take-over check whose world model it runs in
    world_noise: float = 1.0
    world_rounds: int = 2
    # as the take-over check labelled its world models' and refinements' frames
    takeovers_as_collisions: bool = True
    # also the paper's -unc ablation in the other world model (--no-uncertainty), paired with
    # the refinement with the term: does the term matter in a world model where refinement works?
    unc: bool = False
    # "all": the world check's own world model; "demos" or "rounds": one learnt here anew, by
    # the check's own command from the same round's run, on only that check's demonstrations
    # or only its take-over rounds (which of its data carries what refinement uses)
    world_data: str = "all"
    seeds: tuple[int, ...] = (0, 1, 2, 3, 4)
    eval_tracks: str = StudyConfig.eval_tracks
    parallel: int = 2
    # the checks' own fields study_for sets (it reads them off any check's config)
    demo_noise: tuple[float, ...] = ()
    study: StudyConfig = field(default_factory=StudyConfig)


@dataclass(frozen=True)
class Chain:
    """One seed's paths: the start (the check's world model run: the last round's policy and
    that world model), the other world model (and, with `world_data`, the run it is learnt
    from and on which frames), the start's frames and its evaluated rows."""

    tag: str
    start: Path
    world: Path
    data: list[Path]
    start_run: Path  # the last round's policy as the check drove it
    il_equal_run: Path
    own_refined_run: Path
    world_from: Path | None = None
    world_episodes: tuple[Path, ...] = ()

    def checks_rows(self, k: int) -> list[tuple[str, Path]]:
        """(model, run) of the rows the check made: the start, IL at its frames, its refinement."""
        return [(f"takeovers{k}", self.start_run), (f"IL-equal-takeovers{k}", self.il_equal_run),
                (f"takeovers{k}+refined", self.own_refined_run)]  # fmt: skip


WORLD_DATA = ("all", "demos", "rounds")


def episodes_of(out: str, sigma: float, seed: int, rounds: int) -> tuple[Path, list[Path]]:
    """A take-over check's demonstrations and its chain's take-over rounds, as it names them."""
    data = Path(out) / "data"
    return data / f"expert-noise{sigma:g}", [
        data / f"rounds-noise{sigma:g}-seed{seed}-iter{i}" for i in range(1, rounds + 1)
    ]


def chain_paths(cfg: SwapConfig, seed: int) -> Chain:
    def runs(out: str, sigma: float) -> Path:
        return Path(out) / "runs" / f"noise{sigma:g}-seed{seed}"

    k, mine = cfg.policy_rounds, runs(cfg.policy_out, cfg.policy_noise)
    demos, rounds = episodes_of(cfg.policy_out, cfg.policy_noise, seed, k)
    theirs, kw = runs(cfg.world_out, cfg.world_noise), cfg.world_rounds
    world, world_from, world_episodes = theirs / f"takeovers{kw}-world-model", None, ()
    if cfg.world_data != "all":
        their_demos, their_rounds = episodes_of(cfg.world_out, cfg.world_noise, seed, kw)
        world_episodes = tuple([their_demos] if cfg.world_data == "demos" else their_rounds)
        world_from = theirs / f"takeovers{kw}"
        world = runs(cfg.out, cfg.world_noise) / f"takeovers{kw}-{cfg.world_data}-world-model"
    return Chain(f"noise{cfg.policy_noise:g}-seed{seed}", mine / f"takeovers{k}-world-model",
                 world, [demos, *rounds], mine / f"takeovers{k}", mine / f"il-equal-takeovers{k}",
                 mine / f"takeovers{k}-refined", world_from, world_episodes)  # fmt: skip


def missing_inputs(cfg: SwapConfig) -> list[str]:
    """What a seed needs that its checks have not made (one line each)."""
    out = []
    for seed in cfg.seeds:
        c = chain_paths(cfg, seed)
        needed = [c.start / "policy.pt", *c.data]
        for _, run in c.checks_rows(cfg.policy_rounds):  # its laps there, or its policy
            needed.append(checked(cfg, run) or run / "policy.onnx")
        if c.world_from is None:
            needed.append(c.world / "world_model.pt")
        else:
            needed += [c.world_from / "policy.pt", *c.world_episodes]
        out += [f"{p} does not exist (seed {seed})" for p in needed if not p.exists()]
    return out


def checked(cfg: SwapConfig, run: Path) -> Path | None:
    """The laps the check drove with `run`'s policy on eval_tracks, if it drove them there."""
    result = run / f"eval{suffix(cfg)}.json"
    return result if result.is_file() else None


def other_name(cfg: SwapConfig, unc: bool = False) -> str:
    data = "" if cfg.world_data == "all" else f"-{cfg.world_data}"
    return f"refined{'-unc' if unc else ''}-in-noise{cfg.world_noise:g}{data}"


def variants(cfg: SwapConfig) -> list[tuple[str, list[str]]]:
    """(run name part, iterate.py flags) of each refinement in the other world model."""
    out = [(other_name(cfg), [])]
    return [*out, (other_name(cfg, unc=True), ["--no-uncertainty"])] if cfg.unc else out


def compose(start: Path, world: Path, into: Path) -> Path:
    """A run directory holding the start's policy and the other world model, for --init."""
    into.mkdir(parents=True, exist_ok=True)
    shutil.copy2(start / "policy.pt", into / "policy.pt")
    shutil.copy2(world / "world_model.pt", into / "world_model.pt")
    return into


def plan_mover(start: Path, episodes: list[Path]):
    """How far refinement moved the start's plan, as a function of a refined checkpoint:
    null_candidates' measure (mean |Δμ| by channel and the signed throttle shift) on the start's
    recorded frames, which are sampled and planned by the start once."""
    from export.parity import sample_frames
    from research.null_candidates import FRAMES, plan, plan_move, throttle_shift
    from training import checkpoint as ck

    frames = sample_frames([str(e) for e in episodes], max_frames=FRAMES)
    before = plan(ck.load_policy(start)[0], frames)

    def moved(refined: Path) -> dict:
        after = plan(ck.load_policy(refined)[0], frames)
        return plan_move(after, before) | {"throttle_signed": throttle_shift(after, before)}

    return moved


def chain(cfg: SwapConfig, step: StudyStep, seed: int, rows: list[dict]) -> None:
    c, k = chain_paths(cfg, seed), cfg.policy_rounds
    runs = Path(cfg.out) / "runs" / c.tag
    labels = collision_labels(cfg.takeovers_as_collisions)
    if c.world_from is not None:  # the other world model, learnt here on part of its data
        argv = world_model_cmd(cfg.study, list(c.world_episodes), c.world, c.world_from, seed,
                               labels)  # fmt: skip
        step(f"train-noise{cfg.world_noise:g}-seed{seed}-{c.world.name}", argv, c.world / ".done")
        if not (c.world / "world_model.pt").is_file():  # a resumed run's count stops here
            return
    init = compose(c.start, c.world, runs / f"takeovers{k}-{other_name(cfg)}-init")
    evaluated, driven = [], {}
    for model, run in c.checks_rows(k):
        result = checked(cfg, run)
        if result is None:  # placements the check did not drive (validation): driven here
            result = runs / run.name / f"eval{suffix(cfg)}.json"
            result.parent.mkdir(parents=True, exist_ok=True)
            driven[result] = evaluate(cfg.study, step, f"{c.tag}-{model}{suffix(cfg)}",
                                      run / "policy.onnx", result)  # fmt: skip
        evaluated.append((model, run, result))
    swapped = set()
    for name, flags in variants(cfg):
        run, model = runs / f"takeovers{k}-{name}", f"takeovers{k}+{name}"
        argv = refine_cmd(cfg.study, c.data, run, init, seed, labels, flags)
        step(f"train-{c.tag}-{run.name}", argv, run / ".done")
        result = run / f"eval{suffix(cfg)}.json"
        driven[result] = evaluate(cfg.study, step, f"{c.tag}-{model}{suffix(cfg)}",
                                  run / "policy.onnx", result)  # fmt: skip
        evaluated.append((model, run, result))
        swapped.add(result)
    counting = getattr(step, "counting", False)  # a resumed run's count: rows thrown away
    mover = None
    for name, run, out in evaluated:
        driving = driven.get(out) or (output_of(step, out) if out.is_file() else None)
        if not driving:
            continue
        refined = run / "policy.pt"
        moved = None
        if "+" in name and not counting and refined.is_file():
            mover = mover or plan_mover(c.start / "policy.pt", c.data)
            moved = mover(refined)
        row = {"model": name, "seed": seed, "run": str(run), "moved": moved,
               "aggregate": driving.get("aggregate"), "runs": driving.get("runs", [])}  # fmt: skip
        rows.append(row | ({"world_model": world_model_facts(c.world)} if out in swapped else {}))


def world_model_facts(run: Path) -> dict | None:
    """What a world model learnt from and how its checks scored it (its run's metrics.json)."""
    path = run / "metrics.json"
    if not path.is_file():
        return None
    m = json.loads(path.read_text())
    metrics, data = m.get("metrics") or {}, m.get("data") or {}
    return {"run": str(run), "train_frames": data.get("train_frames"),
            "collision_frames": data.get("collision_frames"),
            "response_steering_risk": metrics.get("response_steering_risk"),
            "collision_auroc_held_out": metrics.get("collision_auroc"),
            "counterfactual": m.get("counterfactual")}  # fmt: skip


def parse(argv: list[str] | None) -> SwapConfig:
    p, cfg = read_sets(argv, SwapConfig(), "research.world_model_swap", __doc__, "SwapConfig")
    for option in ("policy_rounds", "world_rounds"):
        if getattr(cfg, option) < 1:
            p.error(f"{option}: {getattr(cfg, option)} (1 or more)")
    if not cfg.seeds:
        p.error("seeds: none given")
    if cfg.world_data not in WORLD_DATA:
        p.error(f"world_data: {cfg.world_data!r} (one of {', '.join(WORLD_DATA)})")
    cfg = dataclasses.replace(cfg, demo_noise=(cfg.policy_noise,))
    cfg = dataclasses.replace(cfg, study=study_for(p, cfg))
    problems = missing_inputs(cfg)
    if problems:
        p.error(
            f"{problems[0]}" + (f" (and {len(problems) - 1} more)" if len(problems) > 1 else "")
        )
    return cfg


def results_name(cfg: SwapConfig) -> str:
    """The swap's files' name: one OUT may hold several swaps sharing the world models learnt
    there, each driven on several sets of placements (test, validation), a file for each."""
    return f"swap-noise{cfg.policy_noise:g}-{other_name(cfg)}{suffix(cfg)}"


def moves_table(rows: list[dict]) -> str:
    """Markdown: per refined model, the plan's move on the start's frames, mean over seeds."""
    lines = ["| refined model | seeds | \\|Δ steering\\| | \\|Δ throttle\\| "
             "| Δ throttle (signed) |", "|---|---|---|---|---|"]  # fmt: skip
    for model in dict.fromkeys(r["model"] for r in rows if r.get("moved")):
        moved = [r["moved"] for r in rows if r["model"] == model and r.get("moved")]
        mean = {key: sum(m[key] for m in moved) / len(moved)
                for key in ("steering", "throttle", "throttle_signed")}  # fmt: skip
        lines.append(f"| {model} | {len(moved)} | {mean['steering']:.4f} | "
                     f"{mean['throttle']:.4f} | {mean['throttle_signed']:+.4f} |")  # fmt: skip
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    cfg = parse(argv)
    out, started = Path(cfg.out), time.monotonic()
    out.mkdir(parents=True, exist_ok=True)
    k = cfg.policy_rounds
    trains = [step_kind(f"train-noise0-seed0-takeovers{k}-{name}") for name, _ in variants(cfg)]
    kinds = Counter({kind: len(cfg.seeds) for kind in trains})
    undriven = sum(checked(cfg, run) is None for seed in cfg.seeds
                   for _, run in chain_paths(cfg, seed).checks_rows(k))  # fmt: skip
    kinds["eval"] = len(variants(cfg)) * len(cfg.seeds) + undriven
    if cfg.world_data != "all":
        learnt = f"train-noise0-seed0-takeovers{cfg.world_rounds}-{cfg.world_data}-world-model"
        kinds[step_kind(learnt)] = len(cfg.seeds)

    def walk(step: StudyStep) -> list[dict]:
        chains = [functools.partial(chain, cfg, step, seed) for seed in cfg.seeds]
        return run_chains(chains)[0]

    finished = finished_steps(out, kinds, walk)
    rows = walk(StudyStep(out, kinds, parallel=cfg.parallel, cwd=ROOT, finished_before=finished))
    other = f"takeovers{k}+{other_name(cfg)}"
    pairs = [(other, f"takeovers{k}"), (f"takeovers{k}+refined", f"takeovers{k}"),
             (other, f"takeovers{k}+refined"), (other, f"IL-equal-takeovers{k}"),
             (f"takeovers{k}+refined", f"IL-equal-takeovers{k}")]  # fmt: skip
    if cfg.unc:
        pairs += [(other, f"takeovers{k}+{other_name(cfg, unc=True)}")]
    which = {
        "all": f"world model of round {cfg.world_rounds}",
        "demos": "demonstrations, a world model learnt on them alone",
        "rounds": f"take-over rounds 1-{cfg.world_rounds}, a world model learnt on them alone",
    }
    text = (f"σ {cfg.policy_noise:g}'s round {k} ({cfg.policy_out}) refined in σ "
            f"{cfg.world_noise:g}'s {which[cfg.world_data]} ({cfg.world_out}):"
            f"\n\n{report(rows, pairs)}\n\nHow far refinement moved the plan, on the start's "
            f"recorded frames:\n\n{moves_table(rows)}")  # fmt: skip
    results = {"config": dataclasses.asdict(cfg), "rows": rows,
               "wall_s": time.monotonic() - started, "environment": environment()}  # fmt: skip
    name = results_name(cfg)
    (out / f"results-{name}.json").write_text(json.dumps(results, indent=1) + "\n")
    (out / f"table-{name}.md").write_text(text + "\n")
    print("\n" + text + f"\n\nwritten: {out}/results-{name}.json, {out}/table-{name}.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
