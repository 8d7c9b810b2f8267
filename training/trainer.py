"""What the three stages' loops share around their optimizer step: data order, DDP, clipping,
the learning-rate schedule, logging, checkpoints, the budget and the signals that stop a run.

Every stage is "sample a batch, compute a loss, step Adam with the gradient clipped by global
norm, checkpoint every N steps". Each stage writes that loop itself, its loss beside its
`optimizer.step()` (training/imitation.py, world_model_stage.py, refine.py); `StageLoop` here
holds the rest, one copy for all three, which is what makes resume exact in all of them: the
batch order is a pure function of (seed, stage, step) — an epoch's permutation comes from
DistributedSampler(seed).set_epoch(epoch) and a resumed run skips the batches it already took
without loading them — so a run killed at step k and restarted takes the same batches as one
that never stopped.

Under torchrun the trained module is wrapped in DistributedDataParallel; each process takes
batch_size / world_size windows of a global batch (the paper's batch sizes stay global), and
only rank 0 writes checkpoints, TensorBoard scalars and progress bars.
"""

from __future__ import annotations

import math
import os
import signal
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
import torch.distributed as torch_dist
from torch import nn
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, Dataset
from torch.utils.data.distributed import DistributedSampler
from tqdm import tqdm

from training.checkpoint import save_checkpoint


class StopRequested(Exception):
    """The run's step budget (config stop_after) is spent; a checkpoint was written."""


class Interrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM arrived; the step in flight finished and a checkpoint was written."""


class _Signals:
    """The first SIGINT/SIGTERM asks the loop to stop at the end of the current step (a
    checkpoint taken mid-step would pair weights with the wrong step count); a second one
    interrupts at once, leaving the last periodic checkpoint as the resume point."""

    def __init__(self) -> None:
        self.hit = False
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> _Signals:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                if signal.getsignal(sig) is not signal.SIG_IGN:
                    self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame) -> None:
        if self.hit:
            raise KeyboardInterrupt
        self.hit = True

    def __exit__(self, *exc) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)

    def requested(self, dist: Dist) -> bool:
        """True on every rank as soon as any rank was signalled (all stop at the same step)."""
        if dist.world_size == 1:
            return self.hit
        flag = torch.tensor([float(self.hit)], device=dist.device)
        torch_dist.all_reduce(flag, op=torch_dist.ReduceOp.MAX)
        return bool(flag.item())


@dataclass
class Dist:
    """Where this process sits in a torchrun job (world_size 1 when run plainly)."""

    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def init_distributed(device: str = "auto") -> Dist:
    """Join the torchrun job if there is one: nccl on CUDA, gloo on the CPU."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        dev = torch.device(device)
    except RuntimeError:
        raise ValueError(f"--device {device}: not a device (auto, cpu, cuda, cuda:N)") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"--device {device}: this torch build sees no CUDA device")
        # One process per GPU under torchrun; set_device needs an explicit index.
        dev = torch.device("cuda", local if world > 1 else (dev.index or 0))
        if dev.index >= torch.cuda.device_count():
            raise ValueError(f"--device {device}: only {torch.cuda.device_count()} CUDA devices")
        torch.cuda.set_device(dev)
    elif dev.type != "cpu":
        raise ValueError(f"--device {device}: only cpu and cuda are supported")
    if world > 1 and not torch_dist.is_initialized():
        torch_dist.init_process_group("nccl" if dev.type == "cuda" else "gloo")
    return Dist(device=dev, rank=rank, world_size=world, local_rank=local)


def shutdown_distributed() -> None:
    if torch_dist.is_available() and torch_dist.is_initialized():
        torch_dist.destroy_process_group()


@dataclass
class Budget:
    """Optimizer steps this invocation may still take across all stages (None = unlimited).

    Lets a run stop cleanly mid-stage, as a killed run would, but at a known step: the
    resume tests use it, and so can a user with an hour of GPU time.
    """

    remaining: int | None = None

    def spend(self) -> bool:
        if self.remaining is None:
            return False
        self.remaining -= 1
        return self.remaining <= 0


@dataclass
class RunContext:
    """What a stage needs from the run besides its data and models."""

    dist: Dist = field(default_factory=Dist)
    ckpt_dir: Path | None = None  # None: keep nothing on disk (tests, benchmarks)
    common: dict[str, Any] = field(default_factory=dict)  # checkpoint fields shared by stages
    writer: Any = None  # torch.utils.tensorboard.SummaryWriter on rank 0, or None
    budget: Budget = field(default_factory=Budget)
    progress: bool = False
    num_workers: int = 0
    pace: Any = None  # training.pace.Pace on rank 0 with progress on: expected time, slow runs
    profile: str = ""  # the profile's name, for pace's step rates

    def checkpoint_path(self, stage: str) -> Path | None:
        return None if self.ckpt_dir is None else self.ckpt_dir / f"{stage}.pt"

    def save(self, stage: str, step: int, **fields: Any) -> None:
        path = self.checkpoint_path(stage)
        if path is None or not self.dist.is_main:
            return
        save_checkpoint(path, **{**self.common, "stage": stage, "step": step, **fields})


STAGE_SEED_OFFSETS = {"imitation": 1, "world_model": 2, "refine": 3}


@dataclass
class StageSpec:
    name: str  # "imitation" | "world_model" | "refine"
    steps: int  # optimizer steps in total (a resumed run continues towards this)
    batch_size: int  # global batch, split across processes
    lr: float
    grad_clip: float  # max global gradient norm
    ckpt_every: int  # steps between checkpoints (0: only at the end)
    log_every: int  # steps between logged scalars
    seed: int
    eval_every: int = 0  # steps between held-out evaluations (0: never)
    train_mode: bool = True  # False: the trained module stays in eval() (BatchNorm frozen)
    final_lr_fraction: float = 1.0  # cosine decay to lr·this at the last step (1: constant)

    @classmethod
    def of(cls, cfg: Any, stage: str) -> StageSpec:
        """A stage's spec from the one config (`<stage>_steps`, `_batch_size`, `_lr`, ...).
        Each stage draws from its own seed; refinement keeps the policy in eval mode, as it
        runs on the car (BatchNorm with the statistics of real frames, not of each small batch
        of start frames); imitation decays its learning rate on a cosine."""
        return cls(
            name=stage,
            steps=getattr(cfg, f"{stage}_steps"),
            batch_size=getattr(cfg, f"{stage}_batch_size"),
            lr=getattr(cfg, f"{stage}_lr"),
            grad_clip=cfg.grad_clip,
            ckpt_every=cfg.ckpt_every,
            log_every=cfg.log_every,
            seed=cfg.seed + STAGE_SEED_OFFSETS[stage],
            eval_every=cfg.eval_every,
            train_mode=stage != "refine",
            final_lr_fraction=cfg.imitation_lr_final if stage == "imitation" else 1.0,
        )

    def lr_at(self, step: int) -> float:
        """The learning rate of optimizer step `step` (0-based): a function of the step alone,
        so a resumed run continues on the same schedule without saving a scheduler."""
        if self.final_lr_fraction >= 1.0 or self.steps <= 1:
            return self.lr
        progress = min(1.0, step / (self.steps - 1))
        cosine = 0.5 * (1.0 + math.cos(math.pi * progress))
        return self.lr * (self.final_lr_fraction + (1.0 - self.final_lr_fraction) * cosine)


@dataclass
class StageResult:
    name: str
    steps: int
    history: list[dict] = field(default_factory=list)  # {"step", "loss", ...} per logged step
    seconds: float = 0.0  # wall time of the steps taken in this invocation
    samples: int = 0  # windows processed in this invocation, all processes together

    @property
    def samples_per_s(self) -> float:
        return self.samples / self.seconds if self.seconds > 0 else float("nan")

    def final(self, last: int = 10) -> dict[str, float]:
        """Mean of each scalar over its last few logged values (one step is too noisy)."""
        out: dict[str, float] = {}
        keys = {k for h in self.history for k in h if k != "step"}
        for k in sorted(keys):
            # Per key: validation scalars are logged every eval_every steps only, and must be
            # averaged over the entries that have them, not over every logged step.
            tail = [h[k] for h in self.history if k in h][-last:]
            out[k] = sum(tail) / len(tail)
        return out


def to_device(batch: dict, device: torch.device) -> dict:
    return {k: v.to(device, non_blocking=True) for k, v in batch.items()}


def per_rank_batch(batch_size: int, dist: Dist) -> int:
    return max(1, batch_size // dist.world_size)


def batches(
    dataset: Dataset, spec: StageSpec, dist: Dist, start_step: int, num_workers: int = 0
) -> Iterator[dict]:
    """Batches for steps start_step, start_step+1, … forever, identical whether resumed or not."""
    per_rank = per_rank_batch(spec.batch_size, dist)
    sampler = DistributedSampler(
        dataset, num_replicas=dist.world_size, rank=dist.rank, shuffle=True, seed=spec.seed
    )
    per_epoch = max(1, len(sampler) // per_rank)
    epoch, offset = divmod(start_step, per_epoch)
    gather = getattr(dataset, "get_batch", None)
    while True:
        sampler.set_epoch(epoch)
        order = list(sampler)
        chunks = [order[i * per_rank : (i + 1) * per_rank] for i in range(per_epoch)][offset:]
        if gather is not None:
            # Frames in RAM: one tensor gather per batch beats a DataLoader's per-item calls,
            # and workers would each hold a copy of every frame (num_workers is ignored).
            for chunk in chunks:
                yield gather(chunk)
            epoch, offset = epoch + 1, 0
            continue
        loader = DataLoader(
            dataset,
            batch_sampler=chunks,
            num_workers=num_workers,
            pin_memory=dist.device.type == "cuda",
        )
        yield from loader
        epoch, offset = epoch + 1, 0


def wrap(module: nn.Module, dist: Dist) -> nn.Module:
    if dist.world_size == 1:
        return module
    ids = [dist.device.index] if dist.device.type == "cuda" else None
    # 1×1 convolution weights get gradients whose (meaningless) strides of size-1 dims differ
    # from DDP's buckets; torch warns about performance on every run. Nothing is wrong.
    warnings.filterwarnings("ignore", message="Grad strides do not match bucket view strides")
    return DistributedDataParallel(module, device_ids=ids)


def _mean_across(values: dict[str, float], dist: Dist) -> dict[str, float]:
    if dist.world_size == 1 or not values:
        return values
    keys = sorted(values)
    t = torch.tensor([values[k] for k in keys], dtype=torch.float64, device=dist.device)
    torch_dist.all_reduce(t)
    return dict(zip(keys, (t / dist.world_size).tolist(), strict=True))


class StageLoop:
    """What a stage's own loop shares with the others around its optimizer step: the optimizer
    and the resume, the batches, DDP, the clipping and learning-rate schedule, the logged
    scalars, the checkpoints and the budget and signals that stop a run. Each stage writes its
    loop with its loss beside the step (imitation.py, world_model_stage.py, refine.py):

        loop = StageLoop(spec, ctx, dataset=…, trainable=…, forward=…, checkpoint_fields=…)
        with loop.running() as steps:
            for step, batch in steps:
                loss, metrics = <stage>_loss(loop.model, batch)
                loop.check_finite(loss, step)
                loop.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                clip = loop.clip_and_schedule(step)
                loop.optimizer.step()
                loop.record(step, batch, loss, metrics, clip)
                loop.checkpoint_or_stop(step)
        return loop.result

    `trainable` is what the optimizer steps and `forward` the module DDP wraps (`loop.model`);
    checkpoint_fields() returns the stage's model state dicts for a checkpoint; resume is a
    checkpoint of this stage whose model weights the caller has already loaded.
    """

    def __init__(
        self,
        spec: StageSpec,
        ctx: RunContext,
        *,
        dataset: Dataset,
        trainable: nn.Module,
        forward: nn.Module,
        checkpoint_fields: Callable[[], dict],
        resume: dict | None = None,
        val_fn: Callable[[], dict[str, float]] | None = None,
    ) -> None:
        self.spec, self.ctx, self.dataset = spec, ctx, dataset
        self.checkpoint_fields, self.val_fn = checkpoint_fields, val_fn
        self.params = [p for p in trainable.parameters() if p.requires_grad]
        self.optimizer = torch.optim.Adam(self.params, lr=spec.lr)
        start, history = 0, []
        if resume is not None and resume.get("stage") == spec.name:
            start = int(resume["step"])
            history = list(resume.get("history", []))
            if resume.get("optimizer") is not None:
                self.optimizer.load_state_dict(resume["optimizer"])
        self.result = StageResult(spec.name, start, history)
        self.model = forward  # DDP's wrapper once running

    @contextmanager
    def running(self) -> Iterator[Iterator[tuple[int, dict]]]:
        """(step, batch on the device) for each step still to take; on leaving, the progress
        bar closed, the signal handlers restored and the stage's wall time kept."""
        spec, ctx, result = self.spec, self.ctx, self.result
        if result.steps >= spec.steps:
            yield iter(())
            return
        if len(self.dataset) == 0:
            raise ValueError(f"{spec.name}: no training windows")
        self.model = wrap(self.model, ctx.dist)
        self.model.train(spec.train_mode)
        data = batches(self.dataset, spec, ctx.dist, result.steps, ctx.num_workers)
        show = ctx.progress and ctx.dist.is_main
        self._bar = tqdm(total=spec.steps, initial=result.steps, desc=spec.name,
                         disable=not show, mininterval=0.5)  # fmt: skip
        t0 = time.perf_counter()
        if ctx.pace is not None:
            ctx.pace.begin(ctx.profile, spec.name, spec.batch_size, result.steps, spec.steps)
        steps = ((step, to_device(next(data), ctx.dist.device))
                 for step in range(result.steps, spec.steps))  # fmt: skip
        try:
            with _Signals() as self._signals:
                yield steps
        finally:
            self._bar.close()
            result.seconds = time.perf_counter() - t0
        if ctx.pace is not None:
            ctx.pace.end()

    def check_finite(self, loss: torch.Tensor, step: int) -> None:
        """A diverged loss stops the run before it reaches the weights (the last checkpoint
        stays intact)."""
        if not torch.isfinite(loss):
            raise FloatingPointError(f"{self.spec.name}: loss is {loss.item()} at step {step}")

    def clip_and_schedule(self, step: int) -> tuple[torch.Tensor, float]:
        """After backward(), before the step: the gradient clipped by its global norm and the
        learning rate of this step set. (gradient norm before clipping, learning rate)"""
        grad_norm = nn.utils.clip_grad_norm_(self.params, self.spec.grad_clip)
        lr = self.spec.lr_at(step)
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        return grad_norm, lr

    def record(self, step: int, batch: dict, loss, metrics: dict, clip: tuple) -> None:
        """After the step: counted, its scalars logged every log_every steps (the mean over the
        processes; with the held-out ones every eval_every), the progress advanced."""
        spec, ctx, result = self.spec, self.ctx, self.result
        done = result.steps = step + 1
        result.samples += len(batch["speed"]) * ctx.dist.world_size
        evaluate = self.val_fn is not None and spec.eval_every and done % spec.eval_every == 0
        if evaluate or done % spec.log_every == 0 or done == spec.steps:
            grad_norm, lr = clip
            scalars = {"loss": loss.item(), "grad_norm": float(grad_norm), "lr": lr}
            scalars.update({k: float(v) for k, v in metrics.items()})
            scalars = _mean_across(scalars, ctx.dist)  # same steps on every rank
            if evaluate and ctx.dist.is_main:
                scalars.update({f"val_{k}": v for k, v in self.val_fn().items()})
            result.history.append({"step": done, **scalars})
            if ctx.writer is not None:
                for k, v in scalars.items():
                    ctx.writer.add_scalar(f"{spec.name}/{k}", v, done)
            self._bar.set_postfix(loss=f"{scalars['loss']:.4g}", refresh=False)
        self._bar.update(1)
        if ctx.pace is not None:
            ctx.pace.step()

    def checkpoint_or_stop(self, step: int) -> None:
        """A checkpoint every ckpt_every steps and at the last; when the budget is spent or a
        signal came (on any rank), the checkpoint, then StopRequested or Interrupted."""
        spec, ctx = self.spec, self.ctx
        done = step + 1
        stop = ctx.budget.spend()
        interrupted = self._signals.requested(ctx.dist)
        periodic = spec.ckpt_every and done % spec.ckpt_every == 0
        if stop or interrupted or periodic or done == spec.steps:
            fields = {**self.checkpoint_fields(), "optimizer": self.optimizer.state_dict(),
                      "history": self.result.history}  # fmt: skip
            ctx.save(spec.name, done, **fields)
        if interrupted:
            raise Interrupted(f"{spec.name} step {done}")
        if stop:
            raise StopRequested(f"{spec.name} step {done}")


def param_digest(module: nn.Module) -> dict[str, torch.Tensor]:
    """A detached copy of parameters AND buffers (BatchNorm statistics), for identity checks."""
    return {k: v.detach().clone() for k, v in module.state_dict().items()}
