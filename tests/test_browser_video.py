"""An episode video plays in a real browser (headless Chromium): H.264, decoded and advancing."""

from __future__ import annotations

import time

from browser import chromium, serve
from episode_factory import make_step, write_episode

from carrt.episodes.reader import read_episode
from carrt.episodes.video import PANEL_W, render_video

STATE = """const v = document.getElementById('v');
return [v.readyState, v.videoWidth, v.videoHeight, v.duration, v.error && v.error.code,
        v.currentTime, v.paused];"""


def test_an_episode_video_plays_in_chromium(tmp_path):
    episodes = [read_episode(write_episode(tmp_path / f"e{k}", [make_step(i) for i in range(30)]))
                for k in range(2)]  # fmt: skip
    render_video(episodes, tmp_path / "site" / "run.mp4")
    (tmp_path / "site" / "index.html").write_text('<video id="v" src="run.mp4" muted></video>')
    with serve(tmp_path / "site") as url, chromium() as browser:
        browser.get(f"{url}/index.html")
        deadline = time.monotonic() + 20
        while (state := browser.execute_script(STATE))[0] < 2 and not state[4]:
            assert time.monotonic() < deadline, f"the video never loaded: {state}"
            time.sleep(0.1)
        _, width, height, duration, error, _, _ = state
        assert error is None, f"Chromium could not decode it (MediaError {error})"
        assert (width, height) == (384 + PANEL_W, 384)
        assert abs(duration - 6.0) < 0.2, "60 frames at 10 fps: both episodes"
        browser.execute_script("document.getElementById('v').play()")
        time.sleep(1.0)
        *_, position, paused = browser.execute_script(STATE)
        assert not paused and position > 0.3, "it plays"
