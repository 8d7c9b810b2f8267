"""One training run: data → imitation (→ world model → refinement) → save → export → report.

    carrt-train --episodes episodes/ --out runs/iter1 --profile cpu
    carrt-train --episodes episodes/ --out runs/iter2 --init runs/iter1
    torchrun --nproc_per_node 2 training/iterate.py …          # DistributedDataParallel

This is the machinery of one run, `run()` read top to bottom: training/iterate.py
(`carrt-train`) runs one or two of them per iteration through training/one_run.py (which turns
what can go wrong into one line and the exit status), and the paper's whole loop from them.
Each stage's loop, its loss beside its optimizer step, is in its own module (imitation.py,
world_model_stage.py, refine.py).

A run without `dirl` (carrt-train's default) is imitation alone: from scratch, or with --init
from the previous policy (and its input scaling) on every labelled frame given, the person's
take-overs in the new episodes included (a take-over round). It builds, trains, saves and
reports no world model.

With `dirl` (carrt-train --dirl's second run, into OUT/refined/, and every run of
research/variants/train.py) a run from scratch learns the policy by imitation, then the world
model, then refines the policy in the world model's imagination. With --init it starts from the
previous policy and world model (when that run has one), trains the world model on ALL the
episodes given and refines; imitation does not run again (the DIRL paper's algorithm)
unless `reimitate` is set. With --world-episodes the world model learns those episodes instead
(imitation and refinement still read --episodes). Its policy.pt is the last stage's.

Every number lives in TrainingConfig (training/config.py); a profile name picks model sizes and
a preset of steps and batch sizes (PRESETS), and `--set field=value` overrides any field.
Checkpoints land in OUT/checkpoints every ckpt_every steps; Ctrl-C or SIGTERM finishes the step
in flight and checkpoints it (a second Ctrl-C stops at once), and running the same command again
resumes exactly where the run stopped. Only rank 0 writes files.

Research variants (research/variants/: refinement by search or by outcomes, the counterfactual
check, the drift report) plug in through `Variants`; this module never imports them, and
without them a config that asks for one is refused in one line.
"""

from __future__ import annotations

import dataclasses
import pickle
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from carrt.errors import UserError
from carrt.model_contract import sim_placements
from training import checkpoint as ck
from training.config import TrainingConfig, UsageError
from training.data import Normalisation, compute_normalisation, data_digest
from training.stage_data import StageData, read_episodes, read_world_episodes
from training.trainer import Budget, Dist, RunContext
from training.training_args import init_paths

RESEARCH_ONLY = ("refine_search", "refine_outcomes", "counterfactual_starts")


@dataclass
class Variants:
    """Research variants plugged into an iteration by research/variants/train.py; carrt-train
    runs with none. `refine(cfg, policy, world_model, data, norm, ctx, resume, demonstrations)`
    returns the refinement stage's StageResult, or None to run the paper's refinement; each
    `report` entry, called after export as f(cfg, out, policy=…, world_model=…, windows=…,
    device=…), returns (metrics.json key, value, report.md lines) or None."""

    refine: Callable | None = None
    report: list[Callable] = field(default_factory=list)

    def check(self, cfg: TrainingConfig) -> None:
        if self.refine is not None or self.report:
            return
        asked = [name for name in RESEARCH_ONLY if getattr(cfg, name, False)]
        if asked:
            raise UsageError(
                f"{asked[0]} is a research variant: run it with research/variants/train.py "
                "(a repository checkout), not carrt-train"
            )

    def refinement(self, *args):
        """The refinement stage of a variant (its StageResult), or None for the paper's."""
        return None if self.refine is None else self.refine(*args)


@dataclass
class Start:
    """Where an iteration begins (the paper's Algorithm 1): iteration 1 from scratch, imitation
    first; a later one (--init) from the previous run's policy and world model, without
    imitation, keeping the input scaling the policy learned with."""

    norm: Any  # data.Normalisation
    iteration: int
    stages: list[str]
    policy: dict | None = None  # the previous checkpoint's state dicts
    world_model: dict | None = None
    refine_start: dict | None = None  # a resumed refinement: the policy it started from


def run(cfg: TrainingConfig, dist: Dist | None = None, variants: Variants | None = None) -> dict:
    """One iteration, as Algorithm 1 reads: its data and starting point, then imitation, the
    world model and refinement (those the start asks for, in that order), the models saved,
    the policy exported and the run reported. Returns a summary (also on non-zero ranks)."""
    from training.export_step import export_policy
    from training.imitation import train_imitation
    from training.refine import train_refine
    from training.run_report import report_run
    from training.world_model_stage import collision_class_weight, train_world_model

    dist = dist or Dist()
    variants = variants or Variants()
    cfg.validate()
    variants.check(cfg)
    episodes, train_eps, val_eps = read_episodes(cfg)
    world = read_world_episodes(cfg)
    start = starting_point(cfg, train_eps)
    policy, world_model = build_models(cfg, start)
    digest = data_digest([*train_eps, *(world.train if world else [])])
    resume = resume_checkpoints(cfg, start, digest, policy, world_model)
    ctx, common = run_context(cfg, dist, start, digest, train_eps)
    announce(cfg, ctx, start, resume)
    data = StageData(cfg, train_eps, val_eps, world)
    results = {}
    try:
        if "imitation" in start.stages:
            free, val_free = data.imitation()
            results["imitation"] = train_imitation(
                cfg, policy, free, ctx, resume=resume.get("imitation"), val_dataset=val_free
            )
        if "world_model" in start.stages:
            windows = data.world_windows
            weight = cfg.collision_weight or collision_class_weight(windows.step_labels())
            results["world_model"] = train_world_model(
                cfg, world_model, windows, start.norm, ctx, collision_weight=weight,
                policy=policy, resume=resume.get("world_model"),
                val_dataset=data.world_val_windows,
            )  # fmt: skip
        if "refine" in start.stages:
            demonstrations = data.demonstrations() if cfg.refine_w_imitation else None
            variant = variants.refinement(cfg, policy, world_model, data, start.norm, ctx,
                                          resume.get("refine"), demonstrations)  # fmt: skip
            results["refine"] = variant or train_refine(  # the paper's
                cfg, policy, world_model, data.windows, start.norm, ctx,
                resume=resume.get("refine"), val_dataset=data.val_windows,
                demonstrations=demonstrations, start_policy=start.refine_start,
            )  # fmt: skip
    finally:
        if ctx.writer is not None:
            ctx.writer.flush()
    summary = {"iteration": start.iteration, "stages": results, "out": cfg.out}
    if not dist.is_main:
        return summary
    save_final(cfg, common, start, results, policy, world_model)
    exported = export_policy(cfg, Path(cfg.out))
    summary.update(
        report_run(
            cfg, Path(cfg.out), exported, policy=policy, world_model=world_model,
            norm=start.norm, train_eps=train_eps, val_eps=val_eps, episodes=episodes,
            digest=digest, world=world, results=results, iteration=start.iteration,
            device=dist.device, writer=ctx.writer, world_size=dist.world_size,
            extras=variants.report,
        ),
        exit_code=exported.exit_code,
    )  # fmt: skip
    ctx.writer.close()
    return summary


def starting_point(cfg: TrainingConfig, train_eps: list) -> Start:
    """Imitation alone without `dirl`; with it, the paper's stages (imitation once)."""
    dirl_stages = ["world_model", "refine"] if cfg.dirl else []
    if not cfg.init:
        iteration = 1 if cfg.dirl and cfg.refine_steps > 0 else 0
        return Start(compute_normalisation(train_eps), iteration, ["imitation", *dirl_stages])
    policy_path, wm_path = init_paths(cfg.init)
    try:
        init_ckpt = ck.load_checkpoint(policy_path)
        init_wm = ck.load_checkpoint(wm_path) if cfg.dirl and wm_path.is_file() else None
    except ck.CheckpointError as exc:
        raise UsageError(f"--init {cfg.init}: {exc}") from None
    if init_ckpt["profile"] != cfg.profile:
        raise UsageError(f"--init {cfg.init} has profile {init_ckpt['profile']}, not {cfg.profile}")
    return Start(
        norm=Normalisation.from_dict(init_ckpt["normalisation"]),
        iteration=int(init_ckpt["iteration"]) + 1,
        stages=(["imitation"] if cfg.reimitate or not cfg.dirl else []) + dirl_stages,
        policy=init_ckpt["policy"],
        world_model=None if init_wm is None or cfg.world_model_fresh else init_wm["world_model"],
    )


def build_models(cfg: TrainingConfig, start: Start):
    from training.models import PolicyNet, WorldModel

    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    policy = PolicyNet(cfg.profile_obj)
    world_model = WorldModel(cfg.profile_obj) if cfg.dirl else None  # imitation alone: none
    policy.set_normalisation(start.norm)
    if world_model is not None:
        world_model.set_normalisation(start.norm)
    if cfg.pretrained:  # before the starts and checkpoints, which overwrite what they hold
        for model in filter(None, (policy, world_model)):
            try:
                model.backbone.load_pretrained(cfg.pretrained)
            except (ValueError, RuntimeError, OSError, pickle.UnpicklingError) as exc:
                first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                raise UserError(f"--pretrained: {first}") from None
    if start.policy is not None:
        policy.load_state_dict(start.policy)
    if start.world_model is not None and world_model is not None:
        world_model.load_state_dict(start.world_model)
    return policy, world_model


def resume_checkpoints(cfg: TrainingConfig, start: Start, digest: str, policy, world_model):
    """The stages this run already checkpointed (running the command again resumes)."""
    targets = {s: getattr(cfg, f"{s}_steps") for s in start.stages}
    out = Path(cfg.out) / "checkpoints"
    existing = ck.resumable(out, targets, profile=cfg.profile, digest=digest)
    for stage in start.stages:  # later stages' checkpoints hold the newer weights: load in order
        if stage in existing:
            if stage == "refine":  # its anchor is the policy it started from, not its own
                start.refine_start = {k: v.clone() for k, v in policy.state_dict().items()}
            _load_weights(existing[stage], policy, world_model)
    return existing


def run_context(cfg: TrainingConfig, dist: Dist, start: Start, digest: str, train_eps: list):
    """What every stage shares: checkpoint fields, TensorBoard (rank 0), budget, progress."""
    out, writer = Path(cfg.out), None
    if dist.is_main:
        out.mkdir(parents=True, exist_ok=True)
        from torch.utils.tensorboard import SummaryWriter

        writer = SummaryWriter(str(out / "tensorboard"))
    common = {
        "config": dataclasses.asdict(cfg),
        "profile": cfg.profile,
        "profile_fields": dataclasses.asdict(cfg.profile_obj),  # should the profile change
        "normalisation": start.norm.to_dict(),
        "data_digest": digest,
        "iteration": start.iteration,
        "code_version": ck.code_version(),
        "episodes": [ep.name for ep in train_eps],
        "sim_placements": sim_placements(ep.meta for ep in train_eps),  # export records them
    }
    ctx = RunContext(
        dist=dist, ckpt_dir=out / "checkpoints", common=common, writer=writer,
        budget=Budget(cfg.stop_after or None), progress=cfg.progress,
        num_workers=cfg.num_workers, pace=pace_of(cfg, dist), profile=cfg.profile,
    )  # fmt: skip
    return ctx, common


def announce(cfg: TrainingConfig, ctx: RunContext, start: Start, resume: dict) -> None:
    """training/pace.py, before the first step: each stage's steps still to take."""
    if ctx.pace is None:
        return
    ctx.pace.announce(cfg.profile, [
        (s, getattr(cfg, f"{s}_steps") - (resume[s]["step"] if s in resume else 0),
         getattr(cfg, f"{s}_batch_size")) for s in start.stages
    ])  # fmt: skip


def pace_of(cfg: TrainingConfig, dist: Dist):
    """training/pace.py on rank 0 with progress on: the expected duration and slow-run warning."""
    if not (cfg.progress and dist.is_main):
        return None
    from training.pace import Pace

    return Pace(f"{dist.device}/threads{torch.get_num_threads()}")


def save_final(cfg, common: dict, start: Start, results: dict, policy, world_model) -> None:
    """policy.pt (what export reads) and, with a world model, world_model.pt (what the next
    iteration continues)."""
    out = Path(cfg.out)
    stages = start.stages
    last = next((s for s in reversed(stages) if results[s].steps > 0), stages[-1])
    final = {**common, "stage": last, "step": results[last].steps, "optimizer": None}
    ck.save_checkpoint(
        out / "policy.pt", **{**final, "policy": policy.state_dict(), "world_model": None}
    )
    if world_model is None:
        return
    ck.save_checkpoint(
        out / "world_model.pt",
        **{**final, "policy": policy.state_dict(), "world_model": world_model.state_dict()},
    )


def _load_weights(c: dict, policy, world_model) -> None:
    if c["policy"]:
        policy.load_state_dict(c["policy"])
    if c["world_model"] is not None and world_model is not None:
        world_model.load_state_dict(c["world_model"])
