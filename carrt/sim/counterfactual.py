"""What really happens under other actions: the ground truth a world model is checked against.

    python -m carrt.sim.counterfactual --model run/policy.onnx --layout hard --tracks 200-204 \
        --starts 20 --out cf.npz

Refinement trusts the world model's answer to "what if the car did this instead?". Nothing in
the recorded episodes can check that answer, because a real car lives each moment once. The
simulator can: from one start state it replays several action sequences open-loop and records
what each one really did. `research/variants/counterfactual.py` then asks the world model the same
questions and scores it (collision AUROC across sequences from one start, speed error, rank
correlation of the refinement objective). Evaluation only: nothing here is a training input.

Start states: on each (held-out) placement the scripted expert, with noise on its steering,
drives from a place 2.5-4 m before a randomly chosen obstacle for 0.5-1.5 s, so most starts
face an obstacle within the plan's horizon at a speed the car really reaches. From there the
sequences are the policy's plan μ and perturbations of it (steering shifted by ±0.3 / ±0.6,
throttle off, a short brake, full throttle, one constant random steering), executed as on the
car: one command per 100 ms, the board's throttle rise limit, the simulated servo and motor lags.
A sequence's steps after its first collision are masked (the car stops there, as it does when
the loop e-stops it).
"""

from __future__ import annotations

import argparse
import copy
import json
import sys

import numpy as np

from carrt.arg_types import parse_int_list
from carrt.errors import EXIT_USAGE, UserError
from carrt.sim.expert import ScriptedExpert
from carrt.sim.render import Renderer
from carrt.sim.track import LAYOUTS, project
from carrt.sim.world import SimWorld
from firmware_bridge.timing import CONTROL_PERIOD_S

CHUNK_S = 0.01  # the throttle rise limit is applied every 10 ms
THROTTLE_RISE_PER_S = 2.0  # the board's default pwm.slew_per_s (rises only; falls are immediate)
STEERING_SHIFTS = (-0.6, -0.3, 0.3, 0.6)
BRAKE_STEPS = 3  # a person's brake: a short hard one, then off the throttle (no reversing)
SEQUENCE_NAMES = (
    "plan",
    *(f"steer{d:+.1f}" for d in STEERING_SHIFTS),
    "lift",
    "brake",
    "full",
    "random",
)


def sequences(plan: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(K, H, 2) action sequences from one (H, 2) plan, in SEQUENCE_NAMES order."""
    out = [plan]
    for shift in STEERING_SHIFTS:
        seq = plan.copy()
        seq[:, 0] = np.clip(seq[:, 0] + shift, -1.0, 1.0)
        out.append(seq)
    lift, brake, full, rand = plan.copy(), plan.copy(), plan.copy(), plan.copy()
    lift[:, 1] = 0.0
    brake[:, 1] = 0.0
    brake[:BRAKE_STEPS, 1] = -0.5
    full[:, 1] = 1.0
    rand[:, 0] = rng.uniform(-1.0, 1.0)
    out += [lift, brake, full, rand]
    return np.stack(out).astype(np.float32)


def clone(world: SimWorld) -> SimWorld:
    """An independent copy of the world's state; the (immutable) track is shared."""
    twin = copy.copy(world)
    twin._locator = copy.copy(world._locator)
    return twin


def hold(world: SimWorld, steering: float, throttle: float, throttle_now: float) -> float:
    """One control period of a command, as the board applies it (throttle rises at most
    THROTTLE_RISE_PER_S, falls at once); stops at a collision. Returns the throttle reached."""
    for _ in range(round(CONTROL_PERIOD_S / CHUNK_S)):
        throttle_now = min(float(throttle), throttle_now + THROTTLE_RISE_PER_S * CHUNK_S)
        if world.step(CHUNK_S, float(steering), throttle_now).collision:
            break
    return throttle_now


def execute(world: SimWorld, actions: np.ndarray, throttle_now: float) -> dict[str, np.ndarray]:
    """Run (H, 2) actions open-loop: per step the speed after it, whether it collided, a mask."""
    h = len(actions)
    speed, collision, mask = np.zeros(h, np.float32), np.zeros(h, np.float32), np.zeros(h)
    for k, (steering, throttle) in enumerate(actions):
        mask[k] = 1.0
        throttle_now = hold(world, steering, throttle, throttle_now)
        speed[k] = world.car.v
        if world.collided:
            collision[k] = 1.0
            break
    return {"speed": speed, "collision": collision, "mask": mask.astype(np.float32)}


def start_state(world: SimWorld, rng: np.random.Generator) -> tuple[SimWorld, float] | None:
    """Drive the noisy expert towards a random obstacle; None if it crashed on the way."""
    track = world.track
    obstacle = track.obstacles[int(rng.integers(len(track.obstacles)))]
    s_obstacle = project(track, obstacle.x, obstacle.y)[0]
    world.reset(world.clear_place_before(s_obstacle - rng.uniform(2.5, 4.0)))
    expert = ScriptedExpert(track, world.params)
    throttle_now = 0.0
    for _ in range(int(rng.integers(5, 16))):
        steering, throttle = expert.act(world.car)
        steering = float(np.clip(steering + rng.normal(0.0, 0.3), -1.0, 1.0))
        throttle_now = hold(world, steering, throttle, throttle_now)
        if world.collided:
            return None
    return world, throttle_now


def generate(
    policy, layout: str, tracks: list[int], starts: int, seed: int = 0
) -> dict[str, np.ndarray]:
    """`starts` start states per placement, len(SEQUENCE_NAMES) sequences from each.

    policy: anything with predict(image, speed) → plan with .mu (H, 2) (carrt.policy.OnnxPolicy).
    """
    rng = np.random.default_rng(seed)
    images, speeds, actions, outcomes, where, poses = [], [], [], [], [], []
    for track_seed in tracks:
        world = SimWorld(layout=layout, seed=track_seed)
        renderer = Renderer(world.track)
        found = attempts = 0
        while found < starts and attempts < 20 * starts:
            attempts += 1
            state = start_state(world, rng)
            if state is None:
                continue
            world, throttle_now = state
            car = world.car
            image = renderer.render(car.x, car.y, car.yaw)
            plan = np.asarray(policy.predict(image, float(car.v)).mu, dtype=np.float32)
            seqs = sequences(plan, rng)
            results = [execute(clone(world), seq, throttle_now) for seq in seqs]
            images.append(image)
            speeds.append(car.v)
            actions.append(seqs)
            outcomes.append(results)
            where.append((track_seed, world.s))
            poses.append((car.x, car.y, car.yaw, car.steer, car.motor))
            found += 1
    if not images:
        raise UserError("no start state found: every noisy approach crashed")

    def field(name: str) -> np.ndarray:
        return np.asarray([[r[name] for r in per_start] for per_start in outcomes], np.float32)

    return {
        "image": np.stack(images),
        "speed": np.asarray(speeds, np.float32),
        "actions": np.stack(actions),
        "true_speed": field("speed"),
        "true_collision": field("collision"),
        "mask": field("mask"),
        "where": np.asarray(where, np.float64),
        # the start's car state (arena x, y, yaw; wheel angle, motor): evaluation only, e.g. to
        # score a world model's motion against a perfect map of the placement
        "pose": np.asarray(poses, np.float64),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m carrt.sim.counterfactual", description=__doc__)
    p.add_argument("--model", required=True, help="policy .onnx whose plans start the sequences")
    p.add_argument("--layout", default="hard", choices=sorted(LAYOUTS))
    p.add_argument("--tracks", default="200-204", help="held-out placements, e.g. 200-204")
    p.add_argument("--starts", type=int, default=20, help="start states per placement")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help=".npz to write")
    a = p.parse_args(argv)
    try:
        from carrt.policy import OnnxPolicy

        tracks = parse_int_list(a.tracks, "tracks")
        if not tracks or a.starts < 1:
            raise UserError("need at least one placement and --starts >= 1")
        policy = OnnxPolicy(a.model, intra_op_threads=1)
        data = generate(policy, a.layout, tracks, a.starts, a.seed)
        meta = {"layout": a.layout, "tracks": tracks, "starts": a.starts, "seed": a.seed,
                "model": str(a.model), "model_sha256": policy.sha256,
                "sequences": list(SEQUENCE_NAMES)}  # fmt: skip
        np.savez_compressed(a.out, meta=np.asarray(json.dumps(meta)), **data)
    except UserError as exc:
        print(f"counterfactual: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    hits = data["true_collision"].max(axis=2)
    print(
        f"wrote {a.out}: {len(data['image'])} starts × {hits.shape[1]} sequences, "
        f"{hits.mean():.0%} of sequences collide within {data['actions'].shape[2]} steps"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
