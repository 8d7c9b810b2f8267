"""The live view's routes: the loop's last LiveStatus as JSON, its frames as JPEG, an e-stop.

Runs on the server's threads only. The loop replaces `loop.live` whole every tick, so reading
it here is one attribute load and always one tick's values together. A tick's JSON and JPEGs
are made once, by whichever request asks first, and shared with every other client until the
next tick: ten browsers cost what one does. JPEGs come from OpenCV (`cv2.imencode`), which
releases the GIL while it encodes.

The only thing a request can do to the car is `POST /estop`, which calls the loop's e-stop
(latched, and on the wire at once through the link's e-stop path, as the pad's button is).
No route clears, arms or drives: those stay with the person holding the pad.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from carrt.interfaces import LiveStatus
from carrt.reasons import Why
from carrt.view.server import Response, Route, json_response, page
from firmware_bridge.timing import CONTROL_PERIOD_S

JPEG_QUALITY = 85
ESTOP_WHY = Why.BROWSER.text()  # what the e-stop says latched it
LONG_POLL_S = 1.0  # `state.json?after=N` waits at most this long for tick N+1
WAIT_STEP_S = 0.002  # how often a tick that is later than due is looked for
DUE_MARGIN_S = 0.003  # looked for this long after it is due


class LiveFeed:
    """`status()` returns the loop's newest LiveStatus; `estop(why)` is the loop's e-stop;
    `crop` the camera config's crop fractions (top, bottom, left, right), drawn on the frame."""

    def __init__(
        self,
        status: Callable[[], LiveStatus],
        estop: Callable[[str], None],
        *,
        command: str,
        crop: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
        period_s: float = CONTROL_PERIOD_S,
        now: Callable[[], float] = time.monotonic,
    ) -> None:
        self.status = status
        self.period_s = period_s
        self.now = now  # the loop's clock, on which LiveStatus.deadline is
        self._estop = estop
        self.command = command
        self.crop = crop
        self._lock = threading.Lock()
        self._cache: dict[str, tuple[LiveStatus, Response]] = {}
        # Pay the encoders' first-use costs (libjpeg's set-up, JSON of every field type) now,
        # before the loop runs, not in the first requests while it drives.
        jpeg(np.zeros((8, 8, 3), np.uint8))
        self._state(LiveStatus())

    def routes(self) -> tuple[dict[str, Route], dict[str, Route]]:
        get = {
            "/": lambda q: page("live.html"),
            "/state.json": self.state,
            "/camera.jpg": lambda q: self._cached("camera", self._camera),
            "/crop.jpg": lambda q: self._cached("crop", self._crop),
        }
        return get, {"/estop": self.estop}

    def state(self, query: dict[str, str]) -> Response:
        """The last tick's state; with `after=N`, the state of the first tick after N.

        Waiting for the next tick is what keeps watching cheap for the loop: the answer (and
        the page's frame requests that follow it) is made right after the loop published a
        tick, while it sleeps until its next deadline, not at a moment that may fall on the
        start of a tick, where the loop wakes up and needs the GIL and a core. The wait sleeps
        until the next tick is due (its deadline plus what the last tick took), so it wakes
        about once per tick, after the tick started: polling every 2 ms instead made ~9% of
        ticks start 0.5-1 ms late on the 2-core bench machine.
        """
        if "after" in query:
            after = int(query["after"])
            give_up = time.monotonic() + LONG_POLL_S
            while (live := self.status()).tick <= after:
                left = give_up - time.monotonic()
                if left <= 0:
                    break
                due = live.deadline + self.period_s + sum(live.sections_s.values()) - self.now()
                due = due + DUE_MARGIN_S if math.isfinite(due) else WAIT_STEP_S
                time.sleep(min(max(due, WAIT_STEP_S), left))
        return self._cached("state", self._state)

    def estop(self, query: dict[str, str]) -> Response:
        del query
        self._estop(ESTOP_WHY)
        return json_response({"estop": True})

    def _cached(self, kind: str, make: Callable[[LiveStatus], Response]) -> Response:
        live = self.status()
        with self._lock:
            hit = self._cache.get(kind)
            if hit is not None and hit[0] is live:
                return hit[1]
        response = make(live)  # outside the lock: two first askers may both encode, harmless
        with self._lock:
            self._cache[kind] = (live, response)
        return response

    def _state(self, live: LiveStatus) -> Response:
        plan = live.plan
        counters = {k: v for k, v in live.link_counters.items() if isinstance(v, (int, float))}
        return json_response(
            {
                "command": self.command,
                "tick": live.tick,
                "frame_seq": None if live.frame is None else live.frame.seq,
                "mode": live.mode.name,
                "why": live.why,
                "speed_mps": live.speed_mps,
                "human": live.human,
                "policy": live.policy,
                "executed": live.executed,
                "plan": None
                if plan is None
                else {"mu": plan.mu.tolist(), "sigma": plan.sigma.tolist()},
                "sections_ms": {k: v * 1e3 for k, v in live.sections_s.items()},
                "board_state": live.board_state,
                "telemetry_age_ms": live.telemetry_age_s * 1e3,
                "link": counters,
                "recording": live.recording,
                "episodes": live.episodes,
                "collisions": live.collisions,
                "laps": live.laps,
                "alert": live.alert,
                # faults and board events, newest last: (seconds ago, the line as printed)
                "notices": [[live.deadline - at, line] for at, line in live.notices],
            }
        )

    def _camera(self, live: LiveStatus) -> Response:
        """The whole camera frame with the policy's crop outlined."""
        if live.frame is None:
            return Response(b"", "image/jpeg", status=404)
        import cv2

        bgr = cv2.cvtColor(live.frame.image, cv2.COLOR_RGB2BGR)  # a new array: the frame stays
        h, w = bgr.shape[:2]
        top, bottom, left, right = self.crop
        cv2.rectangle(
            bgr,
            (round(w * left), round(h * top)),
            (w - round(w * right) - 1, h - round(h * bottom) - 1),
            (0, 220, 255),
            max(1, w // 320),
        )
        return jpeg(bgr)

    def _crop(self, live: LiveStatus) -> Response:
        """The 96×96 image exactly as the policy got it."""
        if live.image is None:
            return Response(b"", "image/jpeg", status=404)
        import cv2

        return jpeg(cv2.cvtColor(live.image, cv2.COLOR_RGB2BGR))


def jpeg(bgr: np.ndarray) -> Response:
    import cv2

    ok, data = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        return Response(b"", "image/jpeg", status=500)
    return Response(data.tobytes(), "image/jpeg")


def live_view(server: Any, loop: Any, config: Any, command: str) -> None:
    """Serve the live view of `loop` on a bound ViewServer and print its URL (with the token
    when bound beyond localhost): print, not the log, so `-q` cannot hide the token."""
    camera = config.camera
    feed = LiveFeed(
        lambda: loop.live,
        loop.estop,
        command=command,
        crop=(camera.crop_top, camera.crop_bottom, camera.crop_left, camera.crop_right),
        period_s=loop.period,
        now=loop.parts.clock.now,
    )
    server.serve(*feed.routes())
    print(f"view: {server.url}", flush=True)
