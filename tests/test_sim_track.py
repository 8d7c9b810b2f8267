"""The simulator's track: one fixed circuit that fits the paper's arena, seeded obstacle layouts,
and the geometry helpers the renderer, the world and the expert lean on."""

from __future__ import annotations

import colorsys
import math

import numpy as np
import pytest

from carrt.sim.track import (
    LAYOUTS,
    boundary_polylines,
    build_track,
    geometry,
    pose_at,
    project,
    start_pose,
)
from carrt.sim.types import ARENA_H, ARENA_W


def _wrap_ds(a, length):
    return (np.asarray(a) + length / 2) % length - length / 2


@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_same_layout_and_seed_give_the_identical_track(layout):
    a, b = build_track(layout, 3), build_track(layout, 3)
    assert np.array_equal(a.centerline, b.centerline)
    assert np.array_equal(a.racing_line, b.racing_line)
    assert a.obstacles == b.obstacles
    assert (a.name, a.seed, a.length) == (layout, 3, b.length)


def test_layouts_have_their_obstacle_counts_and_seeds_move_them():
    for layout, spec in LAYOUTS.items():
        count = spec.obstacles
        low, high = count if isinstance(count, tuple) else (count, count)
        for seed in range(5):
            assert low <= len(build_track(layout, seed).obstacles) <= high
    counts = {name: spec.obstacles for name, spec in LAYOUTS.items()}
    assert counts == {"empty": 0, "easy": 2, "hard": 8, "mixed": (4, 10)}
    assert build_track("hard", 0).obstacles != build_track("hard", 1).obstacles
    assert build_track("easy", 0).obstacles != build_track("hard", 0).obstacles[:2]


def test_unknown_layout_names_the_valid_ones():
    with pytest.raises(ValueError, match=r"empty.*easy.*hard"):
        build_track("medium")


def test_one_circuit_for_every_layout():
    base = build_track("empty", 0)
    for layout in LAYOUTS:
        other = build_track(layout, 7)
        assert np.array_equal(other.centerline, base.centerline)
        assert other.length == base.length
    assert not base.centerline.flags.writeable, "shared arrays are read-only"


def test_track_is_a_closed_evenly_sampled_curve_of_the_stated_length():
    track = build_track("empty")
    pts = track.centerline
    steps = np.hypot(*np.diff(np.vstack([pts, pts[:1]]), axis=0).T)
    assert steps.min() > 0.015 and steps.max() < 0.025, "sampled every ~2 cm, closing segment too"
    assert track.length == pytest.approx(steps.sum())
    assert 10.0 < track.length < 16.0
    assert track.width == pytest.approx(0.8)


def test_track_fits_the_fenced_arena_with_clearance():
    track = build_track("empty")
    assert track.arena == (ARENA_W, ARENA_H) == (6.7, 3.8)
    for line in boundary_polylines(track):
        assert line[:, 0].min() >= 0.3 and line[:, 0].max() <= ARENA_W - 0.3
        assert line[:, 1].min() >= 0.3 and line[:, 1].max() <= ARENA_H - 0.3


def test_track_never_runs_into_itself():
    track = build_track("empty")
    pts, length = track.centerline, track.length
    s = geometry(pts).cum[:-1]
    dist = np.hypot(*(pts[:, None, :] - pts[None, :, :]).transpose(2, 0, 1))
    apart = np.abs(_wrap_ds(s[:, None] - s[None, :], length)) > 1.5
    assert dist[apart].min() > track.width + 0.2, "distinct parts keep a gap between markings"


def test_track_has_a_hairpin_sweepers_and_straights():
    track = build_track("empty")
    geo = geometry(track.centerline)
    kappa = np.abs(geo.curvature)
    assert kappa.max() >= 1 / 0.6, "a sharp corner somewhere"
    # a U-turn: the heading turns through ~180° within 2.5 m
    heading = np.unwrap(geo.vertex_heading)
    window = round(2.5 / (track.length / len(heading)))
    turned = np.abs(
        np.concatenate([heading, heading + 2 * np.pi])[window:][: len(heading)] - heading
    )
    assert np.degrees(turned.max()) >= 175
    # straights: at least 1.5 m without curvature, twice
    flat = kappa < 0.02
    runs, count = [], 0
    for f in np.concatenate([flat, flat]):
        count = count + 1 if f else 0
        runs.append(count)
    assert max(runs) * track.length / len(flat) > 3.0
    # sweepers: long stretches of moderate curvature
    moderate = (kappa > 0.5) & (kappa < 1.2)
    assert moderate.sum() * track.length / len(kappa) > 2.0


def test_racing_line_stays_inside_and_cuts_the_corners():
    track = build_track("empty")
    _, lat, _ = project(track, track.racing_line[:, 0], track.racing_line[:, 1])
    assert np.abs(lat).max() <= track.width / 2 - 0.15 + 1e-6
    assert np.abs(lat).max() > 0.2, "it uses the width"
    centre = geometry(track.centerline).curvature
    race = geometry(track.racing_line).curvature
    spacing = track.length / len(centre)
    assert np.sum(race**2) * spacing < 0.6 * np.sum(centre**2) * spacing, "it bends less overall"
    assert np.abs(race).max() <= np.abs(centre).max() + 0.05


@pytest.mark.parametrize("seed", range(6))
def test_obstacles_are_cylinders_placed_by_the_rules(seed):
    track = build_track("hard", seed)
    half = track.width / 2
    s_list = []
    for ob in track.obstacles:
        assert 0.08 <= ob.radius <= 0.12 and 0.2 <= ob.height <= 0.3
        s, lat, _ = project(track, ob.x, ob.y)
        s_list.append(s)
        assert abs(lat) + ob.radius <= half + 1e-9, "the whole cylinder is on the track"
        left_gap = half - (lat + ob.radius)
        right_gap = half + (lat - ob.radius)
        assert max(left_gap, right_gap) >= 0.35, "a passable gap on one side"
        assert s >= 1.5, "none right after the start line"
        r, g, b = (c / 255 for c in ob.colour)
        hue, sat, val = colorsys.rgb_to_hsv(r, g, b)
        assert sat >= 0.7 and val >= 0.65, f"saturated colour, got {ob.colour}"
        assert not 0.09 < hue < 0.18, "not the centre marking's yellow"
    s_sorted = np.sort(s_list)
    gaps = np.diff(np.append(s_sorted, s_sorted[0] + track.length))
    assert gaps.min() >= 1.2 - 1e-6, "spaced along the track, across the start line too"


def test_project_and_pose_at_round_trip():
    track = build_track("hard", 0)
    rng = np.random.default_rng(1)
    s = rng.uniform(0, track.length, 500)
    lat = rng.uniform(-0.38, 0.38, 500)
    x, y, yaw = pose_at(track, s, lat)
    s2, lat2, heading = project(track, x, y)
    assert np.abs(_wrap_ds(s2 - s, track.length)).max() < 1e-3
    assert np.abs(lat2 - lat).max() < 1e-3
    assert np.abs(_wrap_ds(heading - yaw, 2 * math.pi)).max() < 1e-6
    # scalars give floats, and s wraps
    xs, ys, _ = pose_at(track, float(s[0]) + 2 * track.length, float(lat[0]))
    assert isinstance(xs, float) and (xs, ys) == pytest.approx((x[0], y[0]))
    s_one, lat_one, _ = project(track, xs, ys)
    assert isinstance(s_one, float) and lat_one == pytest.approx(lat[0], abs=1e-3)
    # shapes are kept
    grid_s, _, _ = project(track, x.reshape(20, 25), y.reshape(20, 25))
    assert grid_s.shape == (20, 25)


def test_heading_follows_the_track_and_lateral_is_positive_to_the_left():
    track = build_track("empty")
    x0, y0, yaw0 = pose_at(track, 1.0)
    x1, y1, _ = pose_at(track, 1.05)
    assert math.atan2(y1 - y0, x1 - x0) == pytest.approx(yaw0, abs=1e-3)
    left = (x0 - 0.2 * math.sin(yaw0), y0 + 0.2 * math.cos(yaw0))
    assert project(track, *left)[1] == pytest.approx(0.2, abs=1e-6)


def test_boundaries_are_at_half_the_width():
    track = build_track("empty")
    left, right = boundary_polylines(track)
    assert left.shape == right.shape == track.centerline.shape
    assert project(track, left[:, 0], left[:, 1])[1] == pytest.approx(track.width / 2, abs=1e-3)
    assert project(track, right[:, 0], right[:, 1])[1] == pytest.approx(-track.width / 2, abs=1e-3)


def test_start_pose_is_on_the_start_line_heading_along_the_track():
    track = build_track("hard", 2)
    x, y, yaw = start_pose(track)
    s, lat, heading = project(track, x, y)
    assert min(s, track.length - s) < 1e-6 and abs(lat) < 1e-9 and heading == pytest.approx(yaw)
    for ob in track.obstacles:  # the car starting there has room: none just ahead or behind
        s_ob = project(track, ob.x, ob.y)[0]
        assert 1.5 <= s_ob <= track.length - 0.3
        assert math.hypot(ob.x - x, ob.y - y) > 0.3


def test_inserting_a_layout_moves_no_other_layouts_obstacles(monkeypatch):
    """Placements come from each layout's own stream, not its position in the list: the
    held-out evaluation placements must not move when someone adds a layout."""
    from carrt import layouts
    from carrt.sim import track

    def where(layout, seed):
        return [(o.x, o.y, o.radius, o.colour) for o in track.build_track(layout, seed).obstacles]

    before = {seed: where("hard", seed) for seed in (100, 104)}
    grown = {"new": layouts.Layout(3, stream=99), **layouts.LAYOUTS}
    monkeypatch.setattr(track, "LAYOUTS", grown)
    assert list(grown).index("hard") != list(layouts.LAYOUTS).index("hard")
    assert {seed: where("hard", seed) for seed in (100, 104)} == before
    streams = [layout.stream for layout in layouts.LAYOUTS.values()]
    assert len(set(streams)) == len(streams), "each layout has a stream of its own"
