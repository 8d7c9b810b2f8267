"""The ceiling: model-predictive control with the simulator itself as a perfect world model.

    python -m research.ceiling --models weak=research/runs/ceiling/weak/policy.onnx,demo \
        --forms plain,speed,progress,survival --tracks 200-219 --seeds 0,1 --seconds 30 \
        --out research/runs/ceiling/runs --results research/results/ceiling.json.gz --jobs 1

Why: refinement in a learned world model trusts that model's answer to "what if the car did
this instead?". Before asking how much a learned model gets wrong, this asks how much a model
that gets nothing wrong could give: at every 10 Hz control step the policy's plan μ and 12
alternatives around it (CANDIDATES) are each run open-loop for H steps in a clone of the
simulator, scored by an objective form (FORMS), and the first action of the best plan is
driven. What that gains over the policy alone (`plain`) is the most any world model with that
objective and that search could recover; every learned model is judged by the fraction of it it
recovers. The objective forms are compared on it too, since here the truth is free: `speed` is
the paper's (it pays for speed anywhere), `progress` and `survival` pay for metres along the
track, which only the simulator knows exactly (allowed here: this is the ceiling, not a policy).

The drive itself is a compact copy of what `carrt eval` runs, so plain and controlled runs
differ only in the choice of action: one command per 100 ms held through the board's throttle
rise limit (carrt.sim.counterfactual.hold), the camera frame the latest of a 30 fps camera whose
phase the run seed draws (as carrt.sim.rig does), the speed the car's, and after a collision
the person's auto-reset and a RESET_PAUSE_S standstill (SimPilot's e-stop, settle, clear, arm).
No board, no arbitration, no rendering in the rollouts: that is what makes 13 × H steps per
control step affordable on one core.

Validation placements only (the `hard` layout's 200-219 by default); the test placements
100-199 are refused. Each run is one JSON under OUT, kept: a second call skips it.
"""

from __future__ import annotations

import argparse
import copy
import gzip
import json
import math
import random
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

if __package__ in (None, ""):  # run as a file, from any directory: the repository on the path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np

from carrt.arg_types import parse_int_list
from carrt.errors import EXIT_USAGE, UserError
from carrt.sim.counterfactual import THROTTLE_RISE_PER_S
from carrt.sim.metrics import TrajectoryRecorder
from carrt.sim.world import SimWorld, StepInfo
from firmware_bridge.timing import CONTROL_PERIOD_S
from research.paths import at_root

CHUNK_S = 0.01  # the driven period in 10 ms chunks: throttle rise limit and camera poses
CAMERA_FPS = 30.0
RESET_PAUSE_S = 1.0  # the car stands after an auto-reset: e-stop, settle, clear, arm (SimPilot)
EVALUATION_TRACKS = frozenset(range(100, 200))  # the test placements: never driven here

# The 13 plans, each (name, steering offset, throttle factor) applied to every step of μ and
# clipped to the policy's bounds: μ itself, six steering offsets, two throttle scalings, and
# the four combinations of ±0.3 steering with either throttle scaling. μ is first, so a tie
# keeps it.
CANDIDATES: tuple[tuple[str, float, float], ...] = (
    ("mu", 0.0, 1.0),
    ("steer-0.6", -0.6, 1.0),
    ("steer-0.3", -0.3, 1.0),
    ("steer-0.15", -0.15, 1.0),
    ("steer+0.15", 0.15, 1.0),
    ("steer+0.3", 0.3, 1.0),
    ("steer+0.6", 0.6, 1.0),
    ("throttle*0.5", 0.0, 0.5),
    ("throttle*1.2", 0.0, 1.2),
    ("steer-0.3,throttle*0.5", -0.3, 0.5),
    ("steer+0.3,throttle*0.5", 0.3, 0.5),
    ("steer-0.3,throttle*1.2", -0.3, 1.2),
    ("steer+0.3,throttle*1.2", 0.3, 1.2),
)
FORMS = ("plain", "speed", "progress", "survival")  # plain: the policy alone, no search
# With a learnt world model only, a diagnostic: its imagined paths and survival, the progress
# along them measured on the simulator's track (which a car does not have): what a perfect
# progress signal would add to the learnt hazard.
TRUE_PROGRESS = "survival-true-progress"
MAX_GAIN_PER_METRE = 2.0  # progress counted per metre driven, at most (hold_counted says why)
TIE_TOLERANCE = 1e-9  # a plan must beat μ by more than this to replace it


@dataclass(frozen=True)
class Weights:
    """The objective forms' constants. The speed form's are training's refinement weights (the
    paper's objective as carrt refines with it); the crash cost of the progress forms is larger
    than any plan's progress over the default horizon (2.5 m/s top speed × 1 s), so no crash
    is worth its metres; survival discounts each step ahead by `discount` (the first step is the one
    that runs; later ones are replanned) and adds the speed at the horizon's end × `beyond_s`
    for what lies beyond it, when the plan survived."""

    w_speed: float = 1.0
    w_collision: float = 10.0
    crash_cost_m: float = 10.0
    discount: float = 0.9
    beyond_s: float = 0.5

    @classmethod
    def from_training(cls) -> Weights:
        from training.config import TrainingConfig

        cfg = TrainingConfig()
        return cls(w_speed=cfg.refine_w_speed, w_collision=cfg.refine_w_collision)


@dataclass(frozen=True)
class Outcome:
    """What a plan really did, per step ahead (after each 100 ms): speed (m/s), progress along
    the track since the start as hold_counted counts it (m) and whether the car stands
    collided."""

    speed: np.ndarray
    progress: np.ndarray
    collided: np.ndarray


# -- the search -------------------------------------------------------------------------------


def clone(world: SimWorld) -> SimWorld:
    """An independent copy of the world's state for a rollout (the immutable track, params and
    obstacle list shared): ~5 µs, where copy.deepcopy takes ~1.4 ms copying the track too."""
    twin = copy.copy(world)
    twin._locator = copy.copy(world._locator)
    twin.car = copy.copy(world.car)
    return twin


def candidates(mu: np.ndarray, horizon: int, low, high) -> np.ndarray:
    """(len(CANDIDATES), horizon, 2) plans from the policy's (H_policy, 2) plan μ; a horizon
    longer than μ's holds its last step."""
    mu = np.asarray(mu, np.float32)
    steps = np.minimum(np.arange(horizon), len(mu) - 1)
    base = mu[steps]
    plans = np.repeat(base[None], len(CANDIDATES), axis=0)
    for i, (_, d_steer, k_throttle) in enumerate(CANDIDATES):
        plans[i, :, 0] += d_steer
        plans[i, :, 1] *= k_throttle
    return np.clip(plans, np.asarray(low, np.float32), np.asarray(high, np.float32))


def hold_counted(world: SimWorld, steering: float, throttle: float, throttle_now: float):
    """One 100 ms command as the board applies it (counterfactual.hold's throttle rise limit,
    stopping at a collision), and the progress it earned: each 10 ms chunk's gain along the
    track, counted only while the car is inside the track's markings (track limits) and never
    more than MAX_GAIN_PER_METRE × the metres it drove. Why both: where two legs of the track
    lie close, a car cutting across the infield is projected onto the nearer leg at once, and
    the simulator's own progress jumps metres ahead; a search on that progress finds the cut
    (measured: placement 200, a survival-form search crossed the infield in its first 5 s).
    Returns (throttle reached, metres earned)."""
    earned = 0.0
    for _ in range(round(CONTROL_PERIOD_S / CHUNK_S)):
        throttle_now = min(float(throttle), throttle_now + THROTTLE_RISE_PER_S * CHUNK_S)
        x, y, before = world.car.x, world.car.y, world.progress
        info = world.step(CHUNK_S, float(steering), throttle_now)
        if not world.off_track:
            driven = math.hypot(world.car.x - x, world.car.y - y)
            gain = world.progress - before
            earned += min(max(gain, -driven), MAX_GAIN_PER_METRE * driven)
        if info.collision:
            break
    return throttle_now, earned


def rollout(world: SimWorld, plan: np.ndarray, throttle_now: float) -> Outcome:
    """Run the plan open-loop in a clone of `world` (which stays untouched)."""
    twin = clone(world)
    h = len(plan)
    speed, progress = np.zeros(h), np.zeros(h)
    collided = np.zeros(h, dtype=bool)
    total = 0.0
    for k, (steering, throttle) in enumerate(plan):
        throttle_now, earned = hold_counted(twin, float(steering), float(throttle), throttle_now)
        total += earned
        speed[k], progress[k] = twin.car.v, total
        if twin.collided:  # it stands there, collided, for the rest of the horizon
            collided[k:] = True
            progress[k:] = total
            break
    return Outcome(speed, progress, collided)


def score(form: str, outcome: Outcome, w: Weights) -> float:
    """Higher is better. speed: Σ (w_speed·v − w_collision·collided) per step, the paper's
    objective with the true speed and collision; progress: metres along the track over the
    horizon, less the crash cost; survival: each step's progress discounted by how far ahead
    it is, counted until the crash, the crash cost discounted the same way, and the speed at the
    horizon's end × beyond_s when the plan survived."""
    if form == "speed":
        return float(np.sum(w.w_speed * outcome.speed - w.w_collision * outcome.collided))
    crashed = bool(outcome.collided[-1])
    if form == "progress":
        return float(outcome.progress[-1] - w.crash_cost_m * crashed)
    if form == "survival":
        h = len(outcome.progress)
        gains = np.diff(outcome.progress, prepend=0.0)
        alive = ~np.concatenate(([False], outcome.collided[:-1]))  # steps before the crash's
        weights = w.discount ** np.arange(h)
        total = float(np.sum(weights * gains * alive))
        if crashed:
            first = int(np.argmax(outcome.collided))
            return total - w.crash_cost_m * w.discount**first
        return total + w.discount**h * float(outcome.speed[-1]) * w.beyond_s
    raise ValueError(f"unknown objective form {form!r}")


def choose(
    world: SimWorld, plans: np.ndarray, throttle_now: float, form: str, w: Weights
) -> tuple[int, np.ndarray]:
    """The index of the best plan (μ, index 0, unless another beats it) and every score."""
    scores = np.array([score(form, rollout(world, p, throttle_now), w) for p in plans])
    best = int(np.argmax(scores))
    if scores[best] <= scores[0] + TIE_TOLERANCE:
        best = 0
    return best, scores


def true_progress(world: SimWorld, xy: np.ndarray) -> np.ndarray:
    """(K, H) metres along the simulator's track since the start of imagined paths xy (K, H, 2)
    in the car's frame, counted as hold_counted counts them: inside the markings only, never
    more than MAX_GAIN_PER_METRE × the metres driven (a diagnostic: no car knows this)."""
    from carrt.sim.track import project

    car, track = world.car, world.track
    c, s = math.cos(car.yaw), math.sin(car.yaw)
    pts = np.concatenate([np.zeros((len(xy), 1, 2)), xy], axis=1)
    wx, wy = car.x + c * pts[..., 0] - s * pts[..., 1], car.y + s * pts[..., 0] + c * pts[..., 1]
    along, lateral, _ = project(track, wx, wy)
    length = track.length
    gain = (np.diff(along, axis=1) + length / 2) % length - length / 2
    driven = np.hypot(np.diff(wx, axis=1), np.diff(wy, axis=1))
    gain = np.clip(gain, -driven, MAX_GAIN_PER_METRE * driven)
    inside = np.abs(lateral[:, 1:]) <= track.width / 2
    return np.cumsum(np.where(inside, gain, 0.0), axis=1)


def choose_imagined(
    world_model,
    image: np.ndarray,
    speed: float,
    plans: np.ndarray,
    form: str,
    w: Weights,
    world: SimWorld | None = None,
) -> tuple[int, np.ndarray]:
    """As `choose`, the outcomes imagined by a learnt world model from the camera frame and the
    speed alone (what the car has). `world_model`: (ground model, person's line or None). speed:
    the paper's Σ w_speed·v̂ − w_collision·p̂; survival: as `score`'s, with the progress along
    the person's line the frame predicts (research/person_line.py) for the progress along the
    track, and the imagined chance of surviving each step for the certainty of it. How much of
    `choose`'s gain this recovers is the learnt model's grade."""
    import torch

    model, line = world_model
    with torch.no_grad():
        frame = torch.from_numpy(np.ascontiguousarray(image))[None]
        out = model.imagine(
            frame,
            torch.tensor([[speed]], dtype=torch.float32),
            torch.from_numpy(np.asarray(plans, dtype=np.float32)),
        )
        if form == "speed":
            scores = w.w_speed * out["speed"] - w.w_collision * out["p_collision"]
            scores = scores.sum(dim=1).numpy()
        else:
            from research.person_line import progress_along

            k, h = out["speed"].shape
            if form == TRUE_PROGRESS:
                s = torch.from_numpy(true_progress(world, out["poses"][..., :2].double().numpy()))
                s = s.to(out["speed"].dtype)
            else:
                s = progress_along(line(frame).expand(k, -1, -1), out["poses"][..., :2])
            gains = torch.diff(s, dim=1, prepend=torch.zeros_like(s[:, :1]))
            alive = torch.cat([torch.ones_like(s[:, :1]), out["survival"][:, :-1]], dim=1)
            discount = w.discount ** torch.arange(h, dtype=s.dtype)
            scores = (discount * (gains * alive - w.crash_cost_m * out["p_collision"])).sum(1)
            beyond = w.discount**h * out["speed"][:, -1] * w.beyond_s * out["survival"][:, -1]
            scores = (scores + beyond).numpy()
    best = int(np.argmax(scores))
    if scores[best] <= scores[0] + TIE_TOLERANCE:
        best = 0
    return best, scores


# -- one run ----------------------------------------------------------------------------------


def drive_period(world, steering: float, throttle: float, throttle_now: float, poses: list):
    """One 100 ms command on the driven world, as hold() but through a collision to the period's
    end (the clock runs on while the car stands) and with the pose after each chunk kept for
    the camera. Returns (throttle reached, a collision happened, a lap was completed, the
    period's jump, whether the car left the track's markings during it). The jump is the
    progress credited beyond MAX_GAIN_PER_METRE × the metres driven: off the markings, a cut
    across the infield that the lap counter credits; on them, the inside line of a hairpin,
    whose projection onto the centreline turns faster than the car drives."""
    hit = lap = off = False
    before, driven = world.progress, 0.0
    for _ in range(round(CONTROL_PERIOD_S / CHUNK_S)):
        throttle_now = min(float(throttle), throttle_now + THROTTLE_RISE_PER_S * CHUNK_S)
        x, y = world.car.x, world.car.y
        info = world.step(CHUNK_S, float(steering), throttle_now)
        driven += math.hypot(world.car.x - x, world.car.y - y)
        hit |= info.collision
        lap |= info.lap_completed
        off |= world.off_track
        poses.append((world.time, world.car.x, world.car.y, world.car.yaw))
    del poses[: -round(CONTROL_PERIOD_S / CHUNK_S) - 1]
    jump = max(0.0, world.progress - before - MAX_GAIN_PER_METRE * driven)
    return throttle_now, hit, lap, jump, off


def frame_pose(poses: list, now: float, phase_s: float) -> tuple[float, float, float]:
    """The pose at the latest 30 fps camera frame at or before `now` (frames at phase + n/fps)."""
    period = 1.0 / CAMERA_FPS
    frame_t = phase_s + math.floor((now - phase_s) / period + 1e-9) * period
    for t, x, y, yaw in reversed(poses):
        if t <= frame_t + 1e-9:
            return x, y, yaw
    return poses[0][1:]


def uncut_laps_per_min(row: dict, track_length: float) -> float:
    """Laps per minute of driving counted from the metres gained along the track less the cuts
    (`cut_m`): the lap counter credits a cut across the infield, this does not."""
    along = row["progress_per_metre"] * row["distance"] - row["cut_m"]
    minutes = row["driving_time"] / 60.0
    return along / track_length / minutes if minutes > 0 else 0.0


def run(
    policy,
    *,
    layout: str,
    track: int,
    seed: int,
    form: str,
    seconds: float,
    horizon: int,
    weights: Weights,
    world_model=None,
) -> dict[str, Any]:
    """One drive of `seconds` on one placement: the metrics and the choice statistics. With a
    `world_model` (research.ground_model's) the plans are scored in its imagination, not in the
    simulator (speed; survival with the person's line for the progress)."""
    from carrt.sim.render import Renderer

    world = SimWorld(layout=layout, seed=track)
    renderer = Renderer(world.track)
    phase = random.Random(seed).uniform(0.0, 1.0 / CAMERA_FPS)
    recorder = TrajectoryRecorder()
    recorder.record(world)
    poses = [(world.time, world.car.x, world.car.y, world.car.yaw)]
    throttle_now, standing = 0.0, 0
    jumps, off_track, driving_steps = [0.0, 0.0], 0, 0  # jumps: [on the markings, off them]
    chosen = np.zeros(len(CANDIDATES), dtype=int)
    d_steer: list[float] = []
    started = time.perf_counter()
    for _ in range(round(seconds / CONTROL_PERIOD_S)):
        if standing > 0:  # the auto-reset's pause: nothing drives
            standing -= 1
            throttle_now, *_ = drive_period(world, 0.0, 0.0, 0.0, poses)
            recorder.record(world, StepInfo(False, "", False), resetting=True)
            continue
        driving_steps += 1
        image = renderer.render(*frame_pose(poses, world.time, phase))
        plan = policy.predict(image, float(world.car.v))
        plans = candidates(plan.mu, horizon, policy.action_low, policy.action_high)
        best = 0
        if form != "plain" and world_model is not None:
            best, _ = choose_imagined(
                world_model, image, float(world.car.v), plans, form, weights, world
            )
            chosen[best] += 1
            d_steer.append(abs(float(plans[best, 0, 0] - plans[0, 0, 0])))
        elif form != "plain":
            best, _ = choose(world, plans, throttle_now, form, weights)
            chosen[best] += 1
            d_steer.append(abs(float(plans[best, 0, 0] - plans[0, 0, 0])))
        steering, throttle = plans[best, 0]
        throttle_now, hit, lap, jump, off = drive_period(
            world, steering, throttle, throttle_now, poses
        )
        recorder.record(world, StepInfo(hit, "", lap))
        jumps[off] += jump
        off_track += off
        if hit:  # the person lifts the car back on and it stands a moment
            world.reset()
            throttle_now, standing = 0.0, round(RESET_PAUSE_S / CONTROL_PERIOD_S)
            poses.append((world.time, world.car.x, world.car.y, world.car.yaw))
    m = recorder.metrics(world.track.length)
    minutes = (recorder.t[-1] - recorder.t[0]) / 60.0
    decisions = int(chosen.sum())
    factors = {f"x{k:g}": 0 for k in (0.5, 1.0, 1.2)}
    for (_, _, k), n in zip(CANDIDATES, chosen, strict=True):
        factors[f"x{k:g}"] += int(n)
    row = {
        "track": track,
        "seed": seed,
        "form": form,
        "horizon": horizon,
        "seconds": seconds,
        "completion_ratio": m.completion_ratio,
        "collisions": m.collisions,
        "collisions_per_min": m.collisions / minutes if minutes > 0 else 0.0,
        "laps": m.laps,
        "laps_per_min": m.laps_per_min,
        "lap_time_mean": m.lap_time_mean,
        "progress_per_metre": m.progress_per_metre,
        "average_speed": m.average_speed,
        "distance": m.distance,
        "driving_time": m.driving_time,
        "off_track_share": off_track / driving_steps if driving_steps else 0.0,  # steps that left
        "cut_m": jumps[True],
        "apex_jump_m": jumps[False],
        "decisions": decisions,
        "kept_mu": float(chosen[0] / decisions) if decisions else 1.0,
        "mean_abs_dsteering": float(np.mean(d_steer)) if d_steer else 0.0,
        "throttle_choices": {k: (n / decisions if decisions else 0.0) for k, n in factors.items()},
        "chosen": {name: int(n) for (name, _, _), n in zip(CANDIDATES, chosen, strict=True)},
        "wall_s": time.perf_counter() - started,
    }
    row["uncut_laps_per_min"] = uncut_laps_per_min(row, world.track.length)
    return row


# -- many runs --------------------------------------------------------------------------------

_POLICIES: dict[str, Any] = {}  # per worker process: each policy file loaded once
_WORLD_MODELS: dict[str, Any] = {}


def _world_model(path: str):
    import torch

    from research import ground_model

    if path not in _WORLD_MODELS:
        from research import person_line

        torch.set_num_threads(1)
        line = Path(path).parent / "person_line.pt"
        _WORLD_MODELS[path] = (
            ground_model.load(Path(path)),
            person_line.load(line) if line.is_file() else None,
        )
    return _WORLD_MODELS[path]


def _policy(path: str):
    from carrt.policy import OnnxPolicy

    if path not in _POLICIES:
        _POLICIES[path] = OnnxPolicy(path, intra_op_threads=1)
    return _POLICIES[path]


def run_task(task: dict[str, Any]) -> dict[str, Any]:
    """One run into its JSON file (written whole: a kill leaves none), or the kept one."""
    target = Path(task["file"])
    if target.is_file():
        row = json.loads(target.read_text())
        if "uncut_laps_per_min" not in row:  # a row from before the column
            length = SimWorld(layout=task["layout"], seed=task["track"]).track.length
            row["uncut_laps_per_min"] = uncut_laps_per_min(row, length)
        return row
    policy = _policy(task["path"])
    row = run(
        policy,
        layout=task["layout"],
        track=task["track"],
        seed=task["seed"],
        form=task["form"],
        seconds=task["seconds"],
        horizon=task["horizon"],
        weights=Weights(**task["weights"]),
        world_model=_world_model(task["world_model"]) if task.get("world_model") else None,
    )
    row = {"model": task["model"], "policy": task["path"], "policy_sha256": policy.sha256, **row}
    if task.get("world_model"):
        row["world_model"] = world_model_tag(task["world_model"])
        row["world_model_path"] = task["world_model"]
    target.parent.mkdir(parents=True, exist_ok=True)
    part = target.with_suffix(".part")
    part.write_text(json.dumps(row, indent=1) + "\n")
    part.replace(target)
    return row


SUMMARY = (
    "completion_ratio",
    "collisions_per_min",
    "laps",
    "laps_per_min",
    "uncut_laps_per_min",
    "lap_time_mean",
    "progress_per_metre",
    "average_speed",
    "off_track_share",
    "cut_m",
    "kept_mu",
    "mean_abs_dsteering",
)


def aggregate(rows: list[dict]) -> list[dict]:
    """Mean ± (population) std of each summary metric per (model, form), in the rows' order."""
    cells: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        form = r["form"] + (f" in {r['world_model']}" if r.get("world_model") else "")
        cells.setdefault((r["model"], form), []).append(r)
    out = []
    for (model, form), runs in cells.items():
        cell: dict[str, Any] = {"model": model, "form": form, "runs": len(runs)}
        for name in SUMMARY:
            values = [float(r[name]) for r in runs if r.get(name) is not None]
            mean = sum(values) / len(values) if values else math.nan
            std = math.sqrt(sum((v - mean) ** 2 for v in values) / len(values)) if values else 0
            cell[name] = {"mean": mean, "std": std}
        out.append(cell)
    return out


def table(cells: list[dict]) -> str:
    """The ceiling's table: one row per policy × objective form, mean ± std over the runs."""
    lines = [
        "| policy | form | runs | completion | collisions / min | laps | laps / min | "
        "uncut laps / min | "
        "lap time s | progress / m | avg m/s | off track | cut m | μ kept | mean abs Δsteering |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in cells:

        def pm(name: str, digits: int, c=c) -> str:
            v = c[name]
            return (
                "—" if math.isnan(v["mean"]) else f"{v['mean']:.{digits}f} ± {v['std']:.{digits}f}"
            )

        lines.append(
            f"| {c['model']} | {c['form']} | {c['runs']} | {pm('completion_ratio', 2)} | "
            f"{pm('collisions_per_min', 1)} | {pm('laps', 1)} | {pm('laps_per_min', 2)} | "
            f"{pm('uncut_laps_per_min', 2)} | "
            f"{pm('lap_time_mean', 1)} | {pm('progress_per_metre', 2)} | "
            f"{pm('average_speed', 2)} | {pm('off_track_share', 2)} | {pm('cut_m', 1)} | "
            f"{pm('kept_mu', 2)} | {pm('mean_abs_dsteering', 3)} |"
        )
    return "\n".join(lines)


def parse_models(text: str) -> list[tuple[str, str]]:
    """`demo,weak=path.onnx,other.onnx` → [(label, path)]; a bare path is labelled by its
    file's stem (or its folder's name for a `policy.onnx`)."""
    from carrt.shipped import resolve_model

    out = []
    for item in (s.strip() for s in text.split(",")):
        if not item:
            continue
        label, _, path = item.rpartition("=")
        path = str(resolve_model(path))  # one line naming the missing file
        if not label:
            p = Path(item)
            label = (
                item
                if p.name == item and not p.suffix
                else (p.parent.name if p.stem == "policy" else p.stem)
            )
        out.append((label, path))
    if not out:
        raise UserError("--models: give at least one policy (demo, or NAME=PATH.onnx)")
    return out


def parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="python -m research.ceiling",
        description=__doc__.split("\n")[0],
        epilog="Candidates: " + ", ".join(n for n, _, _ in CANDIDATES) + ".",
    )
    p.add_argument("--models", default="demo", help="policies: demo, NAME=PATH.onnx, PATH.onnx")
    p.add_argument("--forms", default=",".join(FORMS), help=f"objective forms ({', '.join(FORMS)})")
    p.add_argument("--layout", default="hard")
    p.add_argument("--tracks", default="200-219", help="validation placements (never 100-199)")
    p.add_argument("--seeds", default="0,1", help="run seeds (the camera's phase)")
    p.add_argument("--seconds", type=float, default=30.0, help="simulated s per run")
    p.add_argument("--horizon", type=int, default=10, help="steps of 100 ms each plan is run")
    p.add_argument("--out", default="research/runs/ceiling", help="one JSON per run, kept")
    p.add_argument(
        "--results",
        default="",
        help="results file to write, gzipped when it ends in .gz (default: OUT/results.json)",
    )
    p.add_argument("--jobs", type=int, default=1, help="worker processes")
    p.add_argument(
        "--world-model",
        default="",
        help="learnt world models (research.ground_model's ground_model.pt, comma-separated) to "
        "score the plans in instead of the simulator, each in turn: the speed form, and "
        "survival with a person_line.pt beside it",
    )
    return p.parse_args(argv)


def check(a: argparse.Namespace) -> tuple[list[tuple[str, str]], list[str], list[int], list[int]]:
    """Everything wrong with the command line as one UserError, before anything runs."""
    from carrt.layouts import NAMES
    from carrt.policy import OnnxPolicy

    if a.layout not in NAMES:
        raise UserError(f"--layout {a.layout}: not a layout ({', '.join(NAMES)})")
    tracks = parse_int_list(a.tracks, "tracks")
    if not tracks:
        raise UserError("--tracks: give at least one placement")
    if set(tracks) & EVALUATION_TRACKS:
        raise UserError(
            f"--tracks {a.tracks}: the test placements 100-199 are never driven here "
            "(use validation placements, e.g. 200-219)"
        )
    seeds = parse_int_list(a.seeds, "seeds")
    forms = [f.strip() for f in a.forms.split(",") if f.strip()]
    unknown = [f for f in forms if f not in FORMS and not (f == TRUE_PROGRESS and a.world_model)]
    if unknown or not forms:
        raise UserError(f"--forms {a.forms}: expected some of {', '.join(FORMS)}")
    if not seeds:
        raise UserError("--seeds: give at least one run seed")
    if not (a.seconds > 0 and math.isfinite(a.seconds)):
        raise UserError(f"--seconds {a.seconds}: expected a positive number")
    if a.horizon < 1 or a.jobs < 1:
        raise UserError("--horizon and --jobs: expected at least 1")
    for world_model in world_models(a):
        if not Path(world_model).is_file():
            raise UserError(f"--world-model {world_model}: no such file")
        line = Path(world_model).parent / "person_line.pt"
        allowed = {"plain", "speed", TRUE_PROGRESS} | ({"survival"} if line.is_file() else set())
        if set(forms) - allowed:
            raise UserError(
                f"--world-model: the forms {', '.join(sorted(allowed))} only (survival needs "
                f"the person's line beside it: {line}; `python -m research.person_line train`)"
            )
    models = parse_models(a.models)
    for _, path in models:
        OnnxPolicy(path, intra_op_threads=1)  # a broken file: one line now, not in a worker
    return models, forms, tracks, seeds


def main(argv: list[str] | None = None) -> int:
    a = parse(argv)
    try:
        models, forms, tracks, seeds = check(a)
        weights = Weights.from_training()
    except UserError as exc:
        print(f"ceiling: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    out = Path(at_root(a.out))
    tasks = [
        {
            "model": label,
            "path": path,
            "layout": a.layout,
            "track": track,
            "seed": seed,
            "form": form,
            "seconds": a.seconds,
            "horizon": a.horizon,
            "weights": weights.__dict__,
            "world_model": world_model,
            "file": str(
                out
                / label
                / (form if not world_model else f"{form}-imagined")
                / world_model_tag(world_model)
                / f"h{a.horizon}-{a.layout}{track}-seed{seed}.json"
            ),
        }
        for label, path in models
        for track in tracks
        for seed in seeds
        for form in forms
        # plain drives once; every other form in each learnt model (or in the simulator)
        for world_model in ([""] if form == "plain" else world_models(a) or [""])
    ]
    kept = {t["file"] for t in tasks if Path(t["file"]).is_file()}
    todo = len(tasks) - len(kept)
    print(
        f"ceiling: {len(tasks)} runs ({todo} to drive): {len(models)} policies × "
        f"{len(forms)} forms × placements {a.tracks} × seeds {a.seeds}, {a.seconds:g} s, "
        f"H {a.horizon}, {a.jobs} worker(s); runs under {out}",
        flush=True,
    )
    rows, started, driven = [], time.monotonic(), 0
    pool = ProcessPoolExecutor(a.jobs) if a.jobs > 1 else None
    try:
        results = pool.map(run_task, tasks) if pool else map(run_task, tasks)
        for i, (task, row) in enumerate(zip(tasks, results, strict=True), 1):
            driven += task["file"] not in kept
            rows.append(row)
            eta = (time.monotonic() - started) / driven * (todo - driven) if driven else 0.0
            print(
                f"  [{i}/{len(tasks)}] {row['model']} {row['form']:<8} track {row['track']} "
                f"seed {row['seed']}: completion {row['completion_ratio']:.2f}, "
                f"{row['collisions_per_min']:.1f} collisions/min, {row['laps']} laps, "
                f"{row['average_speed']:.2f} m/s (ETA {eta / 60:.0f} min)",
                flush=True,
            )
    finally:
        if pool:
            pool.shutdown()
    results_file = Path(at_root(a.results) if a.results else out / "results.json")
    write_results(a, rows, weights, results_file)
    return 0


def world_models(a: argparse.Namespace) -> list[str]:
    """--world-model's comma-separated files (none: the simulator scores the plans)."""
    return [p.strip() for p in a.world_model.split(",") if p.strip()]


def world_model_tag(path: str) -> str:
    """A folder name for a learnt world model's runs: its run folder's name and file hash."""
    if not path:
        return ""
    import hashlib

    digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()[:8]
    return f"{Path(path).parent.name}-{digest}"


def write_results(a: argparse.Namespace, rows: list[dict], weights: Weights, path: Path) -> None:
    """The results file: date, command, settings, machine, the table's cells and every run."""
    from bench.provenance import environment

    cells = aggregate(rows)
    payload = {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "command": "python -m research.ceiling " + " ".join(sys.argv[1:]),
        "config": {
            "models": a.models,
            "layout": a.layout,
            "tracks": a.tracks,
            "seeds": a.seeds,
            "seconds": a.seconds,
            "horizon": a.horizon,
            "candidates": [list(c) for c in CANDIDATES],
            "weights": weights.__dict__,
            "reset_pause_s": RESET_PAUSE_S,
            "world_model": a.world_model,
        },
        "environment": environment(),
        "aggregate": cells,
        "rows": rows,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(payload, indent=1) + "\n"
    if path.suffix == ".gz":  # research/results/ keeps its larger files compacted
        path.write_bytes(gzip.compress(text.encode(), mtime=0))
    else:
        path.write_text(text)
    print("\n" + table(cells) + f"\n\nwritten: {path}")


if __name__ == "__main__":
    raise SystemExit(main())
