"""The simulator as a gymnasium environment, so off-the-shelf RL libraries can drive it.

Observation and action are the paper's: a 96×96 RGB frame plus the speed; steering in
[-1, 1] (−1 full left, as the protocol and a real car's `steer_left_us`) and throttle in
[0, 1], held for one 10 Hz control period. Reward is metres gained
along the track (negative when going backwards), minus a penalty on collision; a collision
ends the episode as in the paper, and a run is cut after `max_laps` laps or `max_steps` steps.

Randomness: the obstacle layout comes from the constructor's `seed` (the track seed), so a
policy is compared on a fixed layout unless `options={"track_seed": ...}` asks for another.
`reset(seed=...)` seeds the environment's own generator, which only matters with
`random_start=True` (start at a random obstacle-free arc position instead of the start line).
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from carrt.sim.render import Renderer, top_down
from carrt.sim.track import LAYOUTS, pose_at
from carrt.sim.types import CameraParams
from carrt.sim.world import SimWorld

ENV_ID = "carrt/Sim-v0"
START_CLEARANCE = 0.3  # random starts keep the car's reference point this far from obstacles


def _car(world: SimWorld):
    """The world's car state (`state` where the world names it so, else `car`)."""
    state = getattr(world, "state", None)
    return state if state is not None else world.car


class CarrtSimEnv(gymnasium.Env):
    """One car on one track, stepped at control_hz with physics substeps at physics_hz."""

    metadata: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 10}  # noqa: RUF012

    def __init__(
        self,
        layout: str = "easy",
        seed: int = 0,
        control_hz: float = 10.0,
        physics_hz: float = 200.0,
        max_laps: int = 5,
        max_steps: int = 3000,
        render_mode: str | None = None,
        *,
        collision_penalty: float = 5.0,
        random_start: bool = False,
        camera: CameraParams | None = None,
    ) -> None:
        if layout not in LAYOUTS:
            raise ValueError(f"unknown layout {layout!r}; valid layouts: {', '.join(LAYOUTS)}")
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be None or 'rgb_array', not {render_mode!r}")
        if control_hz <= 0 or physics_hz < control_hz:
            raise ValueError("need 0 < control_hz <= physics_hz")
        self.layout = layout
        self.track_seed = int(seed)
        self.control_hz = float(control_hz)
        self.physics_hz = float(physics_hz)
        self.substeps = max(1, round(physics_hz / control_hz))
        self.max_laps = int(max_laps)
        self.max_steps = int(max_steps)
        self.render_mode = render_mode
        self.collision_penalty = float(collision_penalty)
        self.random_start = random_start
        self.camera = camera if camera is not None else CameraParams()
        self.metadata = {**self.metadata, "render_fps": self.control_hz}
        shape = (self.camera.height, self.camera.width, 3)
        self.observation_space = spaces.Dict(
            {
                "image": spaces.Box(0, 255, shape, np.uint8),
                "speed": spaces.Box(-np.inf, np.inf, (1,), np.float32),
            }
        )
        self.action_space = spaces.Box(
            np.array([-1.0, 0.0], np.float32), np.array([1.0, 1.0], np.float32), dtype=np.float32
        )
        self.world: SimWorld | None = None
        self.renderer: Renderer | None = None
        self._build()

    def _build(self) -> None:
        """(Re)build track, world and camera; the renderer's textures are per track."""
        self.world = SimWorld(layout=self.layout, seed=self.track_seed)
        self.track = self.world.track
        self.renderer = Renderer(self.track, self.camera)
        self._steps = 0

    @property
    def car(self):
        """The simulated car's state (pose, speed, ...) right now."""
        return _car(self.world)

    # -- gymnasium API --------------------------------------------------------------------

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start a new episode. options: "layout" and/or "track_seed" switch the track from
        this episode on (rebuilding it costs a texture); "s" starts at that arc position."""
        super().reset(seed=seed)
        options = options or {}
        layout = options.get("layout", self.layout)
        track_seed = int(options.get("track_seed", self.track_seed))
        if layout not in LAYOUTS:
            raise ValueError(f"unknown layout {layout!r}; valid layouts: {', '.join(LAYOUTS)}")
        if (layout, track_seed) != (self.layout, self.track_seed):
            self.layout, self.track_seed = layout, track_seed
            self._build()
        if "s" in options:
            start = float(options["s"])
        elif self.random_start:
            start = self._random_start()
        else:
            start = 0.0
        # a fresh world per episode: time, laps and progress restart, so a seed replays exactly
        self.world = SimWorld(layout=self.layout, seed=self.track_seed, track=self.track)
        if start:
            self.world.reset(start)
        self._steps = 0
        return self._observation(), self._info("")

    def step(self, action):
        a = np.asarray(action, dtype=np.float64).reshape(2)
        steering = float(np.clip(a[0], -1.0, 1.0))
        throttle = float(np.clip(a[1], 0.0, 1.0))
        world = self.world
        before = world.progress
        dt = 1.0 / self.physics_hz
        kind = ""
        for _ in range(self.substeps):
            info = world.step(dt, steering, throttle)
            if info.collision:
                kind = info.collided_with or "collision"
                break
        self._steps += 1
        collided = bool(kind)
        reward = (world.progress - before) - (self.collision_penalty if collided else 0.0)
        laps = world.laps
        truncated = not collided and (laps >= self.max_laps or self._steps >= self.max_steps)
        return self._observation(), float(reward), collided, truncated, self._info(kind)

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        car = _car(self.world)
        return top_down(self.world.track, poses=[(car.x, car.y, car.yaw)])

    # -- internals ------------------------------------------------------------------------

    def _observation(self) -> dict[str, np.ndarray]:
        car = _car(self.world)
        return {
            "image": self.renderer.render(car.x, car.y, car.yaw),
            "speed": np.array([car.v], dtype=np.float32),
        }

    def _info(self, collision: str) -> dict[str, Any]:
        world, car = self.world, _car(self.world)
        return {
            "speed": float(car.v),
            "s": float(world.s),
            "progress": float(world.distance),  # metres along the track since this start
            "laps": int(world.laps),
            "collision": collision,  # '' or what was hit: 'fence', 'obstacle'
            "off_track": bool(world.off_track),
            "time": float(world.time),
            "steps": self._steps,
        }

    def _random_start(self) -> float:
        """An arc position whose centerline point is clear of every obstacle."""
        track = self.track
        for _ in range(100):
            s = float(self.np_random.uniform(0.0, track.length))
            x, y, _ = pose_at(track, s)
            if all(
                math.hypot(x - o.x, y - o.y) >= o.radius + START_CLEARANCE for o in track.obstacles
            ):
                return s
        return 0.0


if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point="carrt.sim.env:CarrtSimEnv")
