"""The simulator's own speed: camera renders, physics steps and gymnasium steps per second.

Measured on one core (the process is pinned to one CPU while it runs), along laps driven by the
scripted expert on the hard layout, so the camera sees what training sees: fences near and far
and up to eight obstacles. Ratio printed: renders/s against the 1000/s target (DESIGN §8).
"""

from __future__ import annotations

import contextlib
import os
import time

from carrt.sim.env import CarrtSimEnv
from carrt.sim.expert import ScriptedExpert
from carrt.sim.render import Renderer
from carrt.sim.world import SimWorld

TARGET_RENDERS_PER_S = 1000.0
PHYSICS_HZ = 200.0
CONTROL_HZ = 10.0
SUBSTEPS = round(PHYSICS_HZ / CONTROL_HZ)


@contextlib.contextmanager
def one_core():
    """Pin to a single CPU for the measurement, so numbers mean 'per core'."""
    if not hasattr(os, "sched_setaffinity"):
        yield None
        return
    before = os.sched_getaffinity(0)
    cpu = min(before)
    os.sched_setaffinity(0, {cpu})
    try:
        yield cpu
    finally:
        os.sched_setaffinity(0, before)


def drive(layout: str, sim_seconds: float) -> tuple[list, float, int, int]:
    """Expert laps at PHYSICS_HZ: poses at CONTROL_HZ, world-step seconds, steps, collisions."""
    world = SimWorld(layout=layout, seed=0)
    expert = ScriptedExpert(world.track, world.params)
    poses, spent, steps = [], 0.0, 0
    dt = 1.0 / PHYSICS_HZ
    for _ in range(round(sim_seconds * CONTROL_HZ)):
        car = world.car
        poses.append((car.x, car.y, car.yaw))
        steering, throttle = expert.act(car)
        start = time.perf_counter()
        for _ in range(SUBSTEPS):
            info = world.step(dt, steering, throttle)
        spent += time.perf_counter() - start
        steps += SUBSTEPS
        if info.collision:
            world.reset()
            expert.reset()
    return poses, spent, steps, world.collisions


def renders_per_second(layout: str, poses: list, min_seconds: float = 2.0) -> float:
    renderer = Renderer(SimWorld(layout=layout, seed=0).track)
    n, start = 0, time.perf_counter()
    while time.perf_counter() - start < min_seconds:
        for pose in poses:
            renderer.render(*pose)
        n += len(poses)
    return n / (time.perf_counter() - start)


def env_steps_per_second(layout: str, control_steps: int = 1500) -> dict:
    env = CarrtSimEnv(layout=layout, seed=0, control_hz=CONTROL_HZ, physics_hz=PHYSICS_HZ)
    expert = ScriptedExpert(env.track, env.world.params)
    env.reset(seed=0)
    spent, episodes = 0.0, 1
    for _ in range(control_steps):
        action = expert.act(env.car)
        start = time.perf_counter()
        _, _, terminated, truncated, _ = env.step((action[0], max(action[1], 0.0)))
        spent += time.perf_counter() - start
        if terminated or truncated:
            env.reset()
            expert = ScriptedExpert(env.track, env.world.params)
            episodes += 1
    return {"env_steps_per_s": control_steps / spent, "env_episodes": episodes}


def run() -> dict:
    layout = "hard"
    with one_core() as cpu:
        poses, world_s, world_steps, collisions = drive(layout, sim_seconds=60.0)
        render_hard = renders_per_second(layout, poses)
        render_empty = renders_per_second("empty", poses)
        env = env_steps_per_second(layout)
    result = {
        "cpu": cpu,
        "layout": layout,
        "poses": len(poses),
        "renders_per_s": render_hard,
        "renders_per_s_empty_layout": render_empty,
        "ratio_renders_over_target": render_hard / TARGET_RENDERS_PER_S,
        "world_steps_per_s": world_steps / world_s,
        "world_physics_hz": PHYSICS_HZ,
        "world_realtime_factor": world_steps / PHYSICS_HZ / world_s,
        "expert_collisions": collisions,
        **env,
        "env_realtime_factor": env["env_steps_per_s"] / CONTROL_HZ,
    }
    print(
        f"   camera: {render_hard:,.0f} renders/s on one core ({layout} layout; "
        f"{render_empty:,.0f}/s without obstacles) "
        f"= {result['ratio_renders_over_target']:.2f}x the 1000/s target"
    )
    print(
        f"   world: {result['world_steps_per_s']:,.0f} physics steps/s at "
        f"{PHYSICS_HZ:.0f} Hz, no camera = {result['world_realtime_factor']:.0f}x real time"
    )
    print(
        f"   gymnasium env: {env['env_steps_per_s']:,.0f} control steps/s "
        f"({SUBSTEPS} physics substeps + one render each) "
        f"= {result['env_realtime_factor']:.0f}x real time at {CONTROL_HZ:.0f} Hz"
    )
    return result


if __name__ == "__main__":
    run()
