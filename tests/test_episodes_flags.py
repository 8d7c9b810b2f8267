"""Episodes that flag their own problems (issue 68, item 3): each flag found, at its steps, on an
episode crafted to have it and not on one just inside its threshold; `ls` names them, `--flags`
keeps the episodes that have them, `show` lists their steps, `mark --exclude-flag` excludes
exactly those steps (so training never sees them), the scrubber draws them, and a clean episode
recorded by the simulator's expert flags nothing."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest
from episode_factory import image_for, make_step, metadata, mixed_steps, run_cli, write_episode

from carrt.episodes import flags as suspect
from carrt.episodes.marks import read_marks
from carrt.episodes.reader import read_episode
from carrt.interfaces import Mode
from carrt.view.episodes import EpisodeFeed


def _ep(tmp_path, steps, **kwargs):
    return read_episode(write_episode(tmp_path / "eps", steps, **kwargs))


def _steps(n, change=None, **kwargs):
    """n factory steps (random frames, speeds and actions: nothing suspect); `change(i)` gives
    the fields step i gets instead."""
    steps = []
    for i in range(n):
        fields = {**kwargs, **((change and change(i)) or {})}
        steps.append(make_step(fields.pop("index", i), **fields))
    return steps


def test_the_factory_episodes_flag_nothing(tmp_path):
    assert suspect.find_flags(_ep(tmp_path, _steps(50))) == {}
    found = suspect.find_flags(_ep(tmp_path, mixed_steps(30)))
    assert set(found) == {"collision", "takeover"}  # counted, not faults
    # every e-stop while driving is a collision event (i % 6 == 5), the flag at 17 one of them
    assert found["collision"] == [(5, 6), (11, 12), (17, 18), (23, 24), (29, 30)]
    assert found["takeover"] == [(3, 4), (10, 11), (17, 18), (24, 25)]


def test_a_frozen_camera_is_the_run_of_identical_frames_while_moving(tmp_path):
    frozen = _steps(40, lambda i: {"image": image_for(10)} if 10 <= i < 20 else None)
    assert suspect.frozen_camera(_ep(tmp_path, frozen)) == [(10, 20)]
    # FROZEN_STEPS identical frames in a row is not yet frozen
    edge = _steps(40, lambda i: {"image": image_for(10)} if 10 <= i < 10 + suspect.FROZEN_STEPS
                  else None)  # fmt: skip
    assert suspect.frozen_camera(_ep(tmp_path, edge)) == []
    # a parked car (speed 0, no throttle) shows the same scene: the simulator renders it exactly
    still = {"image": image_for(10), "speed_mps": 0.0, "executed_action": (0.0, 0.0)}
    parked = _steps(40, lambda i: still if 10 <= i < 20 else None)
    assert suspect.frozen_camera(_ep(tmp_path, parked)) == []


def test_a_gap_in_the_step_clock_flags_the_step_after_it(tmp_path):
    def change(i):
        t = 1000.0 + i * 0.1 + (0.3 if i >= 25 else 0.0) + (0.05 if i == 12 else 0.0)
        return {"frame_captured_at": t, "index": i + (1 if i >= 33 else 0)}

    ep = _ep(tmp_path, _steps(40, change))
    # 0.4 s before step 25 (4 periods), the loop's index skipping at 33; step 12's 0.15 s
    # (1.5 periods) and 13's 0.05 s are jitter
    assert suspect.clock_gaps(ep) == [(25, 26), (33, 34)]
    backwards = _steps(20, lambda i: {"frame_captured_at": 999.0} if i == 7 else None)
    assert suspect.clock_gaps(_ep(tmp_path, backwards)) == [(7, 8), (8, 9)]


def test_the_gap_is_measured_against_the_episodes_own_rate(tmp_path):
    late = _steps(40, lambda i: {"frame_captured_at": 1000.05 + i * 0.05} if i >= 20 else None,
                  period=0.05)  # 20 Hz, 0.05 s apart, then one period late  # fmt: skip
    meta = {**metadata(), "rate_hz": 20.0}
    assert suspect.clock_gaps(_ep(tmp_path, late, meta=meta)) == [(20, 21)]  # 0.1 s: 2 periods
    assert suspect.clock_gaps(_ep(tmp_path, _steps(40, period=0.15))) == []  # 10 Hz, 1.5 periods


def test_a_dead_speed_sensor_reads_zero_while_the_car_is_commanded_to_move(tmp_path):
    def dead(first, last, mode=Mode.MANUAL, throttle=0.5):
        return lambda i: ({"speed_mps": 0.0, "executed_action": (0.1, throttle), "mode": mode}
                          if first <= i < last else None)  # fmt: skip

    assert suspect.dead_speed_sensor(_ep(tmp_path, _steps(50, dead(10, 30)))) == [(10, 30)]
    assert suspect.dead_speed_sensor(_ep(tmp_path, _steps(50, dead(5, 35, Mode.AUTO)))) == [(5, 35)]
    # one second (a car starting from rest), parked, braking or barely throttled: no fault
    assert suspect.dead_speed_sensor(_ep(tmp_path, _steps(50, dead(10, 20)))) == []
    assert suspect.dead_speed_sensor(_ep(tmp_path, _steps(50, dead(10, 30, Mode.DISARMED)))) == []
    assert suspect.dead_speed_sensor(_ep(tmp_path, _steps(50, dead(10, 30, throttle=-0.8)))) == []
    assert suspect.dead_speed_sensor(_ep(tmp_path, _steps(50, dead(10, 30, throttle=0.2)))) == []
    slow = _steps(50, lambda i: {"speed_mps": 0.01, "executed_action": (0.0, 0.5)})
    assert suspect.dead_speed_sensor(_ep(tmp_path, slow)) == []  # exactly 0, not slow


@pytest.mark.parametrize("axis, name", [(0, "pinned-steering"), (1, "pinned-throttle")])
@pytest.mark.parametrize("limit", [1.0, -1.0])
def test_steering_or_throttle_pinned_at_a_limit(tmp_path, axis, name, limit):
    def pin(first, last):
        def change(i):
            if not first <= i < last:
                return None
            action = [0.3, 0.4]
            action[axis] = limit
            return {"executed_action": tuple(action)}

        return change

    longer = 10 * int(suspect.PINNED_S) + 1  # more than PINNED_S at 10 Hz
    ep = _ep(tmp_path, _steps(80, pin(10, 10 + longer)))
    found = suspect.find_flags(ep)
    assert found == {name: [(10, 10 + longer)]}
    assert suspect.find_flags(_ep(tmp_path, _steps(80, pin(10, 10 + longer - 1)))) == {}
    # at a limit while parked or after an e-stop is not driving
    parked = _steps(80, pin(10, 10 + longer), mode=Mode.ESTOP)
    assert suspect.find_flags(_ep(tmp_path, parked)).get(name) is None


def test_a_short_episode_is_the_whole_episode(tmp_path):
    assert suspect.short_episode(_ep(tmp_path, _steps(15))) == [(0, 15)]  # 1.4 s
    assert suspect.short_episode(_ep(tmp_path, _steps(25))) == []  # 2.4 s


def _crafted(tmp_path):
    """Three episodes: a frozen camera (steps 10–19), a dead speed sensor (20–39), clean."""
    frozen = write_episode(tmp_path / "eps", _steps(
        40, lambda i: {"image": image_for(10)} if 10 <= i < 20 else None))  # fmt: skip
    dead = write_episode(tmp_path / "eps", _steps(
        50, lambda i: {"speed_mps": 0.0, "executed_action": (0.0, 0.6)} if 20 <= i < 40 else None,
        seed=1))  # fmt: skip
    clean = write_episode(tmp_path / "eps", _steps(30, seed=2))
    return frozen, dead, clean


def test_ls_names_the_flags_and_flags_filters(tmp_path, capsys):
    frozen, dead, clean = _crafted(tmp_path)
    assert run_cli(["episodes", "ls", str(tmp_path / "eps")]) == 0
    rows = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()}
    assert rows[frozen.name].endswith("flags: frozen-camera")
    assert rows[dead.name].endswith("flags: dead-speed")
    assert "flags:" not in rows[clean.name]
    assert run_cli(["episodes", "ls", str(tmp_path / "eps"), "--flags", "dead-speed,short"]) == 0
    out = capsys.readouterr().out
    assert dead.name in out and frozen.name not in out and clean.name not in out
    assert "1 episodes with dead-speed, short (of 3)" in out


def test_an_unknown_flag_is_one_line_and_exit_2(tmp_path, capsys):
    from carrt.cli import main

    frozen, _, _ = _crafted(tmp_path)
    for argv in (["ls", str(tmp_path / "eps"), "--flags", "frozen"],
                 ["mark", str(frozen), "--exclude-flag", "frozen-camera,frozen"]):  # fmt: skip
        assert main(["episodes", *argv]) == 2
        captured = capsys.readouterr()
        err = captured.err.strip()
        assert len(err.splitlines()) == 1 and "unknown flag 'frozen'; one of frozen-camera" in err
        assert captured.out == ""
    assert not (frozen / "marks.json").exists()


def test_show_lists_each_flag_with_its_steps(tmp_path, capsys):
    steps = _steps(40, lambda i: {"image": image_for(10)} if 10 <= i < 20 else None)
    steps[30] = make_step(30, collision=True)
    path = write_episode(tmp_path / "eps", steps)
    assert run_cli(["episodes", "show", str(path)]) == 0
    out = capsys.readouterr().out
    assert "flags          frozen-camera: steps 10–19 (1.00–1.90 s)\n" in out
    assert "               collision: 1 (counted, not a fault), steps 30 (3.00 s)" in out
    assert run_cli(["episodes", "show", str(path), "--json"]) == 0
    flags = json.loads(capsys.readouterr().out)["flags"]
    assert flags == {"frozen-camera": [[10, 20]], "collision": [[30, 31]]}
    run_cli(["episodes", "mark", str(path), "--exclude", "1.0-1.5"])  # half the frozen steps
    capsys.readouterr()
    assert run_cli(["episodes", "show", str(path)]) == 0
    assert "frozen-camera: steps 10–19 (1.00–1.90 s)\n" in capsys.readouterr().out
    clean = write_episode(tmp_path / "eps", _steps(30, seed=3))
    assert run_cli(["episodes", "show", str(clean)]) == 0
    assert "flags          none" in capsys.readouterr().out


def test_mark_excludes_exactly_the_flagged_steps(tmp_path, capsys):
    frozen, dead, clean = _crafted(tmp_path)
    argv = ["episodes", "mark", str(frozen), str(dead), str(clean), "--exclude-flag",
            "frozen-camera", "--exclude-flag", "dead-speed"]  # fmt: skip
    assert run_cli(argv) == 0
    out = capsys.readouterr().out
    assert f"{frozen.name}: frozen-camera: 1 range(s)" in out
    assert f"{frozen.name}: excluded 1–1.901 s (10 of 40 steps excluded)" in out
    assert f"{dead.name}: dead-speed: 1 range(s)" in out and "(20 of 50 steps excluded)" in out
    assert f"{clean.name}: none (0 of 30 steps excluded)" in out
    for path, flagged in ((frozen, range(10, 20)), (dead, range(20, 40)), (clean, [])):
        ep = read_episode(path)
        excluded = read_marks(path).excluded(ep.timestamps)
        assert np.flatnonzero(excluded).tolist() == list(flagged), path.name
    # show says the flag is taken care of; training reads the kept steps as segments
    assert run_cli(["episodes", "show", str(frozen)]) == 0
    assert "frozen-camera: steps 10–19 (1.00–1.90 s) (excluded)" in capsys.readouterr().out
    from carrt.episodes.marks import kept_segments

    ep = read_episode(frozen)
    assert kept_segments(read_marks(frozen).excluded(ep.timestamps)) == [(0, 10), (20, 40)]


def test_the_scrubber_gets_the_flagged_ranges_in_its_numbering(tmp_path):
    frozen, dead, clean = _crafted(tmp_path)
    feed = EpisodeFeed([read_episode(p) for p in (clean, frozen, dead)])
    assert feed.timeline()["suspect"] == [
        {"episode": 1, "name": "frozen-camera", "fault": True, "ranges": [[40, 50]]},
        {"episode": 2, "name": "dead-speed", "fault": True, "ranges": [[90, 110]]},
    ]


def test_the_scrubber_draws_and_names_the_flags(tmp_path):
    """In headless Chromium: the frozen steps' columns of the timeline carry the magenta bar,
    the others not, and the episode's flags are named with their steps."""
    from browser import chromium
    from view_rig import carrt_with_view

    frozen, _, _ = _crafted(tmp_path)
    pixel = """const c = document.getElementById('timeline'); const g = c.getContext('2d');
    return Array.from(g.getImageData(Math.floor((arguments[0] + 0.5) * c.width / 40), 2, 1, 1)
    .data).slice(0, 3);"""
    with carrt_with_view(["episodes", "view", str(frozen), "--view", "0"], tmp_path) as run, \
            chromium() as browser:  # fmt: skip
        browser.get(run.url)
        script = "return document.getElementById('suspect').textContent"
        for _ in range(200):
            if browser.execute_script(script) != "–":
                break
            time.sleep(0.05)
        assert browser.execute_script(script) == "frozen-camera 10–19"
        assert browser.execute_script(pixel, 15) == [0xE0, 0x40, 0xFB]
        assert browser.execute_script(pixel, 30) != [0xE0, 0x40, 0xFB]


def test_a_clean_simulator_recording_flags_nothing(tmp_path, capsys):
    """One lap by the simulator's expert, recorded by the real stack on the simulated clock."""
    out = tmp_path / "sim"
    argv = ["teleop", "--sim", "--expert", "auto", "--record", "--layout", "easy",
            "--episodes", "1", "--laps", "1", "--out", str(out), "--duration", "600"]  # fmt: skip
    done = subprocess.run([sys.executable, "-m", "carrt", *argv], capture_output=True, text=True,
                          timeout=300, env={**os.environ, "SDL_VIDEODRIVER": "dummy"})  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    (path,) = [p for p in out.iterdir() if (p / "meta.json").is_file()]
    ep = read_episode(path)
    assert ep.n > 50 and ep.meta["rate_hz"] == 10.0
    assert suspect.find_flags(ep) == {}
    assert run_cli(["episodes", "ls", str(out), "--flags", ",".join(suspect.NAMES)]) == 0
    assert "0 episodes with" in capsys.readouterr().out
