"""Issue 59, item 2: progress as the person drives it, learnt from the frame.

    python -m research.person_line train --episodes DEMOS --out RUN [--seed S] [--steps N]

Why: the ceiling showed that the paper's objective pays for speed anywhere (the car loops
across the infield at full speed) and that racing needs progress along the track. A real car
has no map of the track, but it has the person's laps: from every frame the person drove, the
path they then took (dead reckoning: the wheel odometry's speed and the executed steering
through the car's kinematic model, research/ground_model.py) is the line a racer takes from
here. `LineNet` predicts that line from the frame, as POINTS points at fixed distances along it
in the car's frame on the floor; an imagined path's progress is how far along the predicted line
it gets (`progress_along`), counted only while it stays within `reach` of the line (as the ceiling
counts progress only inside the track's markings). The person's frames only (mode MANUAL): a
policy's drives say where the policy went, not where the track goes.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from carrt.errors import EXIT_USAGE, UserError
from research.ground_model import CarGeometry, MapGrid, dead_reckon, floor_sampling_grid, relative

SPACING_M = 0.25  # the line's points, this far apart along it
POINTS = 10  # … up to 2.5 m: a second at top speed and more


class LineNet(nn.Module):
    """Frame → the person's line from here: (N, POINTS, 2) floor points (x ahead, y left; m)."""

    def __init__(self, geo: CarGeometry, grid: MapGrid, width: int = 16) -> None:
        super().__init__()
        coords, visible = floor_sampling_grid(geo, grid)
        self.register_buffer("coords", coords)
        self.register_buffer("visible", visible.float()[None, None])
        layers, cin = [], 4
        for _ in range(4):  # 40 × 40 cells → 2 × 2 (stride 2 each, then a pool)
            layers += [nn.Conv2d(cin, width, 3, stride=2, padding=1), nn.ReLU()]
            cin, width = width, width * 2
        self.net = nn.Sequential(*layers, nn.AdaptiveAvgPool2d(2), nn.Flatten())
        self.head = nn.Sequential(nn.Linear(cin * 4, 128), nn.ReLU(), nn.Linear(128, 2 * POINTS))

    def forward(self, image: Tensor) -> Tensor:
        img = image.permute(0, 3, 1, 2).float() / 127.5 - 1.0
        top = F.grid_sample(img, self.coords.expand(len(img), -1, -1, -1), align_corners=False)
        vis = self.visible.expand(len(img), -1, -1, -1)
        out = self.head(self.net(torch.cat([top * vis, vis], dim=1))).view(-1, POINTS, 2)
        # the k-th point lies about (k+1)·SPACING ahead: learn the offset from straight on
        ahead = torch.arange(1, POINTS + 1, dtype=out.dtype) * SPACING_M
        return out + torch.stack([ahead, torch.zeros_like(ahead)], dim=-1)


def line_labels(geo: CarGeometry, speed: np.ndarray, steering: np.ndarray, person: np.ndarray,
                events: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Per frame: the person's path from it at SPACING_M, 2·SPACING_M, … along (POINTS, 2) and
    which points exist (the person drove that far, without a collision or e-stop on the way,
    and every step on the way was the person's)."""
    n = len(speed)
    poses = dead_reckon(geo, speed, steering)
    stop = np.full(n + 1, n, dtype=int)  # the first step ≥ t that is not the person's or an event
    bad = ~person.astype(bool)
    bad[np.asarray(events, dtype=int)] = True
    nxt = n
    for t in range(n - 1, -1, -1):
        nxt = t if bad[t] else nxt
        stop[t] = nxt
    points = np.zeros((n, POINTS, 2), np.float32)
    valid = np.zeros((n, POINTS), bool)
    targets = SPACING_M * np.arange(1, POINTS + 1)
    for t in range(n):
        end = stop[t]
        if end <= t:
            continue
        rel = relative(poses[t : end + 1], 0)[:, :2]
        arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(rel, axis=0).T))])
        ok = targets <= arc[-1]
        valid[t] = ok
        if ok.any():
            points[t, ok, 0] = np.interp(targets[ok], arc, rel[:, 0])
            points[t, ok, 1] = np.interp(targets[ok], arc, rel[:, 1])
    return points, valid


def progress_along(line: Tensor, xy: Tensor, reach: float = 0.35) -> Tensor:
    """Metres along the predicted line (N, POINTS, 2) from the car (the line starts at the origin)
    of each point xy (N, T, 2): its projection onto the nearest segment; 0 where it is farther
    than `reach` from the line (off the line, as off the track's markings: no progress)."""
    start = torch.zeros_like(line[:, :1])
    poly = torch.cat([start, line], dim=1)  # (N, P+1, 2)
    a, b = poly[:, :-1], poly[:, 1:]  # segments
    seg = b - a
    length = seg.norm(dim=-1).clamp(min=1e-6)  # (N, P)
    before = torch.cat([torch.zeros_like(length[:, :1]), length.cumsum(dim=1)[:, :-1]], dim=1)
    rel = xy[:, :, None, :] - a[:, None]  # (N, T, P, 2)
    along = ((rel * seg[:, None]).sum(-1) / length[:, None] ** 2).clamp(0, 1)  # (N, T, P)
    nearest = a[:, None] + along[..., None] * seg[:, None]
    dist = (xy[:, :, None, :] - nearest).norm(dim=-1)
    best = dist.argmin(dim=-1, keepdim=True)
    s = (before[:, None] + along * length[:, None]).gather(-1, best)[..., 0]
    return torch.where(dist.gather(-1, best)[..., 0] <= reach, s, torch.zeros_like(s))


@dataclass
class LineConfig:
    steps: int = 1500
    batch: int = 64
    lr: float = 2e-3
    seed: int = 0
    threads: int = 1
    geometry: CarGeometry = field(default_factory=CarGeometry)
    grid: MapGrid = field(default_factory=MapGrid)


def load_data(paths: list[str], cfg: LineConfig) -> dict:
    from carrt.episodes.reader import collision_events
    from carrt.interfaces import Mode
    from training.episodes import load_episodes

    episodes = load_episodes(paths)
    if not episodes:
        raise UserError(f"person line: no episodes under {', '.join(paths)}")
    images, pts, valid = [], [], []
    for ep in episodes:
        speed = np.nan_to_num(np.asarray(ep.steps["speed_mps"], dtype=np.float64))
        steering = np.nan_to_num(np.asarray(ep.steps["executed_action"], dtype=np.float64))[:, 0]
        person = np.asarray(ep.steps["mode"]) == int(Mode.MANUAL)
        p, v = line_labels(cfg.geometry, speed, steering, person,
                           collision_events(ep.steps, ep.end_reason))  # fmt: skip
        keep = v.any(axis=1)
        images.append(np.asarray(ep.frames)[keep])
        pts.append(p[keep])
        valid.append(v[keep])
    if not sum(len(v) for v in valid):
        raise UserError("person line: no frames the person drove on from")
    return {"images": np.concatenate(images), "points": np.concatenate(pts),
            "valid": np.concatenate(valid), "episodes": len(episodes)}  # fmt: skip


def train(paths: list[str], out: Path, cfg: LineConfig) -> LineNet:
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    data = load_data(paths, cfg)
    net = LineNet(cfg.geometry, cfg.grid)
    images = torch.from_numpy(data["images"])
    points, valid = torch.from_numpy(data["points"]), torch.from_numpy(data["valid"])
    print(f"person line: {data['episodes']} episodes, {len(images)} frames the person drove on "
          f"from", flush=True)  # fmt: skip
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, cfg.steps)
    gen = torch.Generator().manual_seed(cfg.seed)
    started, seen = time.monotonic(), 0.0
    for step in range(cfg.steps):
        pick = torch.randint(len(images), (cfg.batch,), generator=gen)
        img, pt, ok = images[pick], points[pick].clone(), valid[pick]
        flip = torch.rand(cfg.batch, generator=gen) < 0.5  # the mirrored frame, the mirrored line
        img = torch.where(flip[:, None, None, None], img.flip(2), img)
        pt[..., 1] = torch.where(flip[:, None], -pt[..., 1], pt[..., 1])
        err = (net(img) - pt).norm(dim=-1)
        loss = err[ok].mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        seen = 0.98 * seen + 0.02 * loss.item() if step else loss.item()
        if (step + 1) % 250 == 0 or step + 1 == cfg.steps:
            rate = (step + 1) / (time.monotonic() - started)
            print(f"person line: step {step + 1}/{cfg.steps} error {seen:.3f} m "
                  f"(ETA {(cfg.steps - step - 1) / rate:.0f} s)", flush=True)  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / "person_line.pt.tmp"
    torch.save({"state_dict": net.state_dict(), "config": asdict(cfg)}, tmp)
    tmp.replace(out / "person_line.pt")
    return net


def load(path: Path) -> LineNet:
    if not path.is_file():
        raise UserError(f"{path}: no such person-line file")
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    cfg = ckpt["config"]
    net = LineNet(CarGeometry(**cfg["geometry"]), MapGrid(**cfg["grid"]))
    net.load_state_dict(ckpt["state_dict"])
    return net.eval()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m research.person_line",
                                description=__doc__.split("\n")[0])  # fmt: skip
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="learn the person's line from their frames")
    t.add_argument("--episodes", nargs="+", required=True)
    t.add_argument("--out", required=True)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--steps", type=int, default=LineConfig.steps)
    t.add_argument("--threads", type=int, default=1)
    a = p.parse_args(argv)
    try:
        if a.steps < 1:
            raise UserError(f"--steps {a.steps}: 1 or more")
        train(a.episodes, Path(a.out), LineConfig(steps=a.steps, seed=a.seed, threads=a.threads))
        return 0
    except UserError as exc:
        print(f"person_line: error: {exc}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    raise SystemExit(main())
