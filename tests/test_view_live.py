"""The live view (`--view`): a real `carrt drive --sim` process, real HTTP, real headless Chromium.

The browser sees the frame counter advance and the mode change when its e-stop is clicked;
bound beyond localhost every request without the token is refused; on localhost none is
needed but the Host must be local; the only thing any route can do to the car is e-stop.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from dataclasses import replace

import numpy as np
from browser import chromium
from view_rig import ROOT, carrt_with_view, request, state

from carrt.interfaces import CameraFrame, LiveStatus, Mode, Plan
from carrt.loop import SECTIONS
from carrt.model_contract import HORIZON
from carrt.view.live import ESTOP_WHY, LiveFeed
from carrt.view.server import ViewServer

SIM_DRIVE = ["drive", "--sim", "--autopilot", "--realtime", "--model", "demo", "--layout", "easy"]


def _text(browser, element_id: str) -> str:
    return browser.execute_script(f"return document.getElementById('{element_id}').textContent")


def _wait(predicate, timeout_s: float, what: str, interval_s: float = 0.02):
    deadline = time.monotonic() + timeout_s
    while not (value := predicate()):
        assert time.monotonic() < deadline, f"{what} within {timeout_s} s"
        time.sleep(interval_s)
    return value


def _auto_state(base: str) -> dict | None:
    now = state(base)
    return now if now["mode"] == "AUTO" else None


def test_browser_sees_frames_advance_and_the_mode_change_on_its_estop(tmp_path):
    with carrt_with_view([*SIM_DRIVE, "--duration", "90", "--view", "0"], tmp_path) as run, \
            chromium() as browser:  # fmt: skip
        assert run.token is None, "localhost needs no token"
        browser.set_window_size(1400, 1000)
        browser.get(run.url)
        _wait(lambda: _text(browser, "mode") == "AUTO", 30, "the page shows AUTO")
        tick0, seq0 = int(_text(browser, "tick")), int(_text(browser, "seq"))
        time.sleep(1.5)
        tick1, seq1 = int(_text(browser, "tick")), int(_text(browser, "seq"))
        assert tick1 >= tick0 + 5, f"the frame counter advances at ~10 Hz: {tick0} -> {tick1}"
        assert seq1 > seq0, "new camera frames"
        sizes = browser.execute_script(
            "return ['camera', 'crop'].map(id => document.getElementById(id).naturalWidth)"
        )
        assert sizes[0] > 0 and sizes[1] == 96, f"camera frame and the 96x96 crop shown: {sizes}"
        shown = browser.execute_script("return document.getElementById('crop').dataset.tick")
        assert int(shown) >= tick0, "the frames shown are this drive's, not the first one's"
        assert "policy" in _text(browser, "actions") and _text(browser, "plan-note").startswith(
            "blue"
        ), "the policy's plan is drawn"
        screenshot = tmp_path / "live_view.png"
        browser.save_screenshot(str(screenshot))
        if os.environ.get("CARRT_VIEW_SCREENSHOT"):  # README's docs/live_view.png
            shutil.copy(screenshot, os.environ["CARRT_VIEW_SCREENSHOT"])
        now = _wait(lambda: _auto_state(run.base), 10, "a state in AUTO")
        assert now["link"]["estops_sent"] == 0 and now["link"]["frames_sent"] > 0
        assert set(now["sections_ms"]) == set(SECTIONS), "every section of the last tick"
        assert now["board_state"] == "ARMED" and 0 <= now["telemetry_age_ms"] < 100
        assert len(now["plan"]["mu"]) == len(now["plan"]["sigma"]) == HORIZON
        assert now["policy"] == now["executed"], "in AUTO the policy's action is executed"

        browser.find_element("id", "estop").click()
        _wait(lambda: _text(browser, "mode") == "ESTOP", 3, "the page shows ESTOP")
        assert _text(browser, "why") == ESTOP_WHY
        assert state(run.base)["link"]["estops_sent"] >= 1, "it went out on the link's e-stop"
        # the autopilot (the simulator's person) clears and re-arms; the page never does
        _wait(lambda: _text(browser, "mode") == "AUTO", 20, "the autopilot drives again")


def test_beyond_localhost_every_request_without_the_token_is_refused(tmp_path):
    argv = ["teleop", "--sim", "--expert", "auto", "--realtime", "--duration", "60",
            "--view", "0.0.0.0:0"]  # fmt: skip
    with carrt_with_view(argv, tmp_path) as run:
        token = run.token
        assert token and len(token) >= 16, f"a token in the printed URL: {run.url}"
        _wait(lambda: state(run.base, token)["tick"] > 0, 20, "ticks")
        paths = ("/", "/state.json", "/camera.jpg", "/crop.jpg")
        for path in paths:
            assert request(run.base + path)[0] == 403, f"{path} without the token"
            assert request(f"{run.base}{path}?token=wrong{token}")[0] == 403, f"{path}, bad token"
        refused = request(f"{run.base}/estop", method="POST", headers={"X-Carrt": "1"})
        assert refused[0] == 403
        assert state(run.base, token)["link"]["estops_sent"] == 0, "the refused e-stop did nothing"
        _wait(lambda: state(run.base, token)["frame_seq"] is not None, 10, "a frame")
        for path in paths:
            status, body = request(f"{run.base}{path}?token={token}")
            assert status == 200 and body, path
        status, _ = request(run.base + "/state.json", headers={"X-Carrt-Token": token})
        assert status == 200, "the token may also come as a header"
        status, _ = request(f"{run.base}/estop?token={token}", method="POST",
                            headers={"X-Carrt": "1"})  # fmt: skip
        assert status == 200
        _wait(lambda: state(run.base, token)["link"]["estops_sent"] >= 1, 3, "the e-stop sent")


class _Loop:
    """What a LiveFeed reads from the loop, with every e-stop call kept."""

    def __init__(self) -> None:
        rng = np.random.default_rng(0)
        frame = CameraFrame(rng.integers(0, 256, (120, 160, 3), np.uint8), 1.0, seq=7)
        plan = Plan(np.full((10, 2), 0.25, np.float32), np.full((10, 2), 0.1, np.float32))
        self.live = LiveStatus(mode=Mode.AUTO, speed_mps=1.5, tick=42, frame=frame,
                               image=rng.integers(0, 256, (96, 96, 3), np.uint8),
                               policy=(0.25, 0.25), plan=plan, executed=(0.25, 0.25),
                               telemetry_age_s=float("inf"),
                               sections_s={"inference": 0.002}, board_state="ARMED",
                               link_counters={"estops_sent": 0})  # fmt: skip
        self.estops: list[str] = []

    def estop(self, why: str) -> None:
        self.estops.append(why)


def test_localhost_needs_no_token_but_a_local_host_and_only_estop_acts():
    loop = _Loop()
    server = ViewServer("0")
    server.serve(*LiveFeed(lambda: loop.live, loop.estop, command="drive").routes())
    base = f"http://127.0.0.1:{server.port}"
    try:
        assert server.token is None and server.url == f"http://127.0.0.1:{server.port}/"
        status, body = request(base + "/state.json")
        assert status == 200
        got = json.loads(body)
        assert (got["tick"], got["frame_seq"], got["mode"]) == (42, 7, "AUTO")
        assert got["plan"]["mu"][3] == [0.25, 0.25] and got["telemetry_age_ms"] is None
        assert got["sections_ms"]["inference"] == 2.0 and got["alert"] == ""
        loop.live = replace(loop.live, alert="RECORDING FAILED: disk full")
        assert json.loads(request(base + "/state.json")[1])["alert"].startswith("RECORDING FAILED")
        loop.live = replace(loop.live, alert="")
        assert request(base + "/")[0] == 200
        for path in ("/camera.jpg", "/crop.jpg"):
            status, body = request(base + path)
            assert status == 200 and body[:2] == b"\xff\xd8", f"{path} is a JPEG"
        started = time.monotonic()
        assert json.loads(request(base + "/state.json?after=42")[1])["tick"] == 42
        assert time.monotonic() - started > 0.9, "after=N waits (up to 1 s) for tick N+1"
        threading.Timer(0.2, lambda: setattr(loop, "live", replace(loop.live, tick=43))).start()
        started = time.monotonic()
        assert json.loads(request(base + "/state.json?after=42")[1])["tick"] == 43
        assert time.monotonic() - started < 0.8, "and answers as soon as it is published"
        rebinding = {"Host": f"evil.example:{server.port}"}
        assert request(base + "/state.json", headers=rebinding)[0] == 403, "DNS rebinding"

        assert request(base + "/estop", method="POST")[0] == 403, "no cross-site form post"
        assert request(base + "/estop")[0] == 405, "GET never e-stops"
        assert loop.estops == []
        for path in ("/clear", "/arm", "/drive", "/auto", "/state.json"):
            assert request(base + path, method="POST", headers={"X-Carrt": "1"})[0] in (404, 405)
        assert loop.estops == [], "nothing but /estop acts"
        assert request(base + "/estop", method="POST", headers={"X-Carrt": "1"})[0] == 200
        assert loop.estops == [ESTOP_WHY]
    finally:
        server.close()


def _carrt(*argv: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy", "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "carrt", *argv], capture_output=True, text=True,
                          timeout=120, env=env, cwd=ROOT)  # fmt: skip


def test_a_bad_view_address_or_a_port_in_use_is_one_line_and_exit_2():
    sim = ["teleop", "--sim", "--expert", "auto", "--duration", "1"]
    for bad in ("nonsense", "host:", ":", "70000", "127.0.0.1:-1"):
        done = _carrt(*sim, "--view", bad)
        assert done.returncode == 2, (bad, done.stderr)
        assert done.stderr.strip().count("\n") == 0 and "--view" in done.stderr, done.stderr
        assert "Traceback" not in done.stderr
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        done = _carrt(*sim, "--view", str(taken.getsockname()[1]))
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().count("\n") == 0 and "cannot listen" in done.stderr, done.stderr


def test_the_page_shows_the_sessions_fault_and_reboot_lines():
    loop = _Loop()
    rebooted = "board rebooted (brown-out; boot id 0000002a → 0000002b): it gets the car's config"
    loop.live = replace(
        loop.live, deadline=100.0, notices=((97.5, "camera stale: newest frame 180 ms old"),
                                            (99.0, rebooted)),
    )  # fmt: skip
    server = ViewServer("0")
    server.serve(*LiveFeed(lambda: loop.live, loop.estop, command="drive").routes())
    try:
        got = json.loads(request(f"http://127.0.0.1:{server.port}/state.json")[1])
        assert got["notices"] == [[2.5, "camera stale: newest frame 180 ms old"], [1.0, rebooted]]
        with chromium() as browser:
            browser.get(server.url)
            text = _wait(lambda: _text(browser, "notices"), 10, "the page lists the lines")
            assert "2.5 s ago" in text and "camera stale: newest frame 180 ms old" in text
            assert "1.0 s ago" in text and rebooted in text
    finally:
        server.close()
