"""`carrt report`: lap times exclude the reset after a collision; speeds and counts are right."""

from __future__ import annotations

import argparse
import json

import pytest
from episode_factory import make_step, write_episode

from carrt import report
from carrt.episodes import read_episode
from carrt.interfaces import Mode

D, M, A, E = Mode.DISARMED, Mode.MANUAL, Mode.AUTO, Mode.ESTOP


def build(segments, *, t0=1000.0, **marks):
    """Steps from (count, mode, speed) segments; marks: flag name -> step indices."""
    steps, i = [], 0
    for count, mode, speed in segments:
        for _ in range(count):
            flags = {name: i in idx for name, idx in marks.items()}
            steps.append(make_step(i, t0=t0, mode=mode, speed_mps=speed, noise=False, **flags))
            i += 1
    return steps


def trial():
    """Lap 1 has a collision (e-stop at 41) and a 3 s reset (ESTOP, then DISARMED, re-arm at 71)."""
    steps = build(
        [
            (5, D, 0.0),
            (6, M, 1.0),
            (30, A, 2.0),
            (10, E, 0.0),
            (20, D, 0.0),
            (30, M, 1.0),
            (50, A, 2.0),
            (5, M, 1.0),
        ],
        lap={10, 100, 150},
        override={20, 30},
        estop=set(range(41, 51)),
        collision={41},
    )
    steps[120].speed_mps = 2.4
    return steps


def test_lap_time_excludes_reset_and_averages_are_over_driving(tmp_path):
    ep = read_episode(write_episode(tmp_path, trial()))
    r = report.run_metrics("trial", [ep])
    assert r["laps_s"] == pytest.approx([9.0 - 3.0, 5.0])
    assert r["laps_total_s"] == pytest.approx(11.0) and r["lap_mean_s"] == pytest.approx(5.5)
    assert r["reset_excluded_s"] == pytest.approx(3.0)
    driving = 41 + 80  # MANUAL steps at 1 m/s, AUTO steps at 2 m/s (one at 2.4)
    assert r["avg_speed_mps"] == pytest.approx((41 * 1.0 + 80 * 2.0 + 0.4) / driving)
    assert r["top_speed_mps"] == pytest.approx(2.4)
    assert r["interventions"] == 2 and r["estops"] == 1 and r["collisions"] == 1
    assert r["frames"] == 156 and r["notes"] == []
    assert r["driving_s"] == pytest.approx(12.0)  # 121 driving steps; the last ends the episode


def test_a_trial_across_episodes_carries_the_reset_and_skips_the_gap(tmp_path):
    first = write_episode(
        tmp_path / "a", build([(10, M, 1.0)], lap={2}), reason="collision"
    )  # the car hit something at step 9: the episode ended, the car was reset
    second = write_episode(tmp_path / "b", build([(10, D, 0.0), (10, M, 1.0)], t0=2000.0, lap={15}))
    eps = [read_episode(first), read_episode(second)]
    r = report.run_metrics("trial", eps)
    assert r["laps_s"] == pytest.approx([0.7 + 0.5])  # 2->9 in the first, re-arm 10->15 after
    assert r["reset_excluded_s"] == pytest.approx(1.0)
    assert r["collisions"] == 1
    assert any("spans the end of" in note for note in r["notes"])


def test_no_lap_marks_means_no_lap_times(tmp_path):
    ep = read_episode(write_episode(tmp_path, build([(20, M, 1.5)])))
    r = report.run_metrics("x", [ep])
    assert r["laps_s"] == [] and r["laps_total_s"] is None and r["lap_mean_s"] is None
    assert "no lap marks" in r["notes"][0]
    assert "no lap marks" in report.render_table([r])
    one = report.run_metrics(
        "y", [read_episode(write_episode(tmp_path, build([(5, M, 1)], lap={2})))]
    )
    assert one["laps_s"] == [] and "one lap mark" in one["notes"][0]


def test_cli_table_json_and_per_episode(tmp_path, capsys):
    write_episode(tmp_path / "eps", trial())
    write_episode(tmp_path / "eps", build([(20, M, 1.5)]))
    parser = argparse.ArgumentParser(prog="carrt")
    report.add_parser(parser.add_subparsers(dest="command", required=True))

    out_json = tmp_path / "r.json"
    args = parser.parse_args(["report", str(tmp_path / "eps"), "--json", str(out_json)])
    assert args.func(args) == 0
    text = capsys.readouterr().out
    assert "lap times 6.00, 5.00 s; reset time excluded 3.0 s" in text
    runs = json.loads(out_json.read_text())["runs"]
    assert len(runs) == 1 and runs[0]["frames"] == 176 and len(runs[0]["episodes"]) == 2

    args = parser.parse_args(["report", str(tmp_path / "eps"), "--per-episode"])
    assert args.func(args) == 0
    text = capsys.readouterr().out
    assert "no lap marks" in text and text.count("\n") >= 5


def test_laps_per_minute_are_the_timed_laps_over_the_minutes_of_driving(tmp_path):
    ep = read_episode(write_episode(tmp_path, trial()))
    r = report.run_metrics("trial", [ep])
    assert r["laps_per_min"] == pytest.approx(2 / (12.0 / 60.0))  # 2 laps in 12 s of driving
    header, _, row = report.render_table([r]).splitlines()[:3]
    assert header.split()[-1] == "laps/min" and row.split()[-1] == "10.00"
    unmarked = report.run_metrics("x", [read_episode(write_episode(tmp_path, build([(20, M, 1)])))])
    assert unmarked["laps_per_min"] == 0.0
    parked = report.run_metrics("p", [read_episode(write_episode(tmp_path, build([(9, D, 0)])))])
    assert parked["laps_per_min"] is None
    assert report.render_table([parked]).splitlines()[2].split()[-1] == "-"


def test_two_drives_in_one_folder_are_two_trials_not_one(tmp_path):
    """Each drive (session) of the simulator ends in a collision; its laps never run on into the
    next drive's, whatever placement it drove (the 2.80 s lap on a 13 m track of issue 68)."""
    from episode_factory import metadata

    def drive(name, session, seed, t0):
        meta = {**metadata(), "session_id": session, "sim": {"layout": "hard", "track_seed": seed}}
        steps = build([(10, M, 1.0)], t0=t0, lap={2, 8})
        return read_episode(write_episode(tmp_path / name, steps, reason="collision", meta=meta))

    eps = [drive("a", "s1", 200, 1000.0), drive("b", "s2", 201, 2000.0)]
    r = report.run_metrics("folder", eps)
    assert r["laps_s"] == pytest.approx([0.6, 0.6]), "one lap in each drive, none between them"
    assert not any("spans the end of" in note for note in r["notes"])
    same = [drive("c", "s3", 200, 3000.0), drive("d", "s3", 200, 4000.0)]
    assert report.run_metrics("one drive", same)["laps_s"] == pytest.approx([0.6, 0.1 + 0.2, 0.6])


def test_a_simulator_drives_laps_are_the_same_in_its_metrics_and_in_its_episodes(tmp_path):
    """The demo printed two tables whose first laps disagreed (8.40 against 7.80 s): the
    simulator's metrics timed the first lap from the session's start, seconds before the car
    was armed; the episode starts when it is. Both are timed from the first driving tick."""
    from e2e_rig import CliRun

    from carrt.shipped import SHIPPED_MODELS

    code = CliRun(
        ["drive", "--sim", "--autopilot", "--model", str(SHIPPED_MODELS["demo"]), "--record",
         "--layout", "hard", "--track-seed", "101", "--duration", "20", "--out", str(tmp_path)]
    ).result(timeout_s=120)  # fmt: skip
    assert code == 0
    simulated = json.loads((tmp_path / "sim_metrics.json").read_text())["lap_times"]
    recorded = report.build_report([str(tmp_path)])[0]["laps_s"]
    assert len(simulated) >= 2, simulated
    assert recorded == pytest.approx(simulated, abs=0.051), (recorded, simulated)
