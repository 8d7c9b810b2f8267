"""A scripted driver that stands in for the human with the joystick.

It plans once per track, the way a driver learns a circuit: the racing line, bent around each
obstacle on its roomier side (the same bounded minimum-curvature fit that makes the racing line,
with the obstacles as extra bounds, so the swerves are as gentle as the room allows), and a
speed profile from that path's curvature with braking zones before the tight parts. Driving is
then pure pursuit on the plan with a speed-dependent lookahead, from the pose the car will have
when the command takes effect (the servo lags, and at 10 Hz a command is held for 0.1 s).

Noise injection (the paper's recovery data) is not done here: carrt/noise.py perturbs what this
driver commands, and this driver recovers from wherever the car ends up.
"""

from __future__ import annotations

import math

import numpy as np

from carrt.sim.car import CarParams
from carrt.sim.track import geometry, project, smooth_offsets
from carrt.sim.types import CarState, Track
from carrt.sim.world import Locator

RACING_BOUND = 0.25  # how far off the centerline the plan may go away from obstacles
EDGE_ROOM = 0.03  # the body stays this far inside the markings when dodging
OBSTACLE_MARGIN = 0.15  # wanted clearance between body and obstacle (less if the gap is tight)
LONGITUDINAL_MARGIN = 0.12  # the path is held clear this far before/after the obstacle


class ScriptedExpert:
    """Pure pursuit on an obstacle-aware racing line; `act(state)` → (steering, throttle)."""

    def __init__(
        self,
        track: Track,
        params: CarParams | None = None,
        *,
        target_speed: float = 2.3,
        lateral_accel: float = 5.0,
        brake_decel: float = 3.0,
        lookahead_base: float = 0.12,
        lookahead_gain: float = 0.15,
        latency: float = 0.03,
    ) -> None:
        self.track = track
        self.params = params if params is not None else CarParams()
        self.target_speed = min(target_speed, self.params.top_speed)
        self.lateral_accel = lateral_accel
        self.brake_decel = brake_decel
        self.lookahead_base = lookahead_base
        self.lookahead_gain = lookahead_gain
        self.latency = latency
        self._locator = Locator(track)
        self.offsets = self._plan_offsets()
        geo = geometry(track.centerline)
        normals = np.stack([-np.sin(geo.vertex_heading), np.cos(geo.vertex_heading)], axis=1)
        self.path = track.centerline + self.offsets[:, None] * normals
        self.speed_profile = self._speed_profile()
        self._n = len(self.path)
        seg = np.roll(self.path, -1, axis=0) - self.path
        self._step = float(np.mean(np.hypot(seg[:, 0], seg[:, 1])))
        self._window = np.arange(math.ceil(3.0 / self._step))

    # -- planning ----------------------------------------------------------------------------

    def _plan_offsets(self) -> np.ndarray:
        """Lateral offset of the plan at each centerline vertex."""
        track, p = self.track, self.params
        geo = geometry(track.centerline)
        s_race, lat_race, _ = project(track, track.racing_line[:, 0], track.racing_line[:, 1])
        order = np.argsort(s_race)
        s_vertex = geo.cum[:-1]
        race = np.interp(s_vertex, s_race[order], lat_race[order], period=geo.length)
        if not track.obstacles:
            return race
        half_w = p.width / 2
        room = track.width / 2 - half_w - EDGE_ROOM  # the body's centre may go this far out
        lo = np.full(geo.n, -RACING_BOUND)
        hi = np.full(geo.n, RACING_BOUND)
        for ob in track.obstacles:
            s_o, lat_o = (float(v) for v in project(track, ob.x, ob.y)[:2])
            left_gap = track.width / 2 - (lat_o + ob.radius)
            right_gap = track.width / 2 + (lat_o - ob.radius)
            gap = max(left_gap, right_gap)
            margin = min(OBSTACLE_MARGIN, max(0.0, (gap - p.width - EDGE_ROOM) / 2))
            clear = ob.radius + half_w + margin
            # the body's points roughly follow the path, so only the stretch of path beside
            # the obstacle has to clear it; the body's chord off a curved path is in the margins
            reach = ob.radius + LONGITUDINAL_MARGIN
            ds = (s_vertex - s_o + geo.length / 2) % geo.length - geo.length / 2
            near = (ds > -reach) & (ds < reach)
            if left_gap >= right_gap:
                lo[near] = np.maximum(lo[near], lat_o + clear)
                hi[near] = np.maximum(hi[near], room)
            else:
                hi[near] = np.minimum(hi[near], lat_o - clear)
                lo[near] = np.minimum(lo[near], -room)
        lo = np.minimum(lo, hi)
        return smooth_offsets(track.centerline, race, lo, hi)

    def _speed_profile(self) -> np.ndarray:
        """Fastest speed at each plan vertex: grip-limited in bends, braking-limited before them."""
        path = self.path
        seg = np.roll(path, -1, axis=0) - path
        seg_len = np.hypot(seg[:, 0], seg[:, 1])
        # curvature over a ±10 cm baseline (the car's own length smooths anything shorter):
        # κ = 2·(ab × bc) / (|ab|·|bc|·|ca|), the circle through three points
        k = max(1, round(0.1 / float(np.mean(seg_len))))
        ab = path - np.roll(path, k, axis=0)
        bc = np.roll(path, -k, axis=0) - path
        cross = ab[:, 0] * bc[:, 1] - ab[:, 1] * bc[:, 0]
        sides = np.hypot(*ab.T) * np.hypot(*bc.T) * np.hypot(*(ab + bc).T)
        kappa = np.abs(2 * cross / np.maximum(sides, 1e-12))
        kappa = np.maximum.reduce([np.roll(kappa, j) for j in range(-k, k + 1)])
        v = np.minimum(self.target_speed, np.sqrt(self.lateral_accel / np.maximum(kappa, 1e-6)))
        for _ in range(2):  # braking zones: twice round, so the lap's end brakes for its start
            for i in range(len(v) - 1, -1, -1):
                j = (i + 1) % len(v)
                v[i] = min(v[i], math.sqrt(v[j] ** 2 + 2 * self.brake_decel * seg_len[i]))
        return v

    # -- driving -----------------------------------------------------------------------------

    def reset(self) -> None:
        """Forget where the car was (call after the car is moved, e.g. by a world reset)."""
        self._locator.reset()

    def act(self, state: CarState) -> tuple[float, float]:
        p = self.params
        v = state.v
        # where the car will be when this command has taken effect
        yaw = state.yaw + state.yaw_rate * self.latency
        x = state.x + v * self.latency * math.cos(state.yaw + 0.5 * state.yaw_rate * self.latency)
        y = state.y + v * self.latency * math.sin(state.yaw + 0.5 * state.yaw_rate * self.latency)
        s, _, _ = self._locator.locate(x, y)
        i = int(s / self.track.length * self._n) % self._n
        idx = (i + self._window) % self._n
        ahead = self.path[idx]
        dist = np.hypot(ahead[:, 0] - x, ahead[:, 1] - y)
        lookahead = self.lookahead_base + self.lookahead_gain * max(v, 0.0)
        beyond = np.nonzero(dist >= lookahead)[0]
        j = int(beyond[0]) if len(beyond) else len(idx) - 1
        tx, ty = ahead[j, 0] - x, ahead[j, 1] - y
        alpha = math.atan2(ty, tx) - yaw
        reach = max(float(dist[j]), 1e-3)
        steer = math.atan2(2 * p.wheelbase * math.sin(alpha), reach)  # wheel angle, + left
        steering = max(-1.0, min(1.0, -steer / p.max_steer))  # the protocol's −1 is left
        # the slowest speed needed over the distance the motor takes to respond
        preview = max(1, round((0.1 + max(v, 0.0) * (p.motor_tau + self.latency)) / self._step))
        v_ref = float(np.min(self.speed_profile[(i + np.arange(preview)) % self._n]))
        return steering, self._throttle(v, v_ref)

    def _throttle(self, v: float, v_ref: float) -> float:
        p = self.params
        if v > v_ref + 0.1:  # too fast: brake in proportion
            return max(-1.0, -1.5 * (v - v_ref))
        hold = (p.drag * v_ref + p.rolling_decel) / p.max_accel  # what holds v_ref on the flat
        return max(0.0, min(1.0, hold + 1.2 * (v_ref - v)))
