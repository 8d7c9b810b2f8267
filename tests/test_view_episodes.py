"""`carrt episodes view`: real episodes on disk, the real command serving them, headless
Chromium scrubbing to a step and seeing that step's frame (pixel for pixel), actions, plan,
flags, collision label and lap marks."""

from __future__ import annotations

import json
import time

import numpy as np
from browser import chromium
from episode_factory import make_step, write_episode
from view_rig import carrt_with_view, request

from carrt.episodes.reader import read_episode
from carrt.interfaces import Mode

PIXELS = """const img = document.getElementById('frame');
const c = document.createElement('canvas');
c.width = img.naturalWidth; c.height = img.naturalHeight;
const g = c.getContext('2d'); g.drawImage(img, 0, 0);
return Array.from(g.getImageData(0, 0, c.width, c.height).data);"""


def _episodes(tmp_path):
    first = write_episode(tmp_path / "a", [make_step(i) for i in range(20)])
    steps = [make_step(i, seed=1, mode=Mode.AUTO) for i in range(30)]
    steps[12] = make_step(12, seed=1, mode=Mode.AUTO, lap=True)
    steps[25] = make_step(25, seed=1, mode=Mode.AUTO, collision=True, override=True)
    second = write_episode(tmp_path / "b", steps, reason="collision")
    return [read_episode(first), read_episode(second)]


def _scrub(browser, k: int) -> None:
    browser.execute_script(
        "const s = document.getElementById('slider'); s.value = arguments[0];"
        "s.dispatchEvent(new Event('input'));",
        k,
    )
    deadline = time.monotonic() + 10
    while browser.execute_script(
        "return [document.getElementById('k').textContent,"
        " document.getElementById('frame').dataset.k]"
    ) != [str(k), str(k)]:
        assert time.monotonic() < deadline, f"the page never showed step {k}"
        time.sleep(0.05)


def _text(browser, element_id: str) -> str:
    return browser.execute_script(f"return document.getElementById('{element_id}').textContent")


def test_scrubbing_to_step_k_shows_step_k(tmp_path):
    episodes = _episodes(tmp_path)
    argv = ["episodes", "view", *(str(ep.path) for ep in episodes), "--view", "0"]
    with carrt_with_view(argv, tmp_path) as run, chromium() as browser:
        browser.set_window_size(1400, 900)
        browser.get(run.url)
        deadline = time.monotonic() + 10
        while _text(browser, "k") != "0" or _text(browser, "episode") != episodes[0].name:
            assert time.monotonic() < deadline, "the page never opened at step 0"
            time.sleep(0.05)
        assert browser.find_element("id", "slider").get_attribute("max") == "49"
        second = episodes[1]
        for k, i in ((20 + 25, 25), (20 + 12, 12), (7, 7)):
            ep = second if k >= 20 else episodes[0]
            _scrub(browser, k)
            s = ep.steps[i]
            assert _text(browser, "episode") == ep.name and _text(browser, "i") == str(i)
            for name, key in (("human", "human_action"), ("executed", "executed_action")):
                for j in (0, 1):
                    assert _text(browser, f"{name}-{j}") == f"{float(s[key][j]):.3f}", (k, name)
            shown = np.array(browser.execute_script(PIXELS), np.uint8).reshape(96, 96, 4)
            assert np.array_equal(shown[..., :3], ep.frames[i]), f"step {k}'s frame, exactly"
            classes = {f: browser.find_element("id", f"flag-{f}").get_attribute("class")
                       for f in ("collision", "lap", "override", "noise")}  # fmt: skip
            flags = {f: "on" in c.split() for f, c in classes.items()}
            assert flags == {f: bool(s[f]) for f in flags}, (k, flags)
            label = _text(browser, "flag-label")
            assert label == f"collision label c={int(ep.collision[i])}"
            plan_note = _text(browser, "plan-note")
            if ep is second:
                assert plan_note.startswith("blue"), "a plan is drawn in AUTO"
                assert _text(browser, "policy-0") == f"{float(s['policy_action'][0]):.3f}"
                assert _text(browser, "laps") == f"lap marks {1 if i >= 12 else 0}"
            else:
                assert plan_note.startswith("no plan") and _text(browser, "policy-0") == "–"
        assert int(second.collision[25]) == 1 and int(second.collision[20]) == 0, "the labels"

        status, body = request(f"{run.base}/step.json?k=9999")
        assert status == 400 and b"not in 0..49" in body
        timeline = json.loads(request(f"{run.base}/episodes.json")[1])
        assert timeline["total"] == 50 and timeline["flags"]["collision"][45] is True


def test_view_of_something_that_is_no_episode_is_one_line_and_exit_2(tmp_path):
    import subprocess
    import sys

    from view_rig import ROOT

    (tmp_path / "notes.txt").write_text("not an episode")
    for path, words in (
        (tmp_path, "no episodes in"),
        (tmp_path / "notes.txt", "not a carrt episode"),
    ):
        done = subprocess.run([sys.executable, "-m", "carrt", "episodes", "view", str(path)],
                              capture_output=True, text=True, cwd=ROOT, timeout=60)  # fmt: skip
        assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
        assert words in done.stderr, done.stderr


def test_a_folder_of_episodes_is_viewed_as_ls_lists_it(tmp_path):
    """`carrt episodes ls DIR` takes a folder of episodes: so does view, in ls's order, and
    folders and single episodes mix in the order given."""
    run = tmp_path / "run"
    first = write_episode(run, [make_step(i) for i in range(20)])
    second = write_episode(run, [make_step(i, seed=1, mode=Mode.AUTO) for i in range(30)])
    assert sorted([first.name, second.name]) == [first.name, second.name], "ls's order"
    extra = write_episode(tmp_path / "later", [make_step(i) for i in range(5)])
    argv = ["episodes", "view", str(run), str(extra), "--view", "0"]
    with carrt_with_view(argv, tmp_path) as served:
        timeline = json.loads(request(f"{served.base}/episodes.json")[1])
        assert timeline["total"] == 20 + 30 + 5
        assert "3 episode(s), 55 steps" in "\n".join(served.lines)
        for k, episode in ((19, first), (20, second), (50, extra)):
            status, body = request(f"{served.base}/step.json?k={k}")
            assert status == 200 and json.loads(body)["episode"] == episode.name, (k, body)


def _key(browser, key: str) -> None:
    browser.execute_script(
        "document.dispatchEvent(new KeyboardEvent('keydown', {key: arguments[0]}))", key
    )


def _wait(browser, script: str, expected, what: str) -> None:
    deadline = time.monotonic() + 10
    while browser.execute_script(script) != expected:
        assert time.monotonic() < deadline, f"the page never showed {what}"
        time.sleep(0.05)


def test_a_range_marked_in_the_browser_is_excluded_and_undone(tmp_path):
    """[ at step 5, ] at step 9: steps 5–9 of the first episode are excluded (marks.json beside
    it, the recording's bytes unchanged, the timeline's count says 5, training reads the rest);
    u takes it back."""
    import hashlib

    from carrt.episodes.marks import read_marks

    episodes = _episodes(tmp_path)
    first = episodes[0].path
    digest = {n: hashlib.sha256((first / n).read_bytes()).hexdigest()
              for n in ("steps.bin", "frames.u8", "meta.json")}  # fmt: skip
    argv = ["episodes", "view", *(str(ep.path) for ep in episodes), "--view", "0"]
    with carrt_with_view(argv, tmp_path) as run, chromium() as browser:
        browser.set_window_size(1400, 900)
        browser.get(run.url)
        _wait(browser, "return document.getElementById('marks').textContent", "none", "marks")
        _scrub(browser, 5)
        _key(browser, "[")
        _scrub(browser, 9)
        _key(browser, "]")
        _wait(browser, "return document.getElementById('marks').dataset.excluded", "5",
              "5 excluded steps")  # fmt: skip
        marks = read_marks(first)
        t = episodes[0].steps["frame_captured_at"]
        assert np.flatnonzero(marks.excluded(t)).tolist() == [5, 6, 7, 8, 9]
        assert "excluded" in _text(browser, "marks")
        _key(browser, "u")
        _wait(browser, "return document.getElementById('marks').textContent", "none", "undo")
        assert read_marks(first).exclude == []
    assert digest == {n: hashlib.sha256((first / n).read_bytes()).hexdigest()
                      for n in ("steps.bin", "frames.u8", "meta.json")}  # fmt: skip


def test_a_policy_replayed_over_the_episodes_is_a_row_and_a_trace(tmp_path):
    """`carrt episodes view EP --model M`: each step's action of M as the car would have run
    it, in the actions table and as a steering trace on the timeline."""
    from onnx_models import build_policy

    from carrt.episodes import replay
    from carrt.policy import OnnxPolicy

    episodes = _episodes(tmp_path)
    model = build_policy(tmp_path / "left.onnx", steering=-0.6, throttle=(0.4, 0.0))
    expected = replay.model_actions(OnnxPolicy(model), episodes[1])
    argv = ["episodes", "view", *(str(ep.path) for ep in episodes), "--model", str(model),
            "--view", "0"]  # fmt: skip
    with carrt_with_view(argv, tmp_path) as run, chromium() as browser:
        timeline = json.loads(request(f"{run.base}/episodes.json")[1])
        trace = np.array(timeline["replayed"]["left.onnx"])
        assert trace.shape == (50, 2)
        np.testing.assert_allclose(trace[20:], expected, atol=1e-3)
        browser.set_window_size(1400, 900)
        browser.get(run.url)
        deadline = time.monotonic() + 10
        while _text(browser, "k") != "0":
            assert time.monotonic() < deadline, "the page never opened at step 0"
            time.sleep(0.05)
        _scrub(browser, 33)
        assert "replay: left.onnx" in _text(browser, "actions")
        assert _text(browser, "replay-0-0") == f"{float(expected[13][0]):.3f}"
        colour = browser.execute_script(
            "const c = document.getElementById('timeline'), g = c.getContext('2d');"
            "const d = g.getImageData(0, 0, c.width, c.height).data; let n = 0;"
            "for (let i = 0; i < d.length; i += 4)"
            "  if (d[i] < 40 && d[i + 1] > 200 && d[i + 2] > 230) n++;"
            "return n;"
        )
        assert colour > 50, "the replayed steering is drawn on the timeline (cyan)"
