"""The simulator through the real commands: the full stack over the pty in real time, and the
same loop on the simulated clock (expert recording, autopilot with auto-reset)."""

from __future__ import annotations

import json
import time

import numpy as np
from e2e_rig import CliRun, keyboard_teleop
from onnx_models import build_policy

from carrt.episodes.reader import list_episodes, read_episode
from carrt.interfaces import Mode


def test_realtime_stack_drives_a_lap_through_the_pty_without_a_trip(tmp_path, capsys):
    out = tmp_path / "run"
    code = CliRun(
        ["teleop", "--sim", "--expert", "auto", "--realtime", "--layout", "empty",
         "--laps", "1", "--episodes", "1", "--out", str(out), "--duration", "60"]
    ).result(timeout_s=90)  # fmt: skip
    assert code == 0
    text = capsys.readouterr().out
    assert "virtual board on" in text, "real time goes through the pty"
    assert "FAILSAFE" not in text and "failsafe" not in text, text
    metrics = json.loads((out / "sim_metrics.json").read_text())
    assert metrics["laps"] >= 1
    assert metrics["collisions"] == 0
    assert metrics["completion_ratio"] == 1.0


def test_expert_recording_on_the_simulated_clock(tmp_path):
    out = tmp_path / "expert"
    start = time.monotonic()
    code = CliRun(
        ["teleop", "--sim", "--expert", "auto", "--record", "--layout", "easy",
         "--episodes", "2", "--laps", "1", "--out", str(out), "--duration", "300"]
    ).result(timeout_s=120)  # fmt: skip
    wall = time.monotonic() - start
    assert code == 0
    episodes = [read_episode(p) for p in list_episodes(out)]
    assert len(episodes) == 2
    simulated = sum(ep.duration_s for ep in episodes)
    # a generous sanity bound (the speed is measured in make bench): faster than real time
    assert simulated > wall, f"{simulated:.0f} s simulated in {wall:.0f} s of wall time"
    for ep in episodes:
        steps = ep.steps
        assert ep.end_reason == "disarmed" and ep.collision.sum() == 0
        assert (steps["mode"][:-1] == Mode.MANUAL).all()  # the last step is the disarm
        assert steps["speed_mps"].max() > 1.5
        noisy = steps["noise"].astype(bool)
        assert 0.2 < noisy.mean() < 0.8, "noise on about half of the time"
        manual = steps["mode"] == Mode.MANUAL
        delta = steps["executed_action"] - steps["human_action"]
        assert np.abs(delta[manual & ~noisy]).max() < 1e-6
        assert np.abs(delta[manual & noisy]).max() <= 0.3 + 1e-6
        assert ep.meta["sim"]["layout"] == "easy"
        # the pilot marks the line at the standing start and again when the lap is done
        assert steps["lap"].sum() == 2 and steps["lap"][0] and steps["lap"][-2:].any()
        # the camera saw the track: not a blank image
        assert ep.frames[len(ep.frames) // 2].std() > 5


def test_autopilot_resets_after_collisions_and_labels_them(tmp_path, capsys):
    # A policy that always steers hard right at full throttle: it will hit the fence.
    model = build_policy(tmp_path / "crash.onnx", steering=0.0, throttle=(1.0, 0.0))
    out = tmp_path / "auto"
    code = CliRun(
        ["drive", "--sim", "--autopilot", "--model", str(model), "--record", "--layout", "easy",
         "--episodes", "2", "--out", str(out), "--duration", "120",
         "--plot", str(tmp_path / "traj.png")]
    ).result(timeout_s=120)  # fmt: skip
    assert code == 0
    episodes = [read_episode(p) for p in list_episodes(out)]
    assert len(episodes) == 2
    for ep in episodes:
        assert ep.end_reason == "collision"
        assert ep.steps["collision"][-1]
        assert ep.collision[-1] == 1 and ep.collision[0] == 0
        assert (ep.steps["mode"][5:-1] == Mode.AUTO).all()
    metrics = json.loads((out / "sim_metrics.json").read_text())
    assert metrics["collisions"] == 2
    assert 0.0 <= metrics["completion_ratio"] < 1.0
    assert (tmp_path / "traj.png").stat().st_size > 1000
    assert "completion" in capsys.readouterr().out
    (run_png,) = (out / "sim-runs").glob("*.png")
    assert run_png.stat().st_size > 1000, "every saved run has its trajectory plot"

    from carrt.cli import main

    assert main(["report", str(out)]) == 0
    report = capsys.readouterr().out
    assert "simulation" in report and "completion" in report
    row = next(line for line in report.splitlines() if line.startswith(run_png.stem[:20]))
    assert row.split()[-2] == "2", "two collisions in the simulation table"
    assert "interv" in report and "e-stop" in report, "and the real-car table from the episodes"


def _autopilot_steps(tmp_path, name: str, *settings: str) -> dict:
    """A gentle constant policy on the empty layout, recorded for 20 simulated s."""
    model = build_policy(tmp_path / f"{name}.onnx", steering=0.0, throttle=(0.3, 0.0))
    out = tmp_path / name
    code = CliRun(
        ["drive", "--sim", "--autopilot", "--model", str(model), "--record", "--layout", "empty",
         "--out", str(out), "--duration", "20", "--set", "noise.period_s=2.0", *settings]
    ).result(timeout_s=120)  # fmt: skip
    assert code == 0
    return np.concatenate([read_episode(p).steps for p in list_episodes(out)])


def test_noise_perturbs_the_policy_only_when_asked(tmp_path):
    """noise.during_auto: the world model's exploration data; off by default (AUTO untouched)."""
    plain = _autopilot_steps(tmp_path, "plain")
    auto = plain["mode"] == Mode.AUTO
    assert auto.sum() > 100
    assert not plain["noise"][auto].any()
    np.testing.assert_allclose(plain["executed_action"][auto], plain["policy_action"][auto])

    steps = _autopilot_steps(tmp_path, "explore", "--set", "noise.during_auto=true")
    auto = steps["mode"] == Mode.AUTO
    noisy = steps["noise"].astype(bool) & auto
    assert 0.3 < noisy.sum() / auto.sum() < 0.7, "half of the AUTO time, as in teleop"
    delta = steps["executed_action"] - steps["policy_action"]
    np.testing.assert_allclose(delta[auto & ~noisy], 0.0, atol=1e-6)
    assert np.abs(delta[noisy]).max() > 0.05 and np.abs(delta[noisy]).max() <= 0.3 + 1e-6
    stopped = steps["mode"] != Mode.AUTO
    stopped &= steps["mode"] != Mode.MANUAL
    assert not steps["noise"][stopped].any(), "never noise on a car that is meant to stand"


def test_keyboard_window_drives_the_simulator(tmp_path):
    import pygame

    out = tmp_path / "keys"
    run, key = keyboard_teleop(out, "--record")
    key(pygame.KEYDOWN, pygame.K_RETURN)  # arm
    time.sleep(0.5)
    key(pygame.KEYDOWN, pygame.K_UP)  # accelerate
    time.sleep(1.5)
    key(pygame.KEYUP, pygame.K_UP)
    key(pygame.KEYDOWN, pygame.K_SPACE)  # e-stop
    assert run.result(timeout_s=30) == 0
    (path,) = list_episodes(out)
    ep = read_episode(path)
    assert ep.end_reason == "estop"
    assert ep.steps["human_action"][:, 1].max() > 0.9, "the held key ramps the throttle up"
    assert ep.steps["speed_mps"].max() > 0.5, "and the simulated car moved"


def test_expert_recording_with_only_episodes_ends_by_itself(tmp_path):
    """`teleop --sim --expert auto --record --episodes 2` with no --laps: one lap each."""
    out = tmp_path / "two"
    code = CliRun(
        ["teleop", "--sim", "--expert", "auto", "--record", "--layout", "easy",
         "--episodes", "2", "--out", str(out)]
    ).result(timeout_s=120)  # fmt: skip
    assert code == 0
    episodes = [read_episode(p) for p in list_episodes(out)]
    assert len(episodes) == 2
    assert [int(ep.steps["lap"].sum()) for ep in episodes] == [2, 2]  # start + one lap


def test_one_story_the_loop_the_simulator_and_the_report_count_the_same(tmp_path):
    """For one run, the loop's summary, the simulator's table and `carrt report` agree on
    collisions, interventions and laps (carrt/laps.py's rule), with and without a safety
    driver taking over. The shipped policy on a validation placement where it still collides."""
    from carrt.report import build_report

    seen = {"collisions": 0, "interventions": 0, "laps": 0}
    for name, extra in (("alone", []), ("safety-driver", ["--expert-intervene"])):
        out, summary = tmp_path / name, tmp_path / f"{name}.json"
        code = CliRun(
            ["drive", "--sim", "--autopilot", "--model", "demo", "--layout", "hard",
             "--track-seed", "206", "--seed", "0", "--duration", "60", "--record",
             "--out", str(out), "--summary-json", str(summary), *extra]
        ).result(timeout_s=180)  # fmt: skip
        assert code == 0
        loop = json.loads(summary.read_text())
        sim = json.loads((out / "sim_metrics.json").read_text())
        (report,) = build_report([str(out)])
        counts = {
            "collisions": (loop["collisions"], sim["collisions"], report["collisions"]),
            "interventions": (loop["interventions"], sim["interventions"], report["interventions"]),
            "laps": (loop["laps"], sim["laps"], len(report["laps_s"])),
        }
        for what, (a, b, c) in counts.items():
            assert a == b == c, f"{name}: {what} loop {a}, simulator {b}, report {c}"
            seen[what] += a
    assert all(v > 0 for v in seen.values()), f"nothing to agree on: {seen}"


def test_expert_episodes_of_n_laps_count_n_laps_everywhere(tmp_path):
    """--episodes 3 --laps 2: 6 laps in the simulator, pooled in the report, and 2 per episode,
    with no lap said to span two episodes (each episode is a trial of its own)."""
    from carrt.report import build_report

    out = tmp_path / "laps"
    code = CliRun(
        ["teleop", "--sim", "--expert", "auto", "--record", "--layout", "easy",
         "--episodes", "3", "--laps", "2", "--out", str(out)]
    ).result(timeout_s=180)  # fmt: skip
    assert code == 0
    assert json.loads((out / "sim_metrics.json").read_text())["laps"] == 6
    (pooled,) = build_report([str(out)])
    assert len(pooled["laps_s"]) == 6 and pooled["notes"] == []
    per_episode = build_report([str(out)], per_episode=True)
    assert [len(r["laps_s"]) for r in per_episode] == [2, 2, 2]


def test_recording_on_the_simulated_clock_waits_for_a_slow_disk_and_drops_nothing(
    tmp_path, monkeypatch
):
    """A disk slower than the simulation (here 5 ms a write) must not cost training data: on the
    simulated clock the loop waits for the writer, so every step is on disk, in order."""
    import carrt.episodes.writer as writer_mod

    real_write = writer_mod.write_all

    def slow_write(fd, data):
        time.sleep(0.005)
        real_write(fd, data)

    monkeypatch.setattr(writer_mod, "write_all", slow_write)
    out = tmp_path / "expert"
    code = CliRun(
        ["teleop", "--sim", "--expert", "auto", "--record", "--layout", "easy",
         "--episodes", "1", "--laps", "1", "--out", str(out), "--duration", "300"]
    ).result(timeout_s=120)  # fmt: skip
    assert code == 0
    (path,) = list_episodes(out)
    ep = read_episode(path)
    assert ep.meta["counts"]["dropped"] == 0
    assert ep.n > 50, f"a lap is more than {ep.n} steps"
    assert (np.diff(ep.steps["index"]) == 1).all(), "gaps are dropped steps"
