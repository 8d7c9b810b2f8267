"""Issue 67, item 2: the ground model v2 — the car's own start state, the board's rise limit,
a speed law fitted on clean steps, fused hazard maps and a per-step uncertainty.

    python -m research.ground_v2 train --episodes DEMOS… --recorded REC_DIR --out RUN \
        [--members 3] [--steps 1200]

What changed from research/ground_model.py (v1), each from issue 59's code review:
  start state  v1 let the servo jump to each plan's first command and started the motor at
           the speed's steady state. A car knows its last executed commands: `start_state`
           runs them through the servo lag, the board's throttle rise limit and the learnt
           motor lag from the last reset (or the episode's start, at rest).
  rise limit   `drive` holds each command as the board does: the throttle rises at most
           RISE_PER_S (the firmware's pwm.slew_per_s default, 2 /s), falls at once.
  speed law    fitted (`SpeedLaw.fit`) over the 10 ms chunks of each 100 ms step, with the
           rise limit, leaving out the steps near a collision (impact), the sliding ones
           (lateral demand past 0.8 × grip) and standstill: v1's fit included them and
           under-predicted steady speed by ~0.2 m/s (τ 0.50 s).
  fused map    the hazard maps of the last FUSE frames are carried into the current frame
           by dead reckoning (recorded speed and steering), so floor that has left the view
           keeps what an earlier frame saw; floor no frame saw gets the base hazard rate (the
           share of hazard among the labels there), never "free".
  uncertainty  an ensemble of hazard nets (bootstrapped frames, own seeds): the members'
           disagreement on each step's chance of a hit; and an evidential head per cell
           (Beta evidence, the paper's kind of uncertainty): u = 2 / (α + β).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from carrt.errors import EXIT_USAGE, UserError
from research.ground_model import (
    CarGeometry,
    HazardNet,
    MapGrid,
    body_points,
    dead_reckon,
    hazard_labels,
    points_at,
    relative,
)

RISE_PER_S = 2.0  # the board's throttle rise limit (firmware pwm.slew_per_s default)
CHUNK_S = 0.01  # the board applies a command in 10 ms chunks
FUSE = 3  # frames fused: this one and the two before


@dataclass
class SpeedLaw:
    """v' = a·m⁺ + b·m⁻ − c·v − d, the motor state m following the board's (rise-limited)
    throttle with time constant tau."""

    tau: float = 0.25
    coef: tuple[float, float, float, float] = (5.0, 7.0, 1.9, 0.3)
    period_s: float = 0.1
    rise_per_s: float = RISE_PER_S

    @classmethod
    def fit(cls, segments: list[dict], period_s: float = 0.1, geo: CarGeometry | None = None):
        """Non-negative least squares per candidate tau over the chunks of each clean step
        (`clean_steps`); the tau with the smallest residual. Returns (law, info)."""
        from scipy.optimize import nnls

        geo = geo or CarGeometry()
        n_chunk = round(period_s / CHUNK_S)
        best = None
        for tau in (0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.5):
            rows, target = [], []
            for seg in segments:
                v, u = seg["speed"], seg["executed"][:, 1]
                if len(v) < 3:
                    continue
                _, motor = board_motor(u, tau, n_chunk)  # (n, n_chunk) during each step
                keep = clean_steps(seg, geo)
                frac = (np.arange(n_chunk) + 1.0) / n_chunk
                vc = v[:-1, None] + frac[None] * (v[1:] - v[:-1])[:, None]
                m = motor[: len(v) - 1]
                x = (
                    np.stack(
                        [
                            np.maximum(m, 0).sum(1),
                            np.minimum(m, 0).sum(1),
                            -vc.sum(1),
                            -np.full(len(m), float(n_chunk)),
                        ],
                        axis=1,
                    )
                    * CHUNK_S
                )
                rows.append(x[keep])
                target.append((v[1:] - v[:-1])[keep])
            a_mat, y = np.concatenate(rows), np.concatenate(target)
            if len(y) < 10:
                raise UserError("ground model v2: too few clean steps to fit the speed law")
            coef, _ = nnls(a_mat, y)
            residual = float(np.mean((a_mat @ coef - y) ** 2))
            if best is None or residual < best[0]:
                best = (residual, tau, coef, len(y))
        residual, tau, coef, n = best
        law = cls(tau=tau, coef=tuple(float(c) for c in coef), period_s=period_s)
        return law, {"residual": residual, "steps": n}


def board_motor(throttle: np.ndarray, tau: float, n_chunk: int = 10):
    """From rest, each step's commands through the board's rise limit and the motor lag:
    (board throttle after each step (n+1,), motor state after each chunk (n+1, n_chunk); row t
    is step t's chunks, the last row the state held after the last step)."""
    k = 1.0 - math.exp(-CHUNK_S / tau)
    n = len(throttle)
    thr, m = 0.0, 0.0
    board = np.zeros(n + 1)
    motor = np.zeros((n + 1, n_chunk))
    for t in range(n):
        cmd = float(np.clip(throttle[t], -1, 1))
        for c in range(n_chunk):
            thr = min(cmd, thr + RISE_PER_S * CHUNK_S)
            m += (thr - m) * k
            motor[t, c] = m
        board[t + 1] = thr
    motor[n] = m
    return board, motor


def clean_steps(seg: dict, geo: CarGeometry) -> np.ndarray:
    """(n−1,) steps t → t+1 the speed law is fitted on: rolling at both ends, not within a
    step before or three after a collision (impact, the reset), not sliding (the lateral
    demand v²·tan δ / L past 0.8 × grip, δ the servo-lagged recorded steering)."""
    v, steer = seg["speed"], seg["executed"][:, 0]
    n = len(v)
    keep = (v[:-1] > 0.05) & (v[1:] > 0.05)
    for e in seg.get("events", ()):
        keep[max(0, e - 1) : min(n - 1, e + 4)] = False
    delta = servo_angles(steer, geo)[: n - 1]
    lateral = v[:-1] ** 2 * np.abs(np.tan(delta)) / geo.wheelbase
    return keep & (lateral < 0.8 * geo.grip)


def servo_angles(steering: np.ndarray, geo: CarGeometry) -> np.ndarray:
    """(n+1,) front-wheel angle (rad, + left) before each step, from rest (0)."""
    k = 1.0 - math.exp(-CHUNK_S / geo.steer_tau)
    d, out = 0.0, [0.0]
    for s in steering:
        target = -float(np.clip(s, -1, 1)) * geo.max_steer
        for _ in range(round(geo.period_s / CHUNK_S)):
            d += (target - d) * k
        out.append(d)
    return np.asarray(out)


def start_states(executed: np.ndarray, law: SpeedLaw, geo: CarGeometry) -> np.ndarray:
    """(n, 3) the state before each step t of a segment (from rest): servo angle, the board's
    throttle, the motor state — what the car's recorded commands say, no simulator state."""
    board, motor = board_motor(executed[:, 1], law.tau, round(geo.period_s / CHUNK_S))
    steer = servo_angles(executed[:, 0], geo)
    m_before = np.concatenate([[0.0], motor[:-1, -1]])[: len(executed)]
    return np.stack([steer[: len(executed)], board[: len(executed)], m_before], axis=1)


def drive(geo: CarGeometry, law: SpeedLaw, v0: Tensor, actions: Tensor, state0: Tensor):
    """(N, H) speeds and (N, H, 3) poses after each step of (N, H, 2) actions from speed v0
    (N,) and the start state (N, 3: servo angle, board throttle, motor): 10 ms chunks, the
    board's rise limit, the motor lag, the speed law, the kinematic bicycle with the tyres'
    limit and the slide's speed loss (as ground_model.drive)."""
    n, h, _ = actions.shape
    n_chunk = round(geo.period_s / CHUNK_S)
    dt = CHUNK_S
    k_servo = 1.0 - math.exp(-dt / geo.steer_tau)
    k_motor = 1.0 - math.exp(-dt / law.tau)
    a, b, c, d = law.coef
    x = torch.zeros(n, dtype=actions.dtype)
    y, yaw = torch.zeros_like(x), torch.zeros_like(x)
    v = v0.to(actions.dtype)
    delta, thr, m = (state0[:, i].to(actions.dtype) for i in range(3))
    speeds, poses = [], []
    for k in range(h):
        target = -actions[:, k, 0].clamp(-1, 1) * geo.max_steer
        cmd = actions[:, k, 1].clamp(-1, 1)
        for _ in range(n_chunk):
            delta = delta + (target - delta) * k_servo
            thr = torch.minimum(cmd, thr + law.rise_per_s * dt)
            m = m + (thr - m) * k_motor
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


# -- hazard: evidential head, fusion ------------------------------------------------------------


class EvidentialHazardNet(HazardNet):
    """HazardNet with two more output channels: Beta evidence for hazard and for free floor."""

    def __init__(self, geo: CarGeometry, grid: MapGrid, width: int = 24) -> None:
        super().__init__(geo, grid, width)
        self.net[-1] = nn.Conv2d(width, 3, 1)

    def forward(self, image: Tensor) -> Tensor:
        return self.net(self.floor(image))[:, 0]

    def maps(self, image: Tensor) -> tuple[Tensor, Tensor]:
        """(N, X, Y) hazard probability and evidential uncertainty 2 / (α + β)."""
        out = self.net(self.floor(image))
        alpha, beta = 1 + F.softplus(out[:, 1]), 1 + F.softplus(out[:, 2])
        return torch.sigmoid(out[:, 0]), 2.0 / (alpha + beta)

    def at_all(self, image: Tensor, points: Tensor) -> Tensor:
        """(N, 3, M): the three output channels at floor points."""
        out = self.net(self.floor(image))
        where = self.grid.normalised(points[..., 0], points[..., 1]).unsqueeze(1)
        return F.grid_sample(out, where, align_corners=False, padding_mode="border")[:, :, 0]


def evidential_loss(e_hazard: Tensor, e_free: Tensor, y: Tensor, anneal: float) -> Tensor:
    """Sensoy et al.'s expected squared error under Beta(α, β) plus the annealed KL of the
    misleading evidence to the uniform Beta(1, 1)."""
    alpha, beta = 1 + F.softplus(e_hazard), 1 + F.softplus(e_free)
    s = alpha + beta
    p = alpha / s
    mse = (y - p) ** 2 + p * (1 - p) / (s + 1)
    a2, b2 = 1 + (1 - y) * (alpha - 1), 1 + y * (beta - 1)
    s2 = a2 + b2
    kl = (
        torch.lgamma(s2)
        - torch.lgamma(a2)
        - torch.lgamma(b2)
        + (a2 - 1) * (torch.digamma(a2) - torch.digamma(s2))
        + (b2 - 1) * (torch.digamma(b2) - torch.digamma(s2))
    )
    return (mse + anneal * kl).mean()


def cell_centres(grid: MapGrid) -> Tensor:
    """(X, Y, 2) floor points of the grid's cells (x ahead, y left), as grid_sample reads."""
    nx, ny = grid.shape
    gy = (2 * torch.arange(nx) + 1) / nx - 1
    gx = (2 * torch.arange(ny) + 1) / ny - 1
    xs = grid.x_min + (gy + 1) / 2 * (grid.x_max - grid.x_min)
    ys = -gx * grid.y_half
    return torch.stack(torch.meshgrid(xs, ys, indexing="ij"), dim=-1)


def fuse(grid: MapGrid, maps: list[Tensor], visible: Tensor, past: list[np.ndarray], base: float):
    """One frame's fused map. maps: [(C, X, Y) this frame's, then earlier frames'] (channels:
    hazard probability, evidential u, …); past: for each earlier frame, this frame's pose in its
    car frame (x, y, yaw). Each cell takes the newest frame that saw it; a cell no frame saw
    gets `base` hazard and u 1. Returns ((C, X, Y), seen (X, Y))."""
    out = maps[0].clone()
    seen = visible > 0.5
    centres = cell_centres(grid)
    for m, pose in zip(maps[1:], past, strict=True):
        if seen.all():
            break
        c, s = math.cos(pose[2]), math.sin(pose[2])
        qx = pose[0] + c * centres[..., 0] - s * centres[..., 1]
        qy = pose[1] + s * centres[..., 0] + c * centres[..., 1]
        where = grid.normalised(qx, qy)[None]  # (1, X, Y, 2)
        vals = F.grid_sample(m[None], where, align_corners=False, padding_mode="zeros")[0]
        vis = (
            F.grid_sample(visible[None, None], where, align_corners=False, padding_mode="zeros")[
                0, 0
            ]
            > 0.5
        )
        new = vis & ~seen
        out[:, new] = vals[:, new]
        seen = seen | vis
    out[0][~seen] = base
    if out.shape[0] > 1:
        out[1][~seen] = 1.0
    return out, seen


class Ensemble:
    """The v2 ground model: one motion (the speed law, the car's geometry), K hazard nets."""

    def __init__(
        self,
        law: SpeedLaw,
        members: list[EvidentialHazardNet],
        base: float,
        geo: CarGeometry | None = None,
        grid: MapGrid | None = None,
    ) -> None:
        self.law, self.members, self.base = law, members, base
        self.geo, self.grid = geo or CarGeometry(), grid or MapGrid()
        self.points = body_points(self.geo)

    @torch.no_grad()
    def frame_maps(self, images: np.ndarray) -> Tensor:
        """(K, N, 2, X, Y) each member's hazard probability and evidential u for N frames."""
        img = torch.from_numpy(np.ascontiguousarray(images))
        return torch.stack([torch.stack(m.maps(img), dim=1) for m in self.members])

    @torch.no_grad()
    def imagine(self, maps: Tensor, seen: Tensor, v0: Tensor, state0: Tensor, plans: Tensor):
        """maps (K, N, 2, X, Y) fused; seen (N, X, Y); v0 (N,), state0 (N, 3); plans
        (N, P, H, 2). Returns per member (K, N, P, H) p_collision and survival, and (N, P, H)
        speeds, poses (N, P, H, 3), evidential u and the unseen share per step."""
        k, n = maps.shape[:2]
        p_plans, h = plans.shape[1], plans.shape[2]
        flat = plans.reshape(n * p_plans, h, 2).float()
        speeds, poses = drive(
            self.geo,
            self.law,
            v0.repeat_interleave(p_plans),
            flat,
            state0.repeat_interleave(p_plans, dim=0),
        )
        pts = points_at(poses, self.points).reshape(n, p_plans * h * len(self.points), 2)
        where = self.grid.normalised(pts[..., 0], pts[..., 1]).unsqueeze(1)  # (N, 1, M, 2)
        shape = (n, p_plans, h, len(self.points))
        unseen = 1 - F.grid_sample(
            seen[:, None].float(), where, align_corners=False, padding_mode="zeros"
        )[:, 0, 0].view(shape)
        out = {
            "speed": speeds.view(n, p_plans, h),
            "poses": poses.view(n, p_plans, h, 3),
            "unseen": unseen.mean(-1),
        }
        hits, evid = [], []
        for j in range(k):
            at = F.grid_sample(maps[j], where, align_corners=False, padding_mode="border")
            at = at[:, :, 0].view(n, 2, *shape[1:])
            hits.append(at[:, 0].max(dim=-1).values)
            evid.append(at[:, 1].mean(dim=-1))
        p_here = torch.stack(hits)  # (K, N, P, H)
        alive = torch.cumprod(1 - p_here, dim=-1)
        before = torch.cat([torch.ones_like(alive[..., :1]), alive[..., :-1]], dim=-1)
        out["p_collision"] = before * p_here
        out["survival"] = alive
        out["u_evidential"] = torch.stack(evid).mean(0)
        return out


# -- data and training -------------------------------------------------------------------------


def segments_from_episodes(paths: list[str]) -> list[dict]:
    from carrt.episodes.reader import collision_events
    from training.episodes import load_episodes

    out = []
    for ep in load_episodes(paths):
        speed = np.nan_to_num(np.asarray(ep.steps["speed_mps"], dtype=np.float64))
        executed = np.nan_to_num(np.asarray(ep.steps["executed_action"], dtype=np.float64))
        out.append(
            {
                "images": np.asarray(ep.frames),
                "speed": speed,
                "executed": executed,
                "events": [int(e) for e in collision_events(ep.steps, ep.end_reason)],
            }
        )
    return out


def segments_from_recorded(rec: dict[str, np.ndarray]) -> list[dict]:
    """research.plan_distil's recorded drives, one segment per stretch between resets."""
    out = []
    for s in np.unique(rec["segment"]):
        idx = np.nonzero(rec["segment"] == s)[0]
        col = rec["collision"][idx]
        out.append(
            {
                "images": rec["image"][idx],
                "speed": rec["speed"][idx].astype(np.float64),
                "executed": rec["executed"][idx].astype(np.float64),
                "events": [int(i) for i in np.nonzero(col)[0]],
                "index": idx,
            }
        )
    return out


def train(
    segments: list[dict],
    out: Path,
    members: int,
    steps: int,
    seed: int = 0,
    lookahead: int = 15,
    log=print,
) -> Ensemble:
    geo, grid = CarGeometry(), MapGrid()
    # the law from the policy's recorded drives when there are any: the same loop records the
    # speed and the command it then executes (the demonstrations' episodes come through
    # carrt's loop, whose recorded speed and executed command sit at other instants)
    own = [s for s in segments if "index" in s] or segments
    law, info = SpeedLaw.fit(own, geo.period_s, geo)
    log(
        f"v2 speed law: tau {law.tau:.2f} s, coef {tuple(round(c, 3) for c in law.coef)}, "
        f"{info['steps']} clean steps, residual {info['residual']:.4f}"
    )
    images, pts, labs = [], [], []
    for seg in segments:
        p, lab = hazard_labels(
            geo, seg["speed"], seg["executed"][:, 0], np.asarray(seg["events"]), lookahead
        )
        images.append(seg["images"])
        pts.append(p)
        labs.append(lab)
    images = torch.from_numpy(np.concatenate(images))
    points = torch.from_numpy(np.concatenate(pts))
    labels = torch.from_numpy(np.concatenate(labs))
    frames = torch.nonzero((labels >= 0).any(dim=1))[:, 0]
    visible = HazardNet(geo, grid).visible[0, 0]
    seen = (
        F.grid_sample(
            visible[None, None],
            grid.normalised(points[..., 0], points[..., 1])[:, None].view(1, 1, -1, 2),
            align_corners=False,
        )[0, 0, 0].view(points.shape[:2])
        > 0.5
    )
    lab_unseen = labels[(labels >= 0) & ~seen]
    base = float((lab_unseen == 1).float().mean()) if len(lab_unseen) else 0.0
    log(
        f"v2 hazard: {len(frames)} labelled frames, {int((labels == 0).sum())} free and "
        f"{int((labels == 1).sum())} hazard points; base rate on unseen floor {base:.4f}"
    )
    nets = []
    out.mkdir(parents=True, exist_ok=True)
    for j in range(members):
        f = out / f"member{j}.pt"
        net = EvidentialHazardNet(geo, grid)
        if f.is_file():
            net.load_state_dict(torch.load(f, map_location="cpu"))
            nets.append(net.eval())
            continue
        torch.manual_seed(seed * 100 + j)
        gen = torch.Generator().manual_seed(seed * 100 + j)
        boot = frames[torch.randint(len(frames), (len(frames),), generator=gen)]
        opt = torch.optim.AdamW(net.parameters(), lr=2e-3, weight_decay=1e-4)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
        started, seen_loss = time.monotonic(), 0.0
        for step in range(steps):
            pick = boot[torch.randint(len(boot), (64,), generator=gen)]
            img, pt, lab = images[pick], points[pick].clone(), labels[pick]
            flip = torch.rand(64, generator=gen) < 0.5
            img = torch.where(flip[:, None, None, None], img.flip(2), img)
            pt[..., 1] = torch.where(flip[:, None], -pt[..., 1], pt[..., 1])
            outs = net.at_all(img, pt)
            keep = lab >= 0
            bce = F.binary_cross_entropy_with_logits(outs[:, 0][keep], lab[keep])
            evid = evidential_loss(
                outs[:, 1][keep],
                outs[:, 2][keep],
                lab[keep],
                min(1.0, step / max(1, steps // 2)) * 0.1,
            )
            loss = bce + evid
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            seen_loss = 0.98 * seen_loss + 0.02 * loss.item() if step else loss.item()
            if (step + 1) % 200 == 0:
                rate = (step + 1) / (time.monotonic() - started)
                log(f"member {j}: step {step + 1}/{steps} loss {seen_loss:.4f} ({rate:.1f}/s)")
        torch.save(net.state_dict(), f)
        nets.append(net.eval())
    meta = {"law": asdict(law), "base": base, "members": members, "law_fit": info}
    (out / "ensemble.json").write_text(__import__("json").dumps(meta, indent=1) + "\n")
    return Ensemble(law, nets, base, geo, grid)


def load(run: Path) -> Ensemble:
    import json

    meta = json.loads((run / "ensemble.json").read_text())
    law = SpeedLaw(**{k: (tuple(v) if k == "coef" else v) for k, v in meta["law"].items()})
    geo, grid = CarGeometry(), MapGrid()
    nets = []
    for j in range(meta["members"]):
        net = EvidentialHazardNet(geo, grid)
        net.load_state_dict(torch.load(run / f"member{j}.pt", map_location="cpu"))
        nets.append(net.eval())
    return Ensemble(law, nets, meta["base"], geo, grid)


def past_poses(speed: np.ndarray, steering: np.ndarray, geo: CarGeometry) -> np.ndarray:
    """(n, FUSE−1, 3): for each step t of a segment, its pose in the car frame of t−1, t−2…
    (dead reckoning on the recorded speed and steering; NaN where before the segment)."""
    poses = dead_reckon(geo, speed, steering)
    n = len(speed)
    out = np.full((n, FUSE - 1, 3), np.nan)
    for t in range(n):
        for j in range(1, FUSE):
            if t - j >= 0:
                out[t, j - 1] = relative(poses, t - j)[t]
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m research.ground_v2", description=__doc__.split("\n")[0]
    )
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train")
    t.add_argument("--episodes", nargs="*", default=[])
    t.add_argument("--recorded", nargs="*", default=[])
    t.add_argument("--out", required=True)
    t.add_argument("--members", type=int, default=3)
    t.add_argument("--steps", type=int, default=1200)
    t.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    try:
        from research.recorded_runs import load_recorded

        segs = segments_from_episodes(a.episodes) if a.episodes else []
        for r in a.recorded:
            segs += segments_from_recorded(load_recorded(Path(r)))
        if not segs:
            raise UserError("no data")
        train(segs, Path(a.out), a.members, a.steps, a.seed, log=lambda s: print(s, flush=True))
        return 0
    except UserError as exc:
        print(f"ground_v2: error: {exc}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    raise SystemExit(main())
