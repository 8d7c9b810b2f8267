"""The car's camera image and a top-down map, in numpy only.

The camera must keep up with faster-than-real-time simulation (≥ 1000 frames/s on one core),
so nothing is rasterised per frame. What depends only on the camera mount (each pixel's ray,
where it meets the floor in the car's frame, its azimuth and its slope) is computed once; the
floor markings are rasterised once into a 5 mm/px texture. A frame is then a rotation and a
gather for the floor, plus horizontal ray casts for the vertical things (fence, obstacles) in a
few hundred azimuth bins. Every pixel looks up the bin of its own azimuth, so verticals lean as
they do through a pitched pinhole and meet the floor where the floor says they stand.

Colours are packed into one little-endian uint32 per pixel so each gather moves one word.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterable, Sequence

import numpy as np

from carrt.sim.car import CarParams
from carrt.sim.types import RGB, CameraParams, Track

SKY_COLOUR: RGB = (125, 145, 175)  # the hall's wall above the fence
FENCE_BASE_H = 0.04  # darker stripe at the fence's foot: its height in the image gives distance
FENCE_BASE_SHADE = 0.7
WALL_SHADE = (0.92, 1.0, 0.84, 0.96)  # south, east, north, west: corners stay visible
BOUNDARY_W = 0.025
CENTRE_W = 0.02
DASH_M = 0.1  # centre line: dash and gap length
FLOOR_NOISE = 4  # ± grey levels of fixed speckle, so motion over plain floor is visible
TEXTURE_PPM = 200  # floor texture resolution, pixels per metre
TEXTURE_MARGIN = 0.5  # floor beyond the fence, in case a pose sits on or past it
N_BINS_PER_COLUMN = 4
_NO_HIT = 1e6  # finite stand-ins for "never", so no inf/nan arithmetic per frame
_MAX_GROUND = 20.0  # rays that meet the floor further than this are behind the fence anyway

_CAR = CarParams()  # the map draws the default car's body
_SHADES = 32  # shading levels on a cylinder's side
_ORDER = np.dtype("<u4")


def _pack(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) colours (any numeric type, clipped to 0..255) → (...) little-endian RGBA words."""
    rgb = np.asarray(rgb)
    c = (
        rgb.astype(_ORDER)
        if rgb.dtype == np.uint8
        else np.clip(np.rint(rgb), 0, 255).astype(_ORDER)
    )
    return c[..., 0] | (c[..., 1] << 8) | (c[..., 2] << 16) | np.asarray(255 << 24, _ORDER)


def boundaries(track: Track) -> tuple[np.ndarray, np.ndarray]:
    """Left and right boundary polylines (closed), offset ±width/2 along the centreline normal.

    Kept here rather than taken from track.py so the renderer works on any Track, including
    hand-made ones.
    """
    c = np.asarray(track.centerline, float)
    t = np.roll(c, -1, axis=0) - np.roll(c, 1, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    n = np.stack([-t[:, 1], t[:, 0]], axis=1)
    half = track.width / 2.0
    return c + half * n, c - half * n


def _resample(poly: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every `step` metres along a closed polyline, with their arc length."""
    closed = np.vstack([poly, poly[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.arange(0.0, cum[-1], step)
    x = np.interp(s, cum, closed[:, 0])
    y = np.interp(s, cum, closed[:, 1])
    return np.stack([x, y], axis=1), s


def _stamp(img: np.ndarray, pts: np.ndarray, width: float, ppm: float, origin, colour) -> None:
    """Paint a thick line through densely sampled points: every pixel whose centre lies within
    width/2 of a sample. Dense samples make this a fair thick polyline without a line drawer."""
    if len(pts) == 0:
        return
    h, w = img.shape[:2]
    r = width / 2.0 * ppm
    k = math.ceil(r) + 1
    off = np.arange(-k, k + 1)
    ox, oy = np.meshgrid(off, off)
    ox, oy = ox.ravel(), oy.ravel()
    px = (pts[:, 0] - origin[0]) * ppm
    py = (pts[:, 1] - origin[1]) * ppm
    ix = np.floor(px)[:, None].astype(int) + ox
    iy = np.floor(py)[:, None].astype(int) + oy
    d2 = (ix + 0.5 - px[:, None]) ** 2 + (iy + 0.5 - py[:, None]) ** 2
    keep = (d2 <= r * r) & (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    img[iy[keep], ix[keep]] = colour


def floor_image(track: Track, ppm: float, margin: float, noise: int = 0) -> np.ndarray:
    """The floor seen from above, row 0 at y = -margin (y grows with the row), RGB uint8."""
    aw, ah = track.arena
    w = math.ceil((aw + 2 * margin) * ppm)
    h = math.ceil((ah + 2 * margin) * ppm)
    img = np.empty((h, w, 3), np.uint8)
    img[:] = track.floor_colour
    origin = (-margin, -margin)
    step = 0.5 / ppm
    for line in boundaries(track):
        pts, _ = _resample(line, step)
        _stamp(img, pts, BOUNDARY_W, ppm, origin, track.marking_colour)
    pts, s = _resample(np.asarray(track.centerline, float), step)
    dash = (s % (2 * DASH_M)) < DASH_M
    _stamp(img, pts[dash], CENTRE_W, ppm, origin, track.centre_marking_colour)
    if noise:
        rng = np.random.default_rng(track.seed)
        speckle = rng.integers(-noise, noise + 1, size=(h, w, 1), dtype=np.int16)
        img = np.clip(img + speckle, 0, 255).astype(np.uint8)
    return img


class Renderer:
    """The car's forward camera over one track. Deterministic: a pose gives one image.

    Pixels are kept in azimuth-bin order, so the pixels an obstacle can cover are one slice,
    and every frame ends in a single gather from one palette (floor texture followed by this
    frame's fence and obstacle colours). The palette's tail changes per frame, hence the lock.
    """

    def __init__(
        self,
        track: Track,
        camera: CameraParams = CameraParams(),  # noqa: B008 - frozen dataclass, safe default
        sky_colour: RGB = SKY_COLOUR,
    ):
        self.track = track
        self.camera = camera
        self.sky_colour = sky_colour
        self._lock = threading.Lock()
        self._setup_rays()
        self._setup_palette()

    def _setup_rays(self) -> None:
        cam = self.camera
        w, h = cam.width, cam.height
        f = (w / 2.0) / math.tan(math.radians(cam.fov_deg) / 2.0)
        right = (np.arange(w) + 0.5 - w / 2.0) / f
        up = -(np.arange(h) + 0.5 - h / 2.0) / f
        right, up = np.meshgrid(right, up)
        p = math.radians(cam.pitch_deg)
        d_fwd = math.cos(p) + math.sin(p) * up
        d_up = -math.sin(p) + math.cos(p) * up
        slope = (d_up / np.hypot(d_fwd, right)).ravel()
        az = np.arctan2(-right, d_fwd).ravel()  # counter-clockwise, 0 straight ahead
        nb = N_BINS_PER_COLUMN * w
        lo, hi = float(az.min()), float(az.max())
        self._az_lo, self._az_step = lo, (hi - lo) / (nb - 1)
        self._bin_az = lo + self._az_step * np.arange(nb)
        bins = np.rint((az - lo) / self._az_step).astype(np.intp)
        perm = np.argsort(bins, kind="stable")
        self._bins = bins[perm]
        self._counts = np.bincount(bins, minlength=nb)
        self._starts = np.concatenate([[0], np.cumsum(self._counts)])
        self._slope = slope[perm]
        self._sky = self._slope >= 0
        down = ~self._sky
        g = np.zeros(len(perm))
        g[down] = cam.height_m / -self._slope[down]
        g = np.minimum(g, _MAX_GROUND)  # further hits are behind the fence: any index will do
        self._gx = g * np.cos(az[perm])  # floor hit relative to the camera, car frame
        self._gy = g * np.sin(az[perm])
        # image pixel q is sorted pixel inv[q]: bytes to pick from the packed words, alpha dropped
        inv = np.argsort(perm)
        self._out_bytes = ((inv * 4)[:, None] + np.arange(3)).ravel()

    def _setup_palette(self) -> None:
        tex = floor_image(self.track, TEXTURE_PPM, TEXTURE_MARGIN, FLOOR_NOISE)
        self._tex_w, self._tex_h = tex.shape[1], tex.shape[0]
        n_tex = tex.shape[0] * tex.shape[1]
        nb = len(self._counts)
        obs = self.track.obstacles
        self._palette = np.empty(n_tex + (3 + 2 * len(obs)) * nb, _ORDER)
        self._palette[:n_tex] = _pack(tex).ravel()
        self._fence_at = n_tex  # base, side, sky: nb entries each
        self._fence_idx = n_tex + self._bins
        self._ob_at = n_tex + 3 * nb  # per obstacle: side, cap
        self._ob_xy = np.array([[o.x, o.y] for o in obs], float).reshape(-1, 2)
        self._ob_r = np.array([o.radius for o in obs], float)
        self._ob_rgb = np.array([o.colour for o in obs], float).reshape(-1, 3)
        shade = 0.5 + 0.5 * np.minimum(np.arange(_SHADES + 1) / _SHADES, 1.0)
        self._ob_lut = _pack(self._ob_rgb[:, None, :] * shade[None, :, None])
        for j, o in enumerate(obs):
            cap = _pack(np.minimum(np.array(o.colour, float) * 1.15 + 15, 255))
            at = self._ob_at + (2 * j + 1) * nb
            self._palette[at : at + nb] = cap
        fence = np.array(self.track.fence_colour, float)
        shades = np.array(WALL_SHADE)[:, None]
        self._wall_base = _pack(fence * shades * FENCE_BASE_SHADE)
        self._wall_side = _pack(fence * shades)
        self._palette[n_tex + 2 * nb : n_tex + 3 * nb] = _pack(np.array(self.sky_colour, float))
        # a camera above the fence sees floor beyond it, which needs exact texture clipping
        self._over_fence = self.camera.height_m >= self.track.fence_height

    def render(self, x: float, y: float, yaw: float) -> np.ndarray:
        """The (height, width, 3) uint8 RGB frame seen from the car at (x, y, yaw)."""
        with self._lock:
            return self._render(float(x), float(y), float(yaw))

    def _render(self, x: float, y: float, yaw: float) -> np.ndarray:
        cam = self.camera
        h, top = cam.height_m, self.track.fence_height
        c, s = math.cos(yaw), math.sin(yaw)
        aw, ah = self.track.arena
        # camera position, kept inside the fence so every ray meets it exactly once
        cx = min(max(x + cam.forward_m * c, 1e-3), aw - 1e-3)
        cy = min(max(y + cam.forward_m * s, 1e-3), ah - 1e-3)

        # floor: rotate the precomputed floor hits into the world, index the texture
        k = TEXTURE_PPM
        u = self._gx * (c * k) - self._gy * (s * k) + (cx + TEXTURE_MARGIN) * k
        v = self._gx * (s * k) + self._gy * (c * k) + (cy + TEXTURE_MARGIN) * k
        iu, iv = u.astype(np.intp), v.astype(np.intp)
        if self._over_fence:
            np.clip(iu, 0, self._tex_w - 1, out=iu)
            np.clip(iv, 0, self._tex_h - 1, out=iv)
        # indices of rays that meet the fence first may be anything: the fence replaces them
        floor = iv * self._tex_w + iu

        # the fence: one horizontal cast per azimuth bin (cos never returns exactly 0)
        ang = self._bin_az + yaw
        dx, dy = np.cos(ang), np.sin(ang)
        tx = np.where(dx > 0, aw - cx, -cx) / dx
        ty = np.where(dy > 0, ah - cy, -cy) / dy
        d_fence = np.minimum(tx, ty)
        wall = np.where(tx < ty, np.where(dx > 0, 1, 3), np.where(dy > 0, 2, 0))
        nb = len(dx)
        at = self._fence_at
        self._palette[at : at + nb] = self._wall_base[wall]
        self._palette[at + nb : at + 2 * nb] = self._wall_side[wall]
        depth = np.repeat(d_fence, self._counts)
        z = h + depth * self._slope  # height where each ray meets the fence
        kind = (z >= FENCE_BASE_H).astype(np.intp)
        kind += z > top
        fence = kind * nb + self._fence_idx
        on_floor = z < 0
        if self._over_fence:
            on_floor |= (z > top) & ~self._sky
        idx = np.where(on_floor, floor, fence)

        if len(self._ob_r):
            self._draw_obstacles(idx, depth, cx, cy, yaw, dx, dy)
        words = self._palette.take(idx, mode="clip")
        img = words.view(np.uint8).take(self._out_bytes)
        return img.reshape(cam.height, cam.width, 3)

    def _draw_obstacles(self, idx, depth, cx, cy, yaw, dx, dy) -> None:
        """Z-buffered cylinders, each over the slice of pixels whose bins its outline spans."""
        h = self.camera.height_m
        rx, ry = self._ob_xy[:, 0] - cx, self._ob_xy[:, 1] - cy
        dist = np.hypot(rx, ry)
        inside = dist <= self._ob_r
        half = np.arcsin(np.minimum(self._ob_r / np.maximum(dist, 1e-9), 1.0))
        bearing = (np.arctan2(ry, rx) - yaw + math.pi) % (2 * math.pi) - math.pi
        b0 = np.floor((bearing - half - self._az_lo) / self._az_step).astype(int)
        b1 = np.ceil((bearing + half - self._az_lo) / self._az_step).astype(int)
        nb = len(dx)
        seen = (b1 >= 0) & (b0 < nb) & ~inside
        counts, slopes, bins, lut = self._counts, self._slope, self._bins, self._ob_lut
        for j in np.flatnonzero(seen).tolist():
            lo_b, hi_b = max(int(b0[j]), 0), min(int(b1[j]), nb - 1) + 1
            o = self.track.obstacles[j]
            # ray–circle entry (and exit, for the lid) per bin
            proj = rx[j] * dx[lo_b:hi_b] + ry[j] * dy[lo_b:hi_b]
            disc = proj * proj + (o.radius**2 - dist[j] ** 2)
            sq = np.sqrt(np.maximum(disc, 0.0))
            missed = disc <= 0
            d_in = proj - sq
            d_in[missed] = _NO_HIT
            # shaded by how squarely the surface faces the camera, so the roundness shows
            at = self._ob_at + 2 * j * nb
            self._palette[at + lo_b : at + hi_b] = lut[j].take(
                (sq * (_SHADES / o.radius)).astype(np.intp)
            )
            lo, hi = self._starts[lo_b], self._starts[hi_b]
            n = counts[lo_b:hi_b]
            d = np.repeat(d_in, n)
            slope = slopes[lo:hi]
            z = d * slope
            z += h
            nearer = d < depth[lo:hi]
            side = nearer & (z <= o.height) & (z >= 0)
            part = idx[lo:hi]
            np.putmask(part, side, bins[lo:hi] + at)
            if o.height < h:  # the camera looks down onto the lid
                d_out = np.repeat(proj + sq, n)
                lid = nearer & (z > o.height) & (h + d_out * slope <= o.height)
                np.putmask(part, lid, bins[lo:hi] + (at + nb))
                side |= lid
            np.putmask(depth[lo:hi], side, d)


def _pose_xyyaw(p) -> tuple[float, float, float]:
    if hasattr(p, "yaw"):
        return float(p.x), float(p.y), float(p.yaw)
    x, y, yaw = p[:3]
    return float(x), float(y), float(yaw)


class TopDownMap:
    """The arena seen from above, background drawn once so redrawing cars is cheap (teleop
    window, videos). `size` is the image width in pixels; row 0 is the arena's far (y = max)
    side, as a map is read. Cars are drawn with the simulated car's body: the pose is its rear
    axle centre, so the rectangle sits where the collision check puts it."""

    CAR_LENGTH = _CAR.length
    CAR_WIDTH = _CAR.width
    CAR_REAR = _CAR.rear_overhang
    CAR_COLOUR: RGB = (220, 40, 40)
    NOSE_COLOUR: RGB = (255, 230, 60)

    def __init__(self, track: Track, size: int = 670):
        self.track = track
        self.size = size
        aw, ah = track.arena
        border = 0.1
        self.ppm = size / (aw + 2 * border)
        self.border = border
        img = floor_image(track, self.ppm, border).astype(np.float32)
        hgt, wid = img.shape[:2]
        yy, xx = np.mgrid[0:hgt, 0:wid]
        wx = (xx + 0.5) / self.ppm - border
        wy = (yy + 0.5) / self.ppm - border
        for o in track.obstacles:
            rr = np.hypot(wx - o.x, wy - o.y) / o.radius
            inside = rr <= 1.0
            shade = 1.1 - 0.35 * rr[inside]  # lighter centre: reads as a round thing
            img[inside] = np.clip(np.array(o.colour, np.float32) * shade[:, None], 0, 255)
        fence = (wx < 0) | (wx > aw) | (wy < 0) | (wy > ah)
        img[fence] = track.fence_colour
        self._wx, self._wy = wx, wy
        self.background = np.ascontiguousarray(img[::-1].astype(np.uint8))

    def draw(self, poses: Iterable | None = None) -> np.ndarray:
        """A copy of the map with a small oriented rectangle (yellow nose) per pose; poses are
        (x, y, yaw) tuples or anything with .x, .y, .yaw (a CarState)."""
        img = self.background.copy()
        for p in poses or ():
            x, y, yaw = _pose_xyyaw(p)
            self._car(img, x, y, yaw)
        return img

    def _car(self, img: np.ndarray, x: float, y: float, yaw: float) -> None:
        half = math.hypot(self.CAR_LENGTH, self.CAR_WIDTH) + 2 / self.ppm
        lo_c = max(int((x - half + self.border) * self.ppm), 0)
        hi_c = min(int((x + half + self.border) * self.ppm) + 1, img.shape[1])
        lo_r = max(int((y - half + self.border) * self.ppm), 0)
        hi_r = min(int((y + half + self.border) * self.ppm) + 1, img.shape[0])
        if lo_c >= hi_c or lo_r >= hi_r:
            return
        wx = self._wx[lo_r:hi_r, lo_c:hi_c] - x
        wy = self._wy[lo_r:hi_r, lo_c:hi_c] - y
        c, s = math.cos(yaw), math.sin(yaw)
        along = c * wx + s * wy + self.CAR_REAR  # 0 at the back bumper
        across = -s * wx + c * wy
        body = (along >= 0) & (along <= self.CAR_LENGTH) & (np.abs(across) <= self.CAR_WIDTH / 2)
        nose = body & (along >= 0.75 * self.CAR_LENGTH)
        rows = img.shape[0] - 1 - np.arange(lo_r, hi_r)  # the map is flipped vertically
        view = img[rows[:, None], np.arange(lo_c, hi_c)[None, :]]
        view[body] = self.CAR_COLOUR
        view[nose] = self.NOSE_COLOUR
        img[rows[:, None], np.arange(lo_c, hi_c)[None, :]] = view


_last_map: TopDownMap | None = None


def top_down(track: Track, poses: Sequence | None = None, size: int = 670) -> np.ndarray:
    """RGB map of the arena with a car per pose. The background of the last track drawn is
    kept, so calling this every frame for the same track only pays for the cars."""
    global _last_map
    if _last_map is None or _last_map.track is not track or _last_map.size != size:
        _last_map = TopDownMap(track, size)
    return _last_map.draw(poses)
