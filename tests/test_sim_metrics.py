"""The paper's metrics on hand-made trajectories, where the right answer is known, and the plot."""

from __future__ import annotations

import numpy as np
import pytest

from carrt.sim.expert import ScriptedExpert
from carrt.sim.metrics import (
    TrajectoryRecorder,
    compute_metrics,
    format_metrics,
    plot_trajectory,
    run_metrics,
)
from carrt.sim.track import build_track, pose_at
from carrt.sim.world import SimWorld

L = 10.0  # a made-up track length


def _straight_run(seconds, speed=1.0, dt=0.1):
    """Constant speed along a line; progress grows with distance; laps every L metres."""
    t = np.arange(0, seconds + dt / 2, dt)
    progress = speed * t
    x, y = progress, np.zeros_like(t)
    lap = np.zeros(len(t), dtype=bool)
    for k in range(1, int(progress[-1] // L) + 1):
        lap[np.argmax(progress >= k * L)] = True
    return t, x, y, np.full(len(t), speed), progress, lap


def test_completion_ratio_is_the_safe_distance_before_the_first_collision():
    t, x, y, v, progress, lap = _straight_run(10.0)
    collision = np.zeros(len(t), dtype=bool)
    collision[40] = True  # at 4 m
    collision[80] = True  # a second one does not matter
    m = compute_metrics(t, x, y, v, progress, collision, lap, L)
    assert m.completion_ratio == pytest.approx(0.4)
    assert m.collisions == 2 and m.interventions == 0, "a crash is no takeover"
    clean = compute_metrics(t, x, y, v, progress, np.zeros(len(t), bool), lap, L)
    assert clean.completion_ratio == 1.0, "capped at one lap"
    half = compute_metrics(t[:51], x[:51], y[:51], v[:51], progress[:51], None, lap[:51], L)
    assert half.completion_ratio == pytest.approx(0.5), "no collision: as far as it got"


def test_a_takeover_counts_as_an_intervention_and_ends_the_safe_distance():
    t, x, y, v, progress, lap = _straight_run(10.0)
    takeover = np.zeros(len(t), dtype=bool)
    takeover[25:28] = True  # one takeover flagged for three samples
    m = compute_metrics(t, x, y, v, progress, None, lap, L, intervention=takeover)
    assert m.interventions == 1 and m.collisions == 0
    assert m.completion_ratio == pytest.approx(0.25)


def test_lap_times_only_for_complete_collision_free_laps():
    t, x, y, v, progress, lap = _straight_run(35.0, speed=1.0)
    m = compute_metrics(t, x, y, v, progress, None, lap, L)
    assert m.laps == 3
    assert m.lap_times == pytest.approx((10.0, 10.0, 10.0))
    assert m.best_lap == pytest.approx(10.0)
    collision = np.zeros(len(t), dtype=bool)
    collision[150] = True  # in the second lap (10 s .. 20 s)
    m = compute_metrics(t, x, y, v, progress, collision, lap, L)
    assert m.lap_times == pytest.approx((10.0, 10.0)), "lap 2 is dropped"


def test_average_and_top_speed_over_driving_time():
    t = np.arange(0, 10.01, 0.1)
    speed = np.where(t < 5, 1.0, 2.0)
    speed[0] = 0.0
    progress = np.cumsum(speed * 0.1)
    zeros = np.zeros(len(t), dtype=bool)
    m = compute_metrics(t, progress, zeros, speed, progress, zeros, zeros, L)
    assert m.top_speed == 2.0
    assert m.average_speed == pytest.approx(1.5, abs=0.02)
    assert m.driving_time == pytest.approx(10.0)
    assert m.distance == pytest.approx(progress[-1] - progress[0])
    # standing still while being reset does not drag the average down
    resetting = (t > 2) & (t <= 4)
    still = np.where(resetting, 0.0, speed)
    m2 = compute_metrics(t, progress, zeros, still, progress, zeros, zeros, L, resetting=resetting)
    assert m2.driving_time == pytest.approx(8.0)
    assert m2.average_speed == pytest.approx((3 * 1.0 + 5 * 2.0) / 8, abs=0.02)


def test_time_for_five_laps_excludes_reset_time():
    t, x, y, v, progress, lap = _straight_run(60.0, speed=1.0)
    assert lap.sum() == 6
    m = compute_metrics(t, x, y, v, progress, None, lap, L)
    assert m.time_for_laps == pytest.approx(50.0)
    # a crash at 12 s, then 3 s standing while the car is carried back (resetting)
    collision = np.zeros(len(t), dtype=bool)
    collision[120] = True
    resetting = (t > 12.0) & (t <= 15.0)
    m = compute_metrics(t, x, y, v, progress, collision, lap, L, resetting=resetting)
    assert m.time_for_laps == pytest.approx(47.0)
    assert m.collisions == 1 and m.interventions == 0
    short = compute_metrics(t[:300], x[:300], y[:300], v[:300], progress[:300], None, lap[:300], L)
    assert short.time_for_laps is None, "fewer than five laps: no time"
    assert compute_metrics(t, x, y, v, progress, None, lap, L, n_laps=2).time_for_laps == (
        pytest.approx(20.0)
    )
    assert "time for 5 laps 50.0 s (resets excluded)" in format_metrics(m_all := compute_metrics(
        t, x, y, v, progress, None, lap, L))  # fmt: skip
    assert m_all.laps == 6, "six laps driven beside the time for five: the label says five"
    two = compute_metrics(t, x, y, v, progress, None, lap, L, n_laps=2)
    assert "time for 2 laps 20.0 s" in format_metrics(two)


def test_empty_trajectory_is_all_zeros():
    m = compute_metrics([], [], [], [], [], [], [], L)
    assert (m.average_speed, m.completion_ratio, m.laps, m.time_for_laps) == (0.0, 0.0, 0, None)


def test_recorder_with_auto_reset_and_the_plot(tmp_path):
    world = SimWorld("easy", 0)
    expert = ScriptedExpert(world.track, world.params)
    recorder = TrajectoryRecorder()
    recorder.record(world)
    crashed = False
    while world.laps < 1 and world.time < 30:
        steering, throttle = expert.act(world.car)
        if 3.0 < world.time < 6.0 and not crashed:
            steering = 1.0  # swerve right, into the outer fence, once
        info = world.step(0.1, steering, throttle)
        recorder.record(world, info)
        if info.collision:
            crashed = True
            recorder.record(world, info, resetting=True)
            world.reset()
            expert.reset()
    assert crashed and world.laps == 1
    m = run_metrics(world.track, recorder)
    assert m.collisions == 1 and m.laps == 1
    assert 0.0 < m.completion_ratio < 1.0
    assert m.lap_times == (), "the only lap had a crash in it"
    assert "completion" in format_metrics(m)
    out = tmp_path / "run.png"
    a = recorder.arrays()
    plot_trajectory(
        world.track, a["x"], a["y"], a["collision"], out, "easy seed 0", speeds=a["speed"]
    )
    assert out.stat().st_size > 10_000
    bare = tmp_path / "bare.png"
    plot_trajectory(build_track("hard", 3), a["x"], a["y"], a["collision"], bare, "no speeds")
    assert bare.stat().st_size > 10_000


def test_run_metrics_reads_any_log_with_the_columns():
    class Log:
        def __init__(self):
            t, self.x, self.y, self.speed, self.progress, lap = _straight_run(12.0)
            self.t, self.lap = t.tolist(), lap.tolist()
            self.collision = [False] * len(t)

    track = build_track("empty")
    m = run_metrics(track, Log())
    assert m.laps == 1, "lap flags come from the log"
    assert m.completion_ratio == pytest.approx(12.0 / track.length)
    x, _, _ = pose_at(track, 0.0)
    assert x == pytest.approx(3.2)


def test_laps_per_minute_and_mean_lap_from_known_lap_times():
    t, x, y, v, progress, lap = _straight_run(35.0, speed=1.0)  # laps at 10, 20, 30 s
    m = compute_metrics(t, x, y, v, progress, None, lap, L)
    assert m.laps_per_min == pytest.approx(3 / (35.0 / 60.0))
    assert m.lap_time_mean == pytest.approx(10.0)
    # a crash in lap 2 and 3 s of resetting: lap 2 is no clean lap, and minutes of driving are
    # what laps are counted against (standing crashed and resetting excluded)
    collision = np.zeros(len(t), dtype=bool)
    collision[150] = True
    resetting = (t > 15.0) & (t <= 18.0)
    m = compute_metrics(t, x, y, v, progress, collision, lap, L, resetting=resetting)
    assert m.driving_time == pytest.approx(35.0 - 0.1 - 3.0)
    assert m.laps_per_min == pytest.approx(3 / ((35.0 - 3.1) / 60.0))
    assert m.lap_times == pytest.approx((10.0, 10.0)) and m.lap_time_mean == pytest.approx(10.0)
    uneven = lap.copy()
    uneven[[100, 200]] = False
    uneven[[80, 240]] = True  # laps of 8, 16 and 6 s
    m = compute_metrics(t, x, y, v, progress, None, uneven, L)
    assert m.lap_time_mean == pytest.approx(10.0) and m.best_lap == pytest.approx(6.0)
    none = compute_metrics(t[:50], x[:50], y[:50], v[:50], progress[:50], None, lap[:50], L)
    assert (none.laps_per_min, none.lap_time_mean) == (0.0, None)


def test_progress_per_metre_is_one_on_the_centerline():
    track = build_track("hard", 3)
    s = np.arange(0.0, 1.5 * track.length, 0.05)  # 1.5 laps along the centerline at 1 m/s
    x, y = np.array([pose_at(track, si)[:2] for si in s]).T
    t = s.copy()
    m = compute_metrics(t, x, y, np.ones(len(t)), s, None, None, track.length)
    assert m.progress_per_metre == pytest.approx(1.0, abs=0.01)
    assert m.along_track == pytest.approx(s[-1])


def test_progress_per_metre_falls_with_a_loop_across_the_infield():
    """5 m along a straight track, a full loop of radius 1 m (2π m driven, no net progress),
    5 m more: 10 m of progress for 10 + 2π m driven. Progress is the position along the track
    (here x), as the simulator's is."""
    dt, ds = 0.01, 0.01
    first = np.arange(0.0, 5.0, ds)
    angle = np.arange(0.0, 2 * np.pi, ds)  # the loop starts at (5, 0) heading +x, turning left
    loop_x, loop_y = 5.0 + np.sin(angle), 1.0 - np.cos(angle)
    last = np.arange(5.0, 10.0 + ds / 2, ds)
    x = np.concatenate([first, loop_x, last])
    y = np.concatenate([np.zeros_like(first), loop_y, np.zeros_like(last)])
    t = np.arange(len(x)) * dt
    m = compute_metrics(t, x, y, np.ones(len(t)), x, None, None, 100.0)
    assert m.distance == pytest.approx(10.0 + 2 * np.pi, rel=1e-3)
    assert m.progress_per_metre == pytest.approx(10.0 / (10.0 + 2 * np.pi), rel=1e-3)
    n = len(first)
    before = compute_metrics(t[:n], x[:n], y[:n], np.ones(n), x[:n], None, None, 100.0)
    assert before.progress_per_metre == pytest.approx(1.0), "on the line before the loop"


def test_a_resets_jump_is_neither_distance_nor_progress():
    t, x, y, v, progress, lap = _straight_run(20.0)
    collision = np.zeros(len(t), dtype=bool)
    collision[50] = True
    resetting = (t > 5.0) & (t <= 6.0)
    jumped = progress + np.where(t > 6.0, 2.0, 0.0)  # the car set down 2 m further on
    hold = np.where(t > 5.0, np.where(t > 6.0, jumped, jumped[50]), jumped)
    m = compute_metrics(t, hold, y, v, hold, collision, lap, L, resetting=resetting)
    assert m.along_track == pytest.approx(m.distance)
    assert m.progress_per_metre == pytest.approx(1.0)
    back = compute_metrics(t, x, y, v, L - progress, None, None, L)  # driving the wrong way
    assert back.progress_per_metre == pytest.approx(-1.0)


def test_the_racing_numbers_are_in_the_summary_and_the_saved_dict():
    import dataclasses

    t, x, y, v, progress, lap = _straight_run(35.0)
    m = compute_metrics(t, x, y, v, progress, None, lap, L)
    racing = next(line for line in format_metrics(m).splitlines() if line.startswith("racing"))
    assert "5.14 laps/min of driving, mean lap 10.00 s, progress 1.00 m per m driven" in racing
    saved = dataclasses.asdict(m)  # what `carrt drive --sim --out` writes as sim_metrics.json
    assert saved["laps_per_min"] == m.laps_per_min and saved["progress_per_metre"] == 1.0
    assert saved["lap_time_mean"] == pytest.approx(10.0)


def test_the_saved_runs_table_of_carrt_report_shows_the_racing_numbers():
    from carrt.sim.runs import render_sim_table

    t, x, y, v, progress, lap = _straight_run(35.0)
    m = compute_metrics(t, x, y, v, progress, None, lap, L)
    header, row = render_sim_table([("run", m)]).splitlines()
    assert "completion prog/m best lap s laps/min laps collisions" in " ".join(header.split())
    # completion, progress per metre, best lap, laps per minute, laps, collisions, 5 laps
    assert row.split()[3:] == ["100.0%", "1.00", "10.00", "5.14", "3", "0", "-"]
