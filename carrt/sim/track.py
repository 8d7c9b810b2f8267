"""The arena's one closed track, its racing line, seeded obstacle layouts, and fast geometry.

One fixed track for every layout: the paper drove one circuit and varied only the obstacles, so
a policy's numbers across layouts compare like with like. The circuit is built from straights
and arcs (a sweeper, a tight hairpin, a right-left S-bend), its heading blended over half a
metre at each joint, so the centerline has no curvature jumps a real taped track would not have.

Arc position s runs counter-clockwise from the start line (s = 0, on the bottom straight);
lateral offsets are positive to the left of the direction of travel (towards the infield).
"""

from __future__ import annotations

import colorsys
import functools
import math

import numpy as np

from carrt.layouts import LAYOUTS
from carrt.sim.types import Obstacle, Track

TRACK_WIDTH = 0.8
SAMPLE_SPACING = 0.02  # centerline sampling, metres
RACING_MARGIN = 0.15  # racing line stays this far inside each boundary
OBSTACLE_MIN_SPACING = 1.2  # along the track, metres
OBSTACLE_START_CLEAR = 1.5  # no obstacle this soon after the start line
OBSTACLE_END_CLEAR = 0.3  # nor right behind it, where the car sits at the start
OBSTACLE_MIN_GAP = 0.36  # free width left on the roomier side, inside the boundaries

_START = (3.2, 0.75, 0.0)  # x, y, heading of the start line
# (length, signed curvature): bottom straight, right sweeper, top straight, left hairpin,
# short infield straight, then an S-bend (right, left) back onto the bottom straight.
_SEGMENTS = (
    (1.6, 0.0),
    (math.pi * 1.15, 1 / 1.15),
    (3.5, 0.0),
    (math.pi * 0.55, 1 / 0.55),
    (0.7, 0.0),
    (math.pi / 2 * 0.6, -1 / 0.6),
    (math.pi / 2 * 0.6, 1 / 0.6),
)
_BLEND = 0.5  # curvature blending window (Hann), metres


def build_track(layout: str = "easy", seed: int = 0) -> Track:
    """The fixed circuit with `LAYOUTS[layout]` obstacles drawn from `seed` (positions, sizes
    and vivid colours always; for a (low, high) layout also the count, uniform in [low, high])."""
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; valid layouts: {', '.join(LAYOUTS)}")
    centerline, racing_line, length = _base_geometry()
    rng = np.random.default_rng([int(seed) % 2**32, LAYOUTS[layout].stream])
    base = Track(layout, int(seed), centerline, TRACK_WIDTH, racing_line, length=length)
    count = LAYOUTS[layout].obstacles
    if isinstance(count, tuple):
        count = int(rng.integers(count[0], count[1] + 1))
    obstacles = _place_obstacles(base, count, rng)
    return Track(
        layout, int(seed), centerline, TRACK_WIDTH, racing_line, obstacles=obstacles, length=length
    )


# ---------------------------------------------------------------------------------------------
# geometry queries


class _Geometry:
    """Per-track precomputed segment data, so queries are a few vectorised numpy ops."""

    def __init__(self, points: np.ndarray) -> None:
        self.points = np.asarray(points, dtype=np.float64)
        self.n = len(self.points)
        self.seg = np.roll(self.points, -1, axis=0) - self.points
        self.seg_len = np.hypot(self.seg[:, 0], self.seg[:, 1])
        self.cum = np.concatenate(([0.0], np.cumsum(self.seg_len)))
        self.length = float(self.cum[-1])
        seg_heading = np.arctan2(self.seg[:, 1], self.seg[:, 0])
        # vertex tangent: halfway between the two adjacent segments' directions
        prev = np.roll(seg_heading, 1)
        turn = _wrap(seg_heading - prev)
        self.vertex_heading = prev + 0.5 * turn
        self.tangent = np.stack([np.cos(self.vertex_heading), np.sin(self.vertex_heading)], 1)
        self.tangent_step = np.roll(self.tangent, -1, axis=0) - self.tangent
        self.curvature = turn / (0.5 * (self.seg_len + np.roll(self.seg_len, 1)))

    def heading_at(self, idx: np.ndarray, t: np.ndarray) -> np.ndarray:
        tx = self.tangent[idx, 0] + t * self.tangent_step[idx, 0]
        ty = self.tangent[idx, 1] + t * self.tangent_step[idx, 1]
        return np.arctan2(ty, tx)

    def project_window(self, x, y, idx: np.ndarray):
        """Nearest point among segments `idx` for each point: (segment, t, squared distance)."""
        px = np.asarray(x, dtype=np.float64)[..., None] - self.points[idx, 0]
        py = np.asarray(y, dtype=np.float64)[..., None] - self.points[idx, 1]
        sx, sy, ln = self.seg[idx, 0], self.seg[idx, 1], self.seg_len[idx]
        t = np.clip((px * sx + py * sy) / (ln * ln), 0.0, 1.0)
        d2 = (px - t * sx) ** 2 + (py - t * sy) ** 2
        k = np.argmin(d2, axis=-1)
        take = np.take_along_axis
        return idx[k], take(t, k[..., None], -1)[..., 0], take(d2, k[..., None], -1)[..., 0]

    def describe(self, x, y, seg: np.ndarray):
        """(s, lateral, heading) of points near segments `seg`, along the smooth normal field.

        Normals are interpolated between vertices (as pose_at offsets points), not taken per
        segment: otherwise points offset outside a bend all project onto the vertex, and
        pose_at → project would not round-trip.
        """
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        for _ in range(2):  # the root may lie on a neighbouring segment: move there once
            ax, ay = x - self.points[seg, 0], y - self.points[seg, 1]
            tx, ty = self.tangent[seg, 0], self.tangent[seg, 1]
            dx, dy = self.tangent_step[seg, 0], self.tangent_step[seg, 1]
            bx, by = self.seg[seg, 0], self.seg[seg, 1]
            # (a - t·b) · (T + t·ΔT) = 0, a quadratic in t with a dominant linear term
            c0 = ax * tx + ay * ty
            c1 = ax * dx + ay * dy - (bx * tx + by * ty)
            c2 = -(bx * dx + by * dy)
            t = 2 * c0 / (-c1 + np.sqrt(np.maximum(c1 * c1 - 4 * c0 * c2, 0.0)))
            seg = np.where(t < 0, seg - 1, np.where(t > 1, seg + 1, seg)) % self.n
        t = np.clip(t, 0.0, 1.0)
        s = self.cum[seg] + t * self.seg_len[seg]
        heading = self.heading_at(seg, t)
        ex = x - (self.points[seg, 0] + t * self.seg[seg, 0])
        ey = y - (self.points[seg, 1] + t * self.seg[seg, 1])
        lateral = np.cos(heading) * ey - np.sin(heading) * ex
        return s, lateral, heading


_GEOMETRY_CACHE: dict[int, tuple[np.ndarray, _Geometry]] = {}


def geometry(points: np.ndarray) -> _Geometry:
    """Cached geometry of a closed polyline (keyed by the array object, which it keeps alive)."""
    hit = _GEOMETRY_CACHE.get(id(points))
    if hit is not None and hit[0] is points:
        return hit[1]
    geo = _Geometry(points)
    if len(_GEOMETRY_CACHE) >= 32:
        _GEOMETRY_CACHE.pop(next(iter(_GEOMETRY_CACHE)))
    _GEOMETRY_CACHE[id(points)] = (points, geo)
    return geo


def project(track: Track, x, y):
    """(s, lateral, heading) of the nearest centerline point; scalars or arrays of any shape."""
    geo = geometry(track.centerline)
    xa, ya = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
    flat_x, flat_y = xa.ravel(), ya.ravel()
    out = np.empty((3, flat_x.size))
    every = np.arange(geo.n)
    chunk = max(1, 200_000 // geo.n)  # bounds the (points × segments) scratch arrays
    for a in range(0, flat_x.size, chunk):
        seg, _, _ = geo.project_window(flat_x[a : a + chunk], flat_y[a : a + chunk], every)
        out[:, a : a + chunk] = geo.describe(flat_x[a : a + chunk], flat_y[a : a + chunk], seg)
    if xa.ndim == 0:
        return float(out[0, 0]), float(out[1, 0]), float(out[2, 0])
    return tuple(o.reshape(xa.shape) for o in out)


def pose_at(track: Track, s, lateral=0.0):
    """(x, y, yaw) at arc position s (any real, wrapped) and lateral offset (left positive)."""
    geo = geometry(track.centerline)
    s_arr = np.mod(np.asarray(s, dtype=np.float64), geo.length)
    seg = np.clip(np.searchsorted(geo.cum, s_arr, side="right") - 1, 0, geo.n - 1)
    t = np.clip((s_arr - geo.cum[seg]) / geo.seg_len[seg], 0.0, 1.0)
    yaw = geo.heading_at(seg, t)
    lat = np.asarray(lateral, dtype=np.float64)
    x = geo.points[seg, 0] + t * geo.seg[seg, 0] - np.sin(yaw) * lat
    y = geo.points[seg, 1] + t * geo.seg[seg, 1] + np.cos(yaw) * lat
    if np.ndim(x) == 0:
        return float(x), float(y), float(yaw)
    return x, y, np.broadcast_to(yaw, np.shape(x))


def start_pose(track: Track) -> tuple[float, float, float]:
    return pose_at(track, 0.0)


def boundary_polylines(track: Track) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) boundary markings as closed (N, 2) polylines at ±width/2."""
    normals = _normals(geometry(track.centerline))
    half = track.width / 2
    return track.centerline + half * normals, track.centerline - half * normals


def curvature(points: np.ndarray) -> np.ndarray:
    """Signed curvature at each vertex of a closed polyline (left turns positive)."""
    return geometry(points).curvature


# ---------------------------------------------------------------------------------------------
# construction


@functools.lru_cache(maxsize=1)
def _base_geometry() -> tuple[np.ndarray, np.ndarray, float]:
    centerline = _centerline()
    geo = geometry(centerline)
    bound = TRACK_WIDTH / 2 - RACING_MARGIN
    n = geo.n
    offsets = smooth_offsets(centerline, np.zeros(n), np.full(n, -bound), np.full(n, bound))
    # not resampled: chords of a resampled polyline would add curvature noise
    racing = centerline + offsets[:, None] * _normals(geo)
    for arr in (centerline, racing):
        arr.flags.writeable = False
    return centerline, racing, geo.length


def _centerline() -> np.ndarray:
    total = sum(length for length, _ in _SEGMENTS)
    n = round(total / 0.005)  # integrate finely, resample at SAMPLE_SPACING afterwards
    ds = total / n
    s_mid = (np.arange(n) + 0.5) * ds
    ends = np.cumsum([length for length, _ in _SEGMENTS])
    kappa = np.array([k for _, k in _SEGMENTS])[np.searchsorted(ends, s_mid, side="right")]
    width = round(_BLEND / ds) | 1
    window = np.hanning(width + 2)[1:-1]
    window /= window.sum()
    kappa *= 2 * math.pi / (kappa.sum() * ds)  # exactly one turn: the loop closes in heading
    heading = np.cumsum(kappa) * ds - 0.5 * kappa * ds
    # blend the heading (not the curvature): the straights keep their exact directions
    trend = 2 * math.pi * s_mid / total
    heading = _START[2] + _circular_convolve(heading - trend, window) + trend
    steps = np.stack([np.cos(heading), np.sin(heading)], axis=1) * ds
    pts = np.concatenate([[_START[:2]], _START[:2] + np.cumsum(steps, axis=0)])
    closure = pts[-1] - pts[0]  # blending moved the end a little: spread the error along the lap
    pts = pts[:-1] - closure * (np.arange(n) / n)[:, None]
    return _resample(pts, SAMPLE_SPACING)


def _circular_convolve(signal: np.ndarray, window: np.ndarray) -> np.ndarray:
    half = len(window) // 2
    padded = np.concatenate([signal[-half:], signal, signal[:half]])
    return np.convolve(padded, window, mode="valid")


def _resample(points: np.ndarray, spacing: float) -> np.ndarray:
    """Closed polyline resampled at equal arc length (first point kept)."""
    closed = np.vstack([points, points[:1]])
    seg = np.hypot(*np.diff(closed, axis=0).T)
    cum = np.concatenate(([0.0], np.cumsum(seg)))
    n = max(8, round(cum[-1] / spacing))
    s = np.arange(n) * (cum[-1] / n)
    return np.stack([np.interp(s, cum, closed[:, 0]), np.interp(s, cum, closed[:, 1])], axis=1)


def _normals(geo: _Geometry) -> np.ndarray:
    h = geo.vertex_heading
    return np.stack([-np.sin(h), np.cos(h)], axis=1)


def smooth_offsets(
    points: np.ndarray,
    start: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    *,
    node_spacing: float = 0.06,
    rounds: int = 6,
) -> np.ndarray:
    """Lateral offsets within [lo, hi] per vertex making the offset path bend as little as it can.

    Minimises the integral of squared curvature under box bounds (the bounds turn "smooth" into
    "use the track's width"): Gauss-Newton on nodes every `node_spacing` m, on the true discrete
    curvature (plain second differences of offset points would reward hugging the inside of every
    corner, where the points bunch up), each step an exact bounded least-squares solve, halved
    until the cost falls. A node's bounds are the tightest within its span, so the interpolated
    answer respects them. A tiny pull towards `start` pins the free sideways drift on straights.
    """
    geo = geometry(points)
    step = max(1, round(node_spacing / (geo.length / geo.n)))
    nodes = np.arange(0, geo.n, step)
    m = len(nodes)
    span = np.arange(-step, step + 1)
    lo_c = np.max(lo[(nodes[:, None] + span) % geo.n], axis=1)
    hi_c = np.maximum(np.min(hi[(nodes[:, None] + span) % geo.n], axis=1), lo_c)
    normals = _normals(geo)[nodes]
    base = geo.points[nodes]
    h = geo.length / m
    reg, damp, eps = 1e-3, 1e-2, 1e-6
    target = start[nodes]

    def residuals(d: np.ndarray) -> np.ndarray:  # (..., m) curvature · sqrt(h)
        pts = base + d[..., :, None] * normals
        seg = np.roll(pts, -1, axis=-2) - pts
        ang = np.arctan2(seg[..., 1], seg[..., 0])
        ln = np.hypot(seg[..., 0], seg[..., 1])
        turn = _wrap(ang - np.roll(ang, 1, axis=-1))
        return turn / (0.5 * (ln + np.roll(ln, 1, axis=-1))) * math.sqrt(h)

    def objective(d: np.ndarray) -> float:
        return float(np.sum(residuals(d) ** 2) + reg * np.sum((d - target) ** 2))

    # first guess: curvature linearised around the centerline, κ + κ²d + d'' (a convex fit
    # that copes with bounds far from `start`, where Gauss-Newton from a clipped start stalls)
    eye = np.eye(m)
    kappa = geo.curvature[nodes]
    lin = (np.roll(eye, -1, axis=1) - 2 * eye + np.roll(eye, 1, axis=1)) / h**2 + np.diag(kappa**2)
    lin *= math.sqrt(h)
    d = _box_qp(lin.T @ lin + reg * eye, lin.T @ kappa * math.sqrt(h) - reg * target, lo_c, hi_c)
    cost = objective(d)
    for _ in range(rounds):
        r = residuals(d)
        jac = (residuals(d[None, :] + eps * eye) - r[None, :]).T / eps  # jac[i, j] = ∂r_i/∂d_j
        hess = jac.T @ jac + (reg + damp) * eye
        grad = jac.T @ r + reg * (d - target)
        delta = _box_qp(hess, grad, lo_c - d, hi_c - d)
        for _ in range(8):
            trial = np.clip(d + delta, lo_c, hi_c)
            trial_cost = objective(trial)
            if trial_cost < cost:
                d, cost = trial, trial_cost
                break
            delta = delta / 2
        else:
            break
    out = np.interp(geo.cum[:-1], np.append(geo.cum[nodes], geo.length), np.append(d, d[0]))
    # linear interpolation leaves slope kinks at the nodes; blend them over two node spacings
    window = np.hanning(4 * step + 3)[1:-1]
    out = _circular_convolve(out, window / window.sum())
    return np.clip(out, lo, hi)


def _box_qp(hess: np.ndarray, grad: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """argmin ½xᵀHx + gᵀx with lo ≤ x ≤ hi, H positive definite (primal active set).

    Feasible throughout and the objective falls every step, so it cannot cycle; releasing all
    wrongly-held bounds at once and blocking on all that are hit keeps the step count small.
    """
    x = np.clip(np.zeros_like(grad), lo, hi)
    gr = hess @ x + grad
    held = ((x <= lo) & (gr > 0)) | ((x >= hi) & (gr < 0))
    for _ in range(4 * len(x)):
        free = ~held
        step = np.zeros_like(x)
        if free.any():
            step[free] = -np.linalg.solve(hess[np.ix_(free, free)], gr[free])
        if np.max(np.abs(step)) < 1e-12:
            wrong = (held & (x <= lo) & (gr < 0)) | (held & (x >= hi) & (gr > 0))
            if not wrong.any():
                break
            held &= ~wrong
            continue
        with np.errstate(divide="ignore", invalid="ignore"):
            room = np.where(step > 0, (hi - x) / step, np.where(step < 0, (lo - x) / step, np.inf))
        alpha = min(1.0, float(np.min(room)))
        x = np.clip(x + alpha * step, lo, hi)
        if alpha < 1.0:
            held |= room <= alpha + 1e-12
        gr = hess @ x + grad
    return x


def _place_obstacles(track: Track, count: int, rng: np.random.Generator) -> tuple[Obstacle, ...]:
    if count == 0:
        return ()
    lo_s, hi_s = OBSTACLE_START_CLEAR, track.length - OBSTACLE_END_CLEAR
    slack = hi_s - lo_s - (count - 1) * OBSTACLE_MIN_SPACING
    if slack < 0:
        raise ValueError(f"{count} obstacles do not fit on a {track.length:.1f} m track")
    # uniform over all spacings that respect the minimum: sorted draws plus fixed gaps
    s_pos = lo_s + np.sort(rng.uniform(0.0, slack, count)) + OBSTACLE_MIN_SPACING * np.arange(count)
    half = track.width / 2
    obstacles = []
    for s in s_pos:
        radius = float(rng.uniform(0.08, 0.12))
        height = float(rng.uniform(0.2, 0.3))
        # |offset| >= min_off leaves OBSTACLE_MIN_GAP on the roomier side; <= max_off keeps the
        # whole cylinder on the track, where a policy has to deal with it
        min_off = max(0.0, OBSTACLE_MIN_GAP + radius - half)
        max_off = half - radius
        offset = float(rng.uniform(min_off, max_off)) * (1 if rng.random() < 0.5 else -1)
        x, y, _ = pose_at(track, float(s), offset)
        obstacles.append(Obstacle(x, y, radius, height, _saturated_colour(rng)))
    return tuple(obstacles)


def _saturated_colour(rng: np.random.Generator) -> tuple[int, int, int]:
    """A vivid colour that no floor, fence or marking has (those are greys, white, yellow)."""
    hue = float(rng.uniform(0.18, 1.09)) % 1.0  # skips 0.09-0.18: the centre line's yellow
    r, g, b = colorsys.hsv_to_rgb(hue, float(rng.uniform(0.75, 1.0)), float(rng.uniform(0.7, 1)))
    return round(r * 255), round(g * 255), round(b * 255)


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi
