"""The simulated camera: what it must show (fence, floor, markings, obstacles) and how fast.

Scenes are built by hand where a test needs exact geometry (a circle track around the arena's
centre, an obstacle at a known spot); the real circuit is used where the markings matter.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from carrt.sim.render import Renderer, TopDownMap, top_down
from carrt.sim.types import ARENA_H, ARENA_W, CameraParams, Obstacle, Track

CX, CY = ARENA_W / 2, ARENA_H / 2
RED = (210, 30, 30)


def circle_track(radius: float = 1.5, obstacles: tuple[Obstacle, ...] = ()) -> Track:
    a = np.linspace(0.0, 2 * math.pi, 600, endpoint=False)
    c = np.stack([CX + radius * np.cos(a), CY + radius * np.sin(a)], axis=1)
    return Track("empty", 0, c, 0.6, c.copy(), obstacles, length=2 * math.pi * radius)


def like(img: np.ndarray, colour, lo: float = 0.55, hi: float = 1.1, tol: float = 8) -> np.ndarray:
    """Mask of pixels that are `colour` scaled by a shading factor in [lo, hi] (± tol levels)."""
    px = img.astype(float)
    col = np.asarray(colour, float)
    k = (px @ col) / (col @ col)  # least-squares shade per pixel
    err = np.abs(px - k[..., None] * col).max(axis=-1)
    return (k >= lo) & (k <= hi) & (err <= tol)


@pytest.fixture(scope="module")
def plain():
    return Renderer(circle_track())


def test_shape_dtype_and_determinism(plain):
    a = plain.render(CX, CY, 0.3)
    assert a.shape == (96, 96, 3) and a.dtype == np.uint8 and a.flags.c_contiguous
    plain.render(1.0, 1.0, 2.0)  # another pose in between must leave no trace
    assert np.array_equal(a, plain.render(CX, CY, 0.3))
    assert np.array_equal(a, Renderer(circle_track()).render(CX, CY, 0.3))


def test_other_camera_sizes():
    cam = CameraParams(width=64, height=48, fov_deg=80.0, pitch_deg=10.0, height_m=0.2)
    img = Renderer(circle_track(), cam).render(CX, CY, 0.0)
    assert img.shape == (48, 64, 3)


def test_fence_close_ahead_fills_centre(plain):
    track = plain.track
    img = plain.render(ARENA_W - 0.2, CY, 0.0)  # camera 0.15 m from the east fence
    centre = img[40:56, 40:56]
    assert like(centre, track.fence_colour).all()
    # along the centre column, top to bottom: fence, darker base stripe, floor
    col = img[:, 48]
    fence = like(col, track.fence_colour, lo=0.8)
    base = like(col, track.fence_colour, lo=0.5, hi=0.8)
    floor = like(col, track.floor_colour, lo=0.85, hi=1.15)
    assert fence[0] and base.any() and floor[-1]
    assert np.flatnonzero(fence).max() < np.flatnonzero(base).min()
    assert np.flatnonzero(base).max() < np.flatnonzero(floor).min()


def test_fence_edges_where_a_pinhole_puts_them(plain):
    cam, track = plain.camera, plain.track
    dist = 1.0
    img = plain.render(ARENA_W - dist - cam.forward_m, CY, 0.0)
    f = (cam.width / 2) / math.tan(math.radians(cam.fov_deg / 2))

    def row(elevation: float) -> float:  # image row (continuous) of a ray at this elevation
        return cam.height / 2 - f * math.tan(elevation + math.radians(cam.pitch_deg))

    top = row(math.atan((track.fence_height - cam.height_m) / dist))
    foot = row(math.atan(-cam.height_m / dist))
    col = img[:, 48]
    wall = like(col, track.fence_colour, lo=0.5)
    rows = np.flatnonzero(wall)
    assert abs(rows.min() - top) <= 1.0 and abs(rows.max() + 1 - foot) <= 1.0
    assert np.array_equal(col[0], plain.sky_colour)


def test_far_from_fence_shows_floor(plain):
    img = plain.render(CX, CY, 0.0)  # inside the circle track, nothing within 1.4 m
    assert like(img[40:96, 30:66], plain.track.floor_colour, lo=0.85, hi=1.15).all()
    assert not like(img[40:96], plain.track.fence_colour, lo=0.6).any()


def test_obstacle_ahead_in_centre_and_not_behind():
    cam = CameraParams()
    x0 = CX - cam.forward_m - 0.5  # obstacle 0.5 m straight ahead of the camera
    track = circle_track(obstacles=(Obstacle(CX, CY, 0.08, 0.25, RED),))
    r = Renderer(track, cam)
    img = r.render(x0, CY, 0.0)
    red = like(img, RED, lo=0.45)
    assert red.sum() > 100
    rows, cols = np.nonzero(red)
    assert abs(cols.mean() - 47.5) < 2  # centred left to right
    assert red[22:44, 44:52].all()  # it covers the centre, just above where the floor is aimed
    # its sides are shaded darker than its middle: it reads as round
    row = img[rows.min() + 5].astype(float)
    inside = np.flatnonzero(red[rows.min() + 5])
    assert row[inside[len(inside) // 2], 0] > row[inside[0], 0] + 20
    behind = r.render(x0, CY, math.pi)
    assert not like(behind, RED, lo=0.45).any()


def test_short_obstacle_shows_its_lid():
    cam = CameraParams()
    green = (30, 180, 60)
    track = circle_track(obstacles=(Obstacle(CX, CY, 0.1, 0.06, green),))
    img = Renderer(track, cam).render(CX - cam.forward_m - 0.4, CY, 0.0)
    side = like(img, green, lo=0.45, hi=1.02, tol=6)
    lid = np.all(np.abs(img.astype(int) - np.minimum(np.array(green) * 1.15 + 15, 255)) <= 1, -1)
    assert side.any() and lid.any()
    assert np.nonzero(lid)[0].mean() < np.nonzero(side)[0].mean()  # lid above the side


def test_boundary_markings_left_and_right_on_the_centreline():
    track = circle_track(radius=1.5)
    img = Renderer(track).render(CX, CY - 1.5, 0.0)  # bottom of the circle, facing along it
    white = np.all(img >= 243, axis=-1)
    assert white[:, :40].sum() > 5 and white[:, 56:].sum() > 5
    yellow = like(img, track.centre_marking_colour, lo=0.9, tol=12)
    assert yellow[48:, 40:56].any()  # the dashed centre line runs up the middle


def test_real_track_markings():
    from carrt.sim.track import build_track, pose_at

    track = build_track("empty", 0)
    r = Renderer(track)
    img = r.render(*pose_at(track, 0.3))  # start straight
    white = np.all(img >= 243, axis=-1)
    assert white[:, :40].sum() > 5 and white[:, 56:].sum() > 5


def test_moving_changes_the_image(plain):
    a = plain.render(CX, CY - 1.5, 0.0)
    assert not np.array_equal(a, plain.render(CX + 0.05, CY - 1.5, 0.0))
    assert not np.array_equal(a, plain.render(CX, CY - 1.5, 0.05))


def test_pose_on_or_past_the_fence_does_not_crash(plain):
    for x, y in [(0.0, 0.0), (-1.0, CY), (ARENA_W + 2, ARENA_H + 2), (CX, ARENA_H)]:
        img = plain.render(x, y, 1.0)
        assert img.shape == (96, 96, 3)


def test_renders_per_second_sanity():
    track = circle_track(
        obstacles=tuple(
            Obstacle(CX + 1.5 * math.cos(a), CY + 1.5 * math.sin(a), 0.1, 0.25, RED)
            for a in np.linspace(0, 2 * math.pi, 8, endpoint=False)
        )
    )
    r = Renderer(track)
    poses = [(CX + 1.5 * math.cos(a), CY + 1.5 * math.sin(a), a + 1.6) for a in range(200)]
    start = time.perf_counter()
    for p in poses:
        r.render(*p)
    rate = len(poses) / (time.perf_counter() - start)
    assert rate >= 200, f"{rate:.0f} renders/s"  # the real figure is in bench/bench_sim.py


def test_top_down_map():
    track = circle_track(obstacles=(Obstacle(CX, CY, 0.1, 0.25, RED),))
    img = top_down(track, poses=[(CX, CY - 1.5, 0.0)], size=400)
    assert img.ndim == 3 and img.shape[1] == 400 and img.dtype == np.uint8
    m = TopDownMap(track, size=400)
    car = np.all(img == m.CAR_COLOUR, axis=-1)
    rows, cols = np.nonzero(car)
    # the car sits low in the map (y small → bottom rows), centred left to right
    assert rows.mean() > img.shape[0] * 0.7 and abs(cols.mean() - 200) < 10
    assert like(img, RED, lo=0.6, hi=1.15, tol=10).sum() > 50
    assert np.array_equal(img, m.draw([(CX, CY - 1.5, 0.0)]))
    assert not np.all(m.draw() == m.CAR_COLOUR, axis=-1).any()


def test_a_mirrored_scene_renders_as_the_mirrored_image():
    """training/augment.mirror_batch flips frames left↔right: that is only a frame the car could
    have seen if the camera is left-right symmetric. An obstacle 0.25 m left of the heading line
    and its mirror 0.25 m right, seen from the arena's centre line (fences equally far): the
    obstacle's pixels in one image are the other's, flipped."""
    masks = []
    for side in (1.0, -1.0):
        track = circle_track(obstacles=(Obstacle(CX + 0.6, CY + side * 0.25, 0.12, 0.25, RED),))
        masks.append(like(Renderer(track).render(CX - 0.3, CY, 0.0), RED))
    left, right = masks
    assert left.sum() > 100 and not left[:, 48:].any(), "an obstacle on the left is on the left"
    assert np.array_equal(left, right[:, ::-1]), f"{(left != right[:, ::-1]).sum()} pixels differ"
