"""Issue 59, 3b: a world model whose motion is exact and whose hazard is a place on the ground.

    python -m research.ground_model train --episodes DEMOS DRIVES --out RUN [--seed S] [--steps N]
    python -m research.ground_model check --run RUN --data research/runs/.../counterfactual.npz

Why: the world-model check (research/world_model_check.py) measured the Reveries-net learning a
track-wide rule about steering ("+0.3 is the worse side") rather than what the frame shows: in
demonstrations and drives the action is a function of the image, so a recurrent model fitted to
them can ignore the action. Here the direction a steering change moves the car is not learnt at
all: it is geometry.

  motion   a kinematic bicycle with the car's constants (`CarGeometry`: wheelbase, steering
           range, servo lag, tyre grip; measured on the car, defaults the simulator's car),
           integrated in torch, so an imagined path is differentiable in the actions. The speed
           response is learnt from the wheel odometry alone (`SpeedResponse`: a first-order
           motor lag and a linear longitudinal law, fitted by least squares).
  hazard   a map on the ground in front of the car, predicted from the camera frame
           (`HazardNet`): the frame is projected onto the floor through the camera's mounting
           (height, pitch, field of view: inverse perspective, no learning) and a small
           convolutional net gives each floor cell a hazard logit. It is supervised by the
           episodes alone (`hazard_labels`): the frame's future path by dead reckoning (the
           recorded speed and steering through the same kinematic model) is free ground where the
           car drove on, and the front of the car where an episode ended in a collision is hazard.
  collision  the hazard under the car's front along the imagined path; per step the chance it
           hits there, given that it had not hit before (so Σ p over the horizon is the chance of
           a crash within it, as the check's truth counts one).

`GroundWorldModel.imagine` answers as `training.models.WorldModel.imagine` does (speed,
p_collision, uncertainties), so research/variants/counterfactual.score checks it unchanged. It
has no learnt uncertainty: the u terms are 0 (its -unc is itself).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

if __package__ in (None, ""):  # run as a file: the repository on the path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from carrt.errors import EXIT_USAGE, UserError


@dataclass(frozen=True)
class CarGeometry:
    """The car's measured constants (defaults: the simulator's 1/20-scale car and camera)."""

    wheelbase: float = 0.14  # m, axle to axle
    max_steer: float = 0.45  # front-wheel angle at full lock, rad
    steer_tau: float = 0.08  # servo: first-order time constant, s
    grip: float = 7.4  # lateral acceleration the tyres give before they slide, m/s²
    scrub: float = 0.35  # sliding: speed lost per m/s² of lateral demand past the grip, per s
    period_s: float = 0.1  # the control period: one action per step
    substeps: int = 5
    front: float = 0.17  # the body's front ahead of the rear axle, m
    half_width: float = 0.05
    cam_height: float = 0.12  # the camera above the floor, m
    cam_pitch_deg: float = 20.0  # downwards from horizontal
    cam_fov_deg: float = 100.0  # horizontal
    cam_forward: float = 0.05  # ahead of the rear axle, m
    image_size: int = 96  # the recorded frame (square)


@dataclass(frozen=True)
class MapGrid:
    """The floor the hazard map covers, in the car's frame at the frame (x ahead of the rear
    axle, y to the left), and its cell size."""

    x_min: float = -0.1
    x_max: float = 3.1
    y_half: float = 1.6
    cell: float = 0.08

    @property
    def shape(self) -> tuple[int, int]:
        return (round((self.x_max - self.x_min) / self.cell),
                round(2 * self.y_half / self.cell))  # fmt: skip

    def normalised(self, x: Tensor, y: Tensor) -> Tensor:
        """Floor points → grid_sample coordinates (…, 2): width axis = y (left is column 0),
        height axis = x (row 0 nearest)."""
        gx = -y / self.y_half  # column: +y (left) → −1
        gy = 2 * (x - self.x_min) / (self.x_max - self.x_min) - 1
        return torch.stack([gx, gy], dim=-1)


# The points of the car's body whose ground the hazard is read under: the front corners and
# centre (what meets an obstacle first) and the front wheels' sides.
def body_points(geo: CarGeometry) -> Tensor:
    f, w = geo.front, geo.half_width
    return torch.tensor([[f, 0.0], [f, w], [f, -w], [f - 0.06, w], [f - 0.06, -w]])


FRONT_POINTS = 3  # the first three of body_points: where a collision is labelled


def rollout(geo: CarGeometry, speeds: Tensor, steering: Tensor, steer0: Tensor) -> Tensor:
    """(N, H, 3) poses (x, y, yaw) after each step, from (0, 0, 0), of a car holding each step's
    steering command (protocol sign: −1 full left) while its speed goes from speeds[:, k] to
    speeds[:, k+1] (speeds: (N, H+1) m/s). steer0: (N,) front-wheel angle at the start (rad, +
    left). Differentiable in all three."""
    n, h = steering.shape
    dt = geo.period_s / geo.substeps
    k_servo = 1.0 - math.exp(-dt / geo.steer_tau)
    x = torch.zeros(n, dtype=speeds.dtype)
    y, yaw, delta = torch.zeros_like(x), torch.zeros_like(x), steer0.to(speeds.dtype)
    poses = []
    for k in range(h):
        target = -steering[:, k].clamp(-1, 1) * geo.max_steer
        for s in range(geo.substeps):
            frac = (s + 0.5) / geo.substeps
            v = speeds[:, k] * (1 - frac) + speeds[:, k + 1] * frac
            delta = delta + (target - delta) * k_servo
            rate = v * torch.tan(delta) / geo.wheelbase
            # the tyres' limit: past grip/|v| the car slides and the yaw rate saturates
            limit = geo.grip / v.abs().clamp(min=1e-3)
            rate = torch.maximum(torch.minimum(rate, limit), -limit)
            mid = yaw + 0.5 * rate * dt
            x = x + v * torch.cos(mid) * dt
            y = y + v * torch.sin(mid) * dt
            yaw = yaw + rate * dt
        poses.append(torch.stack([x, y, yaw], dim=-1))
    return torch.stack(poses, dim=1)


def drive(
    geo: CarGeometry, response: SpeedResponse, v0: Tensor, actions: Tensor, steer0: Tensor
) -> tuple[Tensor, Tensor]:
    """What the car does under (N, H, 2) actions from speed v0 (N,) and wheel angle steer0 (N,):
    (N, H) speeds and (N, H, 3) poses after each step. The speed response (learnt) and the
    kinematic bicycle (the car's constants) integrated together, so a slide past the tyres' grip
    costs speed as it does on the car. Differentiable in the actions."""
    n, h, _ = actions.shape
    dt = geo.period_s / geo.substeps
    k_servo = 1.0 - math.exp(-dt / geo.steer_tau)
    k_motor = 1.0 - math.exp(-dt / response.tau)
    a, b, c, d = response.coef
    x = torch.zeros(n, dtype=actions.dtype)
    y, yaw = torch.zeros_like(x), torch.zeros_like(x)
    v, delta = v0.to(actions.dtype), steer0.to(actions.dtype)
    m = response.steady_motor(v)
    speeds, poses = [], []
    for k in range(h):
        target = -actions[:, k, 0].clamp(-1, 1) * geo.max_steer
        throttle = actions[:, k, 1].clamp(-1, 1)
        for _ in range(geo.substeps):
            delta = delta + (target - delta) * k_servo
            m = m + (throttle - m) * k_motor
            v = (v + dt * (a * m.clamp(min=0) + b * m.clamp(max=0) - c * v - d)).clamp(min=0)
            rate = v * torch.tan(delta) / geo.wheelbase
            limit = geo.grip / v.clamp(min=1e-3)
            slide = (v * rate.abs() - geo.grip).clamp(min=0)
            rate = torch.maximum(torch.minimum(rate, limit), -limit)
            v = (v - geo.scrub * slide * dt).clamp(min=0)
            mid = yaw + 0.5 * rate * dt
            x = x + v * torch.cos(mid) * dt
            y = y + v * torch.sin(mid) * dt
            yaw = yaw + rate * dt
        speeds.append(v)
        poses.append(torch.stack([x, y, yaw], dim=-1))
    return torch.stack(speeds, dim=1), torch.stack(poses, dim=1)


def points_at(poses: Tensor, points: Tensor) -> Tensor:
    """(…, P, 2) body points placed at (…, 3) poses."""
    c, s = torch.cos(poses[..., 2:3]), torch.sin(poses[..., 2:3])
    px, py = points[:, 0], points[:, 1]
    x = poses[..., 0:1] + c * px - s * py
    y = poses[..., 1:2] + s * px + c * py
    return torch.stack([x, y], dim=-1)


@dataclass
class SpeedResponse:
    """v' = v + dt·(a·m⁺ + b·m⁻ − c·v − d), the motor state m following the throttle command with
    time constant tau; learnt from recorded (speed, throttle) pairs (`fit`)."""

    tau: float = 0.25
    coef: tuple[float, float, float, float] = (5.0, 7.0, 1.9, 0.3)
    period_s: float = 0.1

    def kappa(self) -> float:
        return 1.0 - math.exp(-self.period_s / self.tau)

    def steady_motor(self, v: Tensor) -> Tensor:
        """The motor state that holds speed v (the start's unknown state)."""
        a, _, c, d = self.coef
        return ((c * v + d) / a).clamp(0, 1)

    @classmethod
    def fit(cls, runs: list[tuple[np.ndarray, np.ndarray]], period_s: float) -> SpeedResponse:
        """Least squares per candidate tau; the tau with the smallest residual. runs: (speed (n,),
        throttle (n,)) per episode; pairs at standstill are left out (the law is for rolling)."""
        from scipy.optimize import nnls

        best = None
        for tau in (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5, 0.6, 0.8):
            kappa = 1.0 - math.exp(-period_s / tau)
            rows, target = [], []
            for v, u in runs:
                if len(v) < 3:
                    continue
                m = np.zeros(len(v))
                for t in range(1, len(v)):
                    m[t] = m[t - 1] + (np.clip(u[t - 1], -1, 1) - m[t - 1]) * kappa
                mn = m[1:]  # the motor state over step t → t+1 (updated first, as in imagine)
                keep = (v[:-1] > 0.05) & (v[1:] > 0.05)  # a stop clips the law at 0
                rows.append(np.stack([np.maximum(mn, 0), np.minimum(mn, 0), -v[:-1],
                                      -np.ones(len(mn))], axis=1)[keep])  # fmt: skip
                target.append(((v[1:] - v[:-1]) / period_s)[keep])
            if not rows:
                raise UserError("ground model: no rolling steps to learn the speed response from")
            a_mat, y = np.concatenate(rows), np.concatenate(target)
            coef, _ = nnls(a_mat, y)  # every coefficient is a physical magnitude ≥ 0
            residual = float(np.mean((a_mat @ coef - y) ** 2))
            if best is None or residual < best[0]:
                best = (residual, tau, coef)
        _, tau, coef = best
        return cls(tau=tau, coef=tuple(float(c) for c in coef), period_s=period_s)


def floor_to_pixel(geo: CarGeometry, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Where floor points (x ahead of the rear axle, y left; m) appear in the frame: (u, v)
    pixel coordinates (pixel centres at +0.5) and whether they lie in front of the camera. A
    pinhole pitched down by cam_pitch_deg at cam_height above the floor, as the camera is
    mounted (the simulator renders through the same model)."""
    p = math.radians(geo.cam_pitch_deg)
    dx, h = x - geo.cam_forward, geo.cam_height
    forward = dx * math.cos(p) + h * math.sin(p)
    up = dx * math.sin(p) - h * math.cos(p)
    size = geo.image_size
    f = (size / 2) / math.tan(math.radians(geo.cam_fov_deg) / 2)
    safe = forward.clamp(min=1e-3)
    return size / 2 - f * y / safe, size / 2 - f * up / safe, forward > 1e-3


def floor_sampling_grid(geo: CarGeometry, grid: MapGrid) -> tuple[Tensor, Tensor]:
    """Where each floor cell's centre appears in the frame: (1, X, Y, 2) grid_sample coordinates
    and (X, Y) visibility."""
    nx, ny = grid.shape
    xs = grid.x_min + (torch.arange(nx, dtype=torch.float64) + 0.5) * grid.cell
    ys = grid.y_half - (torch.arange(ny, dtype=torch.float64) + 0.5) * grid.cell  # col 0: left
    x, y = torch.meshgrid(xs, ys, indexing="ij")
    u, v, ahead = floor_to_pixel(geo, x, y)
    size = geo.image_size
    coords = torch.stack([2 * u / size - 1, 2 * v / size - 1], dim=-1).float()
    visible = ahead & (coords.abs() <= 1).all(dim=-1)
    return coords.unsqueeze(0), visible


class HazardNet(nn.Module):
    """Frame → hazard logits on the floor grid: inverse perspective (fixed), then convolutions
    whose receptive field spans about a metre of floor."""

    def __init__(self, geo: CarGeometry, grid: MapGrid, width: int = 24) -> None:
        super().__init__()
        self.geo, self.grid = geo, grid
        coords, visible = floor_sampling_grid(geo, grid)
        self.register_buffer("coords", coords)
        self.register_buffer("visible", visible.float()[None, None])
        layers, cin = [], 4
        for dilation in (1, 2, 4, 8, 1):
            layers += [nn.Conv2d(cin, width, 3, padding=dilation, dilation=dilation), nn.ReLU()]
            cin = width
        self.net = nn.Sequential(*layers, nn.Conv2d(width, 1, 1))

    def floor(self, image: Tensor) -> Tensor:
        """uint8 (N, S, S, 3) frames → (N, 4, X, Y): the floor's colour (−1..1) and visibility."""
        img = image.permute(0, 3, 1, 2).float() / 127.5 - 1.0
        top = F.grid_sample(img, self.coords.expand(len(img), -1, -1, -1), align_corners=False)
        vis = self.visible.expand(len(img), -1, -1, -1)
        return torch.cat([top * vis, vis], dim=1)

    def forward(self, image: Tensor) -> Tensor:
        return self.net(self.floor(image))[:, 0]  # (N, X, Y)

    def probability(self, image: Tensor, pose_sigma: float = 0.0) -> Tensor:
        """(N, X, Y) the chance that the car's body at each cell meets a hazard; with
        pose_sigma > 0 (m), averaged over a Gaussian error of the imagined pose: where the car
        will really be is uncertain, and the smoothed map also tells a path near a hazard from
        one far from it (a gradient that points away from the hazard, not only inside it)."""
        prob = torch.sigmoid(self(image))
        if pose_sigma <= 0:
            return prob
        sigma = pose_sigma / self.grid.cell
        half = max(1, math.ceil(3 * sigma))
        taps = torch.exp(-0.5 * (torch.arange(-half, half + 1, dtype=prob.dtype) / sigma) ** 2)
        taps = taps / taps.sum()
        x = prob.unsqueeze(1)
        x = F.conv2d(F.pad(x, (0, 0, half, half), mode="replicate"), taps.view(1, 1, -1, 1))
        x = F.conv2d(F.pad(x, (half, half, 0, 0), mode="replicate"), taps.view(1, 1, 1, -1))
        return x[:, 0]

    def at(self, logits: Tensor, points: Tensor) -> Tensor:
        """A map (logits or probabilities) at floor points (N, M, 2) in the frame's car frame →
        (N, M); off the map: the border's."""
        where = self.grid.normalised(points[..., 0], points[..., 1]).unsqueeze(1)  # (N,1,M,2)
        out = F.grid_sample(logits.unsqueeze(1), where, align_corners=False, padding_mode="border")
        return out[:, 0, 0]


def outcome(speeds: Tensor, poses: Tensor, p_here: Tensor) -> dict[str, Tensor]:
    """What imagine() answers, from the path and each step's chance of meeting a hazard there:
    p_collision per step given no hit before (so its sum is the chance of a crash within the
    horizon, as the check's truth counts one), survival after each step, P(crash), and no
    learnt uncertainty (the u terms 0)."""
    alive = torch.cumprod(1 - p_here, dim=1)
    before = torch.cat([torch.ones_like(alive[:, :1]), alive[:, :-1]], dim=1)
    zeros = torch.zeros_like(p_here)
    return {
        "speed": speeds,
        "p_collision": before * p_here,
        "survival": alive,
        "p_crash": 1 - alive[:, -1],
        "poses": poses,
        **{name: zeros for name in ("u_image", "u_speed", "u_collision")},
    }


class GroundWorldModel(nn.Module):
    """The world model of 3b: exact motion, learnt speed response, hazard on the floor."""

    def __init__(self, geo: CarGeometry, grid: MapGrid, speed: SpeedResponse, horizon: int = 10,
                 width: int = 24, pose_sigma: float = 0.0) -> None:  # fmt: skip
        super().__init__()
        self.geo, self.grid, self.speed_response, self.horizon = geo, grid, speed, horizon
        self.pose_sigma = pose_sigma
        self.hazard = HazardNet(geo, grid, width)
        self.register_buffer("points", body_points(geo))

    def imagine(self, image: Tensor, speed: Tensor, actions: Tensor, uncertainty_clip: float = 0.0,
                prior_correction: bool = True) -> dict[str, Tensor]:  # fmt: skip
        """As WorldModel.imagine: N frames, N·K sequences (start i's rows i·K…i·K+K−1)."""
        hazard = self.hazard.probability(image, self.pose_sigma)
        k = actions.shape[0] // hazard.shape[0]
        hazard = hazard.repeat_interleave(k, dim=0) if k > 1 else hazard
        v0 = speed.reshape(-1).to(torch.float32).repeat_interleave(k)
        actions = actions.to(torch.float32)
        steer0 = -actions[:, 0, 0].clamp(-1, 1) * self.geo.max_steer
        speeds, poses = drive(self.geo, self.speed_response, v0, actions, steer0)  # (M, H, ·)
        pts = points_at(poses, self.points)  # (M, H, P, 2)
        m, h, p, _ = pts.shape
        hit = self.hazard.at(hazard, pts.reshape(m, h * p, 2)).view(m, h, p)
        p_here = hit.max(dim=2).values  # the car at step k meets hazard anywhere on its body
        return outcome(speeds, poses, p_here)


class PerfectMapModel(GroundWorldModel):
    """The ground model's motion with a perfect hazard map: the placement's true obstacles and
    fence (the simulator's geometry) instead of the map learnt from the frame. Evaluation only
    (research): it says how much of the check the model's motion allows, so what a learnt map
    misses is told apart from what the motion misses. The hazard of a body point is
    sigmoid(−d / edge) with d its signed distance to the nearest obstacle or the fence (negative
    inside): smooth, so the objective has a gradient, and sharp (edge 2 cm).

    It knows each start by its frame: `starts` maps the frame's bytes to (layout, track seed,
    the start's x, y, yaw), from a counterfactual set with poses (carrt.sim.counterfactual)."""

    def __init__(self, speed: SpeedResponse, data: dict, edge: float = 0.02) -> None:
        super().__init__(CarGeometry(), MapGrid(), speed)
        from carrt.sim.track import build_track

        if "pose" not in data:
            raise UserError("the counterfactual set has no start poses: make it again")
        layout = data["meta"]["layout"]
        tracks = {}
        self.starts = {}
        for image, (seed, _), pose in zip(data["image"], data["where"], data["pose"], strict=True):
            seed = int(seed)
            tracks.setdefault(seed, build_track(layout, seed))
            self.starts[image.tobytes()] = (tracks[seed], pose)
        self.edge = edge

    def imagine(self, image, speed, actions, uncertainty_clip=0.0, prior_correction=True):
        track, pose = self.starts[image[0].numpy().tobytes()]
        v0 = speed.reshape(-1).to(torch.float32).expand(actions.shape[0])
        actions = actions.to(torch.float32)
        steer0 = torch.full((actions.shape[0],), float(pose[3]))
        speeds, poses = drive(self.geo, self.speed_response, v0, actions, steer0)
        pts = points_at(poses, self.points)  # (M, H, P, 2) in the start's car frame
        c, s = math.cos(pose[2]), math.sin(pose[2])
        wx = pose[0] + c * pts[..., 0] - s * pts[..., 1]
        wy = pose[1] + s * pts[..., 0] + c * pts[..., 1]
        width, height = track.arena
        d = torch.minimum(torch.minimum(wx, width - wx), torch.minimum(wy, height - wy))
        for o in track.obstacles:
            d = torch.minimum(d, torch.hypot(wx - o.x, wy - o.y) - o.radius)
        p_here = torch.sigmoid(-d / self.edge).max(dim=2).values
        return outcome(speeds, poses, p_here)


# ---------------------------------------------------------------------------------- labels


def dead_reckon(geo: CarGeometry, speed: np.ndarray, steering: np.ndarray) -> np.ndarray:
    """(n+1, 3) poses of an episode from its start, from what the car records: the wheel
    odometry's speed and the executed steering, through the same kinematic model. Pose t is where
    frame t was taken; pose n is one period after the last step."""
    v = torch.as_tensor(np.append(speed, speed[-1]), dtype=torch.float64)[None]
    s = torch.as_tensor(steering, dtype=torch.float64)[None]
    steer0 = -s[:, 0].clamp(-1, 1) * geo.max_steer
    poses = rollout(geo, v, s, steer0)[0].numpy()
    return np.concatenate([np.zeros((1, 3)), poses])


def relative(poses: np.ndarray, t: int) -> np.ndarray:
    """Poses in the car frame of pose t."""
    x0, y0, yaw0 = poses[t]
    c, s = math.cos(yaw0), math.sin(yaw0)
    dx, dy = poses[:, 0] - x0, poses[:, 1] - y0
    return np.stack([c * dx + s * dy, -s * dx + c * dy, poses[:, 2] - yaw0], axis=1)


def hazard_labels(geo: CarGeometry, speed: np.ndarray, steering: np.ndarray,
                  events: np.ndarray, lookahead: int) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Per frame t: floor points (lookahead·P, 2) in its car frame and labels (0 free, 1 hazard,
    −1 none). Free: the body at each later pose (the car was there and did not hit); hazard: the
    front of the body one period after a collision event's step (a collision, an e-stop while
    driving, or an episode ended by either: `carrt.episodes.reader.collision_events`). Nothing
    is labelled past an event or the episode's end."""
    n = len(speed)
    poses = dead_reckon(geo, speed, steering)
    pts_body = body_points(geo).numpy()
    n_pts = len(pts_body)
    points = np.zeros((n, lookahead * n_pts, 2), dtype=np.float32)
    labels = -np.ones((n, lookahead * n_pts), dtype=np.float32)
    contact = set(int(e) + 1 for e in events)
    for t in range(n):
        rel = relative(poses, t)
        for j in range(lookahead):
            k = t + 1 + j
            if k > n:
                break
            c, s = math.cos(rel[k, 2]), math.sin(rel[k, 2])
            bx, by = pts_body[:, 0], pts_body[:, 1]
            xy = np.stack([rel[k, 0] + c * bx - s * by, rel[k, 1] + s * bx + c * by], axis=1)
            points[t, j * n_pts : (j + 1) * n_pts] = xy
            if k in contact:
                labels[t, j * n_pts : j * n_pts + FRONT_POINTS] = 1.0
                break
            labels[t, j * n_pts : (j + 1) * n_pts] = 0.0
    return points, labels


@dataclass
class TrainConfig:
    """One ground world model's training (`--set`-free: the flags are the config)."""

    steps: int = 3000
    batch: int = 64
    lr: float = 2e-3
    lookahead: int = 15  # label the path this many steps ahead of each frame
    width: int = 24
    seed: int = 0
    threads: int = 1
    flip: bool = True  # mirror frames and labels left-right (the geometry is symmetric)
    geometry: CarGeometry = field(default_factory=CarGeometry)
    grid: MapGrid = field(default_factory=MapGrid)


def load_data(paths: list[str], cfg: TrainConfig) -> dict:
    """Frames, speeds and labels of every episode under `paths` (training placements only)."""
    from carrt.episodes.reader import collision_events
    from training.episodes import load_episodes

    episodes = load_episodes(paths)
    if not episodes:
        raise UserError(f"ground model: no episodes under {', '.join(paths)}")
    images, pts, labs, runs = [], [], [], []
    for ep in episodes:
        speed = np.nan_to_num(np.asarray(ep.steps["speed_mps"], dtype=np.float64))
        executed = np.nan_to_num(np.asarray(ep.steps["executed_action"], dtype=np.float64))
        events = collision_events(ep.steps, ep.end_reason)
        p, lab = hazard_labels(cfg.geometry, speed, executed[:, 0], events, cfg.lookahead)
        images.append(np.asarray(ep.frames))
        pts.append(p)
        labs.append(lab)
        runs.append((speed, executed[:, 1]))
    return {"images": np.concatenate(images), "points": np.concatenate(pts),
            "labels": np.concatenate(labs), "runs": runs, "episodes": len(episodes)}  # fmt: skip


def train(paths: list[str], out: Path, cfg: TrainConfig, log=None) -> GroundWorldModel:
    log = log or (lambda line: print(line, flush=True))
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    data = load_data(paths, cfg)
    speed = SpeedResponse.fit(data["runs"], cfg.geometry.period_s)
    model = GroundWorldModel(cfg.geometry, cfg.grid, speed, width=cfg.width)
    labels = torch.from_numpy(data["labels"])
    has = (labels >= 0).any(dim=1)
    frames = torch.nonzero(has)[:, 0]
    n_hazard = int((labels == 1).sum())
    log(f"ground model: {data['episodes']} episodes, {len(frames)} labelled frames, "
        f"{int((labels == 0).sum())} free and {n_hazard} hazard points; speed response tau "
        f"{speed.tau:.2f} s, coef {tuple(round(c, 3) for c in speed.coef)}")  # fmt: skip
    images, points = torch.from_numpy(data["images"]), torch.from_numpy(data["points"])
    opt = torch.optim.AdamW(model.hazard.parameters(), lr=cfg.lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, cfg.steps)
    gen = torch.Generator().manual_seed(cfg.seed)
    started, seen = time.monotonic(), 0.0
    for step in range(cfg.steps):
        pick = frames[torch.randint(len(frames), (cfg.batch,), generator=gen)]
        img, pt, lab = images[pick], points[pick].clone(), labels[pick]
        if cfg.flip:
            flip = torch.rand(cfg.batch, generator=gen) < 0.5
            img = torch.where(flip[:, None, None, None], img.flip(2), img)
            pt[..., 1] = torch.where(flip[:, None], -pt[..., 1], pt[..., 1])
        logit = model.hazard.at(model.hazard(img), pt)
        keep = lab >= 0
        loss = F.binary_cross_entropy_with_logits(logit[keep], lab[keep])
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        seen = 0.98 * seen + 0.02 * loss.item() if step else loss.item()
        if (step + 1) % 250 == 0 or step + 1 == cfg.steps:
            rate = (step + 1) / (time.monotonic() - started)
            log(f"ground model: step {step + 1}/{cfg.steps} loss {seen:.4f} "
                f"({rate:.1f} steps/s, ETA {(cfg.steps - step - 1) / rate:.0f} s)")  # fmt: skip
    save(model, out, cfg)
    return model


def save(model: GroundWorldModel, out: Path, cfg: TrainConfig) -> None:
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / "ground_model.pt.tmp"
    torch.save({"state_dict": model.hazard.state_dict(), "config": asdict(cfg),
                "speed_response": asdict(model.speed_response)}, tmp)  # fmt: skip
    tmp.replace(out / "ground_model.pt")


def load(path: Path) -> GroundWorldModel:
    if not path.is_file():
        raise UserError(f"{path}: no such ground model file")
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    cfg = ckpt["config"]
    geo, grid = CarGeometry(**cfg["geometry"]), MapGrid(**cfg["grid"])
    speed = ckpt["speed_response"]
    speed = SpeedResponse(speed["tau"], tuple(speed["coef"]), speed["period_s"])
    model = GroundWorldModel(geo, grid, speed, width=cfg["width"])
    model.hazard.load_state_dict(ckpt["state_dict"])
    model.eval()
    return model


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m research.ground_model",
                                description=__doc__.split("\n")[0])  # fmt: skip
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="learn the speed response and the hazard map from episodes")
    t.add_argument("--episodes", nargs="+", required=True)
    t.add_argument("--out", required=True)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--steps", type=int, default=TrainConfig.steps)
    t.add_argument("--threads", type=int, default=1)
    c = sub.add_parser("check", help="score a trained ground model on a counterfactual set")
    c.add_argument("--run", required=True)
    c.add_argument("--data", required=True)
    c.add_argument(
        "--perfect-map",
        action="store_true",
        help="the run's motion with the placement's true hazard map (a ceiling)",
    )
    a = p.parse_args(argv)
    try:
        if a.cmd == "train":
            if a.steps < 1:
                raise UserError(f"--steps {a.steps}: 1 or more")
            train(a.episodes, Path(a.out), TrainConfig(steps=a.steps, seed=a.seed,
                                                       threads=a.threads))  # fmt: skip
            Path(a.out, ".done").touch()
            return 0
        from research.check_summary import summary
        from research.variants.counterfactual import load as load_set
        from research.variants.counterfactual import score
        from training.config import TrainingConfig

        model, data = load(Path(a.run) / "ground_model.pt"), load_set(a.data)
        if a.perfect_map:
            model = PerfectMapModel(model.speed_response, data)
        result = summary(score(model, data, TrainingConfig()))
        print(json.dumps({k: v for k, v in result.items()}, indent=1))
        return 0
    except UserError as exc:
        print(f"ground_model: error: {exc}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    raise SystemExit(main())
