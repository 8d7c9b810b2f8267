"""Track + car + the bookkeeping a run needs: collisions, progress along the track, laps, resets.

Collisions are judged on the car's body rectangle, not its reference point: a 0.20 m car that
clips a bucket with a front corner has crashed, and a policy trained on centre-point collisions
would learn to cut that close. Leaving the track's markings is allowed (the paper's car could
run wide); only the fence and the obstacles stop it.

After a collision the car stands where it hit until reset(), which does what a person does when
they lift a crashed car back on: it sets it down at rest on the centerline, heading along the
track, just past what it hit (its tail `RESET_AHEAD` beyond the obstacle's far edge), at the
first place there where its body is clear of every obstacle and the fence by a margin. Putting
it back behind the obstacle (the old rule) made the car re-crash into the same bucket from rest.

The metres a reset skips forward are not driven: they are kept in `skipped` and laps are
counted on `progress - skipped`, so a crash never brings a lap closer. Completion ratio is
unaffected either way (it stops at the first failure), and the metrics' distance ignores
teleports.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from carrt.sim.car import CarParams, footprint, step_car
from carrt.sim.track import build_track, geometry, pose_at, project
from carrt.sim.types import CarState, Track

MAX_SUBSTEP = 0.01  # collision checks at least every 10 ms (2.5 cm at top speed)
RESET_AHEAD = 0.3  # auto-reset sets the car's tail this far past the far edge of what it hit
RESET_CLEARANCE = 0.15  # and moves on until its body is this far from every obstacle
RESET_FENCE_CLEARANCE = 0.1  # and from the fence
RESET_STEP = 0.05  # search step along the track, metres


@dataclass(frozen=True)
class StepInfo:
    """What happened during one step.

    collision is True on every step while the car stands collided (until reset()), so a
    consumer polling only some steps cannot miss it; count rising edges to count crashes.
    """

    collision: bool
    collided_with: str  # 'fence', 'obstacle' or ''
    lap_completed: bool
    off_track: bool = False  # the body's centre is outside the boundary markings


class SimWorld:
    """One car on one track; `step` advances physics, collisions and progress deterministically.

    Progress: `s` is the arc position in [0, track.length); `progress` is the unwrapped arc
    position (it keeps growing lap after lap, and goes back when the car does or is reset);
    a lap is counted the first time `progress` passes each multiple of the track length, so
    rocking back and forth over the start line counts once.
    """

    def __init__(
        self,
        layout: str = "easy",
        seed: int = 0,
        params: CarParams | None = None,
        *,
        track: Track | None = None,
    ) -> None:
        self.track = track if track is not None else build_track(layout, seed)
        self.params = params if params is not None else CarParams()
        self.time = 0.0
        self.laps = 0
        self.collisions = 0  # collisions since construction
        self.resets = 0
        self.skipped = 0.0  # metres auto-resets carried the car forward (not credited as laps)
        self._locator = Locator(self.track)
        self._obstacles = [(o.x, o.y, o.radius) for o in self.track.obstacles]
        self.car = CarState(*pose_at(self.track, 0.0))
        self.progress = 0.0
        self.lateral = 0.0
        self.off_track = False
        self._place(0.0)

    # -- queries ---------------------------------------------------------------------------

    @property
    def s(self) -> float:
        return self.progress % self.track.length

    @property
    def distance(self) -> float:
        """Distance gained along the track since the last reset (negative when going back)."""
        return self.progress - self._progress_at_reset

    def footprint(self) -> list[tuple[float, float]]:
        return footprint(self.car, self.params)

    # -- stepping --------------------------------------------------------------------------

    def step(self, dt: float, steering_cmd: float, throttle_cmd: float) -> StepInfo:
        """Advance dt seconds holding the commands (long steps are split for collision checks)."""
        n = max(1, math.ceil(dt / MAX_SUBSTEP - 1e-9))
        h = dt / n
        lap = False
        for _ in range(n):
            self.time += h
            if self.collided:
                continue
            self.car = step_car(self.car, self.params, h, steering_cmd, throttle_cmd)
            lap |= self._track_progress()
            hit = self._collision()
            if hit:
                self.collided, self.collided_with = True, hit
                self.collisions += 1
                self.car = _stopped(self.car)
            else:
                self.last_safe_s = self.s
        return StepInfo(self.collided, self.collided_with, lap, self.off_track)

    def reset(self, s: float | None = None) -> None:
        """Put the car back on the centerline at rest, heading along the track: at s, or (the
        auto-reset) where a person would set it down: `reset_place()`.

        Laps, time and the odometer carry on (the paper's reset is a pause, not a new run).
        """
        auto = s is None
        if auto:
            s = self.reset_place()
        self.resets += 1
        before = self.progress
        self._place(float(s))
        if auto:
            self.skipped += max(self.progress - before, 0.0)

    def reset_place(self) -> float:
        """Where the auto-reset sets the car down (an arc position, possibly ≥ track length).

        From where it was last safe, past the obstacle it hit (if it hit one ahead of it), on
        to the first place clear of every obstacle and the fence (`clear_place_after`).
        """
        start = self.last_safe_s
        hit = self._obstacle_hit()
        if hit is not None:
            length = self.track.length
            s_o = project(self.track, hit.x, hit.y)[0]
            ahead = (s_o - start + length / 2) % length - length / 2
            if ahead > -hit.radius - self.params.length:  # beside or ahead: go past it
                start += ahead + hit.radius + RESET_AHEAD + self.params.rear_overhang
        return self.clear_place_after(start)

    def clear_place_after(self, s: float) -> float:
        """The first arc position at or after s where a car at rest on the centerline is clear
        of every obstacle by RESET_CLEARANCE and of the fence by RESET_FENCE_CLEARANCE."""
        return self._first_clear(s, RESET_STEP)

    def clear_place_before(self, s: float) -> float:
        """The first arc position at or behind s where a car at rest is clear (as above)."""
        return self._first_clear(s, -RESET_STEP)

    def body_gaps(self, probe: CarState) -> tuple[float, float]:
        """(nearest obstacle, nearest fence) distance of a car body at `probe`, in metres: the
        one measure the auto-reset's clear place and the safety driver's look-ahead judge by."""
        obstacle = min(
            (_distance_to_body(probe, self.params, ox, oy) - r for ox, oy, r in self._obstacles),
            default=math.inf,
        )
        width, height = self.track.arena
        fence = min(min(x, y, width - x, height - y) for x, y in footprint(probe, self.params))
        return obstacle, fence

    # -- internals -------------------------------------------------------------------------

    def _place(self, s: float) -> None:
        length = self.track.length
        x, y, yaw = pose_at(self.track, s)
        old = self.car
        self.car = CarState(x, y, yaw, odometer=old.odometer, encoder_ticks=old.encoder_ticks)
        # the unwrapped position nearest to where the car was, so laps stay honest
        lap_base = self.progress - self.progress % length
        candidates = [lap_base + (s % length) + k * length for k in (-1, 0, 1)]
        self.progress = min(candidates, key=lambda c: abs(c - self.progress))
        self._progress_at_reset = self.progress
        self.last_safe_s = s % length
        self.collided, self.collided_with = False, ""
        self._locator.reset()
        self._locate()

    def _locate(self) -> float:
        car = self.car
        s, lateral, heading = self._locator.locate(car.x, car.y)
        self.lateral = lateral
        # the body's centre sits ahead of the reference point, off to the side by the heading error
        ahead = self.params.length / 2 - self.params.rear_overhang
        centre_lateral = lateral + ahead * math.sin(car.yaw - heading)
        self.off_track = abs(centre_lateral) > self.track.width / 2
        return s

    def _track_progress(self) -> bool:
        length = self.track.length
        s = self._locate()
        self.progress += (s - self.s + length / 2) % length - length / 2
        if self.progress - self.skipped >= (self.laps + 1) * length:
            self.laps += 1
            return True
        return False

    def _collision(self) -> str:
        corners = self.footprint()
        width, height = self.track.arena
        for cx, cy in corners:  # the fence is straight: the body crosses it corner first
            if cx <= 0.0 or cy <= 0.0 or cx >= width or cy >= height:
                return "fence"
        x, y = self.car.x, self.car.y
        reach = self.params.length + self.params.width  # beyond this no corner can touch
        for ox, oy, r in self._obstacles:
            if abs(ox - x) > reach + r or abs(oy - y) > reach + r:
                continue
            if _distance_to_body(self.car, self.params, ox, oy) <= r:
                return "obstacle"
        return ""

    def _first_clear(self, s: float, step: float) -> float:
        for _ in range(math.ceil(self.track.length / abs(step))):
            if self._clear_at(s):
                return s
            s += step
        return s

    def _clear_at(self, s: float) -> bool:
        obstacle, fence = self.body_gaps(CarState(*pose_at(self.track, s)))
        return obstacle >= RESET_CLEARANCE and fence >= RESET_FENCE_CLEARANCE

    def _obstacle_hit(self):
        """The obstacle the car stands against after an obstacle collision, else None."""
        if not (self.collided and self.collided_with == "obstacle") or not self.track.obstacles:
            return None
        return min(
            self.track.obstacles,
            key=lambda o: _distance_to_body(self.car, self.params, o.x, o.y) - o.radius,
        )


class Locator:
    """`project` for one moving point, walking from the last answer: a step costs a few µs.

    Walking locally also keeps the answer on the same part of the track when the car strays
    towards a neighbouring leg (the hairpin's legs are close), which progress bookkeeping needs.
    A walk longer than `max_walk_m` (a teleport) falls back to the global search.
    """

    def __init__(self, track: Track, max_walk_m: float = 1.0) -> None:
        self.geo = geometry(track.centerline)
        self._px = self.geo.points[:, 0].tolist()
        self._py = self.geo.points[:, 1].tolist()
        self._sx = self.geo.seg[:, 0].tolist()
        self._sy = self.geo.seg[:, 1].tolist()
        self._len2 = (self.geo.seg_len**2).tolist()
        self._len = self.geo.seg_len.tolist()
        self._cum = self.geo.cum.tolist()
        self._tx, self._ty = self.geo.tangent[:, 0].tolist(), self.geo.tangent[:, 1].tolist()
        step = self.geo.tangent_step
        self._dtx, self._dty = step[:, 0].tolist(), step[:, 1].tolist()
        self._max_walk = max(3, math.ceil(max_walk_m / (self.geo.length / self.geo.n)))
        self._every = np.arange(self.geo.n)
        self._hint: int | None = None

    def reset(self) -> None:
        self._hint = None

    def locate(self, x: float, y: float) -> tuple[float, float, float]:
        """(s, lateral, heading) of the nearest centerline point near the previous one."""
        if self._hint is None:
            seg, t, _ = self.geo.project_window(x, y, self._every)
            return self._answer(x, y, int(seg), float(t))
        n = self.geo.n
        i = self._hint
        best, t = self._dist2(i, x, y)
        for direction in (1, -1):
            for _ in range(self._max_walk):
                j = (i + direction) % n
                d2, tj = self._dist2(j, x, y)
                if d2 >= best:
                    break
                i, best, t = j, d2, tj
            else:
                seg, tg, _ = self.geo.project_window(x, y, self._every)
                return self._answer(x, y, int(seg), float(tg))
        return self._answer(x, y, i, t)

    def _dist2(self, i: int, x: float, y: float) -> tuple[float, float]:
        px, py = x - self._px[i], y - self._py[i]
        sx, sy = self._sx[i], self._sy[i]
        t = min(max((px * sx + py * sy) / self._len2[i], 0.0), 1.0)
        ex, ey = px - t * sx, py - t * sy
        return ex * ex + ey * ey, t

    def _answer(self, x: float, y: float, seg: int, t: float) -> tuple[float, float, float]:
        """track.project's answer for this segment, in plain floats (numpy costs more here)."""
        n = self.geo.n
        for _ in range(2):  # same smooth-normal refinement as _Geometry.describe
            ax, ay = x - self._px[seg], y - self._py[seg]
            tx, ty = self._tx[seg], self._ty[seg]
            dx, dy = self._dtx[seg], self._dty[seg]
            bx, by = self._sx[seg], self._sy[seg]
            c0 = ax * tx + ay * ty
            c1 = ax * dx + ay * dy - (bx * tx + by * ty)
            c2 = -(bx * dx + by * dy)
            denom = -c1 + math.sqrt(max(c1 * c1 - 4 * c0 * c2, 0.0))
            t = 2 * c0 / denom if denom > 0 else t
            if t < 0:
                seg = (seg - 1) % n
            elif t > 1:
                seg = (seg + 1) % n
            else:
                break
        t = min(max(t, 0.0), 1.0)
        self._hint = seg
        hx = self._tx[seg] + t * self._dtx[seg]
        hy = self._ty[seg] + t * self._dty[seg]
        heading = math.atan2(hy, hx)
        ex = x - (self._px[seg] + t * self._sx[seg])
        ey = y - (self._py[seg] + t * self._sy[seg])
        lateral = (hx * ey - hy * ex) / math.hypot(hx, hy)
        return self._cum[seg] + t * self._len[seg], lateral, heading


def _distance_to_body(car: CarState, p: CarParams, px: float, py: float) -> float:
    """Distance from a point to the car's rectangle (0 inside)."""
    c, s = math.cos(car.yaw), math.sin(car.yaw)
    dx, dy = px - car.x, py - car.y
    lon, lat = c * dx + s * dy, -s * dx + c * dy
    back, front, half = -p.rear_overhang, p.length - p.rear_overhang, p.width / 2
    ex = max(back - lon, 0.0, lon - front)
    ey = max(abs(lat) - half, 0.0)
    return math.hypot(ex, ey)


def _stopped(car: CarState) -> CarState:
    return CarState(
        car.x,
        car.y,
        car.yaw,
        v=0.0,
        yaw_rate=0.0,
        steer=car.steer,
        motor=0.0,
        sliding=False,
        odometer=car.odometer,
        encoder_ticks=car.encoder_ticks,
    )
