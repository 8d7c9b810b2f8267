"""`carrt episodes view EP...`: scrub recorded episodes in a browser, step by step.

Why a page served by the same small server as the live view, and not a self-contained HTML file
or a notebook: an episode of ten minutes is 6,000 frames, and a file that embedded them all
would be tens of megabytes before it showed anything; served, the reader's memory map is read
only where the slider stops, and nothing new is installed (no Jupyter, no Rerun viewer on a
Jetson). The page gets the whole timeline once (speed, mode, actions, flags: small numbers) and
asks for one step's frame and plan as the slider moves.

The page also marks (carrt/episodes/marks.py): select a range with `[` and `]` (or the buttons)
and it is excluded from training, `u` undoes, `x` excludes the whole episode; the excluded
steps are shaded on the timeline. Marks go to `marks.json` beside the episode through POSTs
(the view server's token and header rules); the recorded files are never written.

Frames are PNG, not JPEG: lossless, so the page shows the 96×96 image the policy was trained
on pixel for pixel (a 96×96 PNG is a few kB; nothing here runs at 10 Hz).
"""

from __future__ import annotations

import argparse
import signal
import threading
from typing import Any

import numpy as np

from carrt.episodes import flags as suspect
from carrt.episodes import marks as mk
from carrt.episodes import replay
from carrt.episodes.format import FLAGS
from carrt.episodes.reader import Episode, in_order, read_episode
from carrt.errors import UserError
from carrt.interfaces import Mode
from carrt.view.server import Response, Route, ViewServer, json_response, page

MODES = {int(m): m.name for m in Mode}


class EpisodeFeed:
    """The steps of `episodes` in order, numbered 0..total-1 across all of them."""

    def __init__(self, episodes: list[Episode], models: dict[str, Any] | None = None) -> None:
        self.episodes = episodes
        self.starts = np.cumsum([0, *(ep.n for ep in episodes)])
        self.total = int(self.starts[-1])
        # each model's action at every step, as the car would have run it (carrt episodes
        # replay): computed once, before the page is served
        self.replayed = {
            name: np.concatenate([replay.model_actions(p, ep) for ep in episodes] or
                                 [np.zeros((0, 2), np.float32)])
            for name, p in (models or {}).items()
        }  # fmt: skip

    def routes(self) -> dict[str, Route]:
        return {
            "/": lambda q: page("episodes.html"),
            "/episodes.json": lambda q: json_response(self.timeline()),
            "/step.json": lambda q: json_response(self.step(self._k(q))),
            "/frame.png": lambda q: self.frame(self._k(q)),
        }

    def post_routes(self) -> dict[str, Route]:
        """Marks from the page: each answers with the episode's marks after the change."""
        return {
            "/exclude.json": lambda q: json_response(
                self.exclude(self._k(q, "k0"), self._k(q, "k1"))
            ),
            "/exclude_episode.json": lambda q: json_response(self.exclude_episode(self._k(q))),
            "/undo.json": lambda q: json_response(self.undo(self._k(q))),
        }

    def _times(self, ep: Episode) -> np.ndarray:
        t = np.asarray(ep.steps["frame_captured_at"], dtype=np.float64)
        return t - t[0]

    def exclude(self, k0: int, k1: int) -> dict[str, Any]:
        (ep, i0), (other, i1) = self.locate(min(k0, k1)), self.locate(max(k0, k1))
        if other is not ep:
            raise IndexError("a range to exclude lies inside one episode")
        rel = self._times(ep)
        lo, hi = float(rel[i0]), float(rel[i1]) + 1e-3  # [lo, hi): step i1 included

        def add(m: mk.Marks) -> None:
            if (lo, hi) not in m.exclude:
                m.exclude.append((lo, hi))

        return self._answer(ep, mk.change(ep.path, add))

    def exclude_episode(self, k: int) -> dict[str, Any]:
        ep, _ = self.locate(k)
        return self._answer(ep, mk.change(ep.path, lambda m: setattr(m, "whole", True)))

    def undo(self, k: int) -> dict[str, Any]:
        ep, _ = self.locate(k)
        try:
            return self._answer(ep, mk.undo(ep.path))
        except UserError as exc:
            return {"episode": ep.name, "error": str(exc)}

    def _answer(self, ep: Episode, marks: mk.Marks) -> dict[str, Any]:
        excluded = int(marks.excluded(ep.steps["frame_captured_at"]).sum())
        return {"episode": ep.name, "marks": marks.describe(), "excluded": excluded}

    def _k(self, query: dict[str, str], name: str = "k") -> int:
        k = int(query[name])
        if not 0 <= k < self.total:
            raise IndexError(f"step {k} is not in 0..{self.total - 1}")
        return k

    def locate(self, k: int) -> tuple[Episode, int]:
        e = int(np.searchsorted(self.starts, k, side="right")) - 1
        return self.episodes[e], k - int(self.starts[e])

    def timeline(self) -> dict[str, Any]:
        """Everything the page draws along the slider, for every step at once."""

        def joined(name: str) -> list:
            parts = [np.asarray(ep.steps[name]) for ep in self.episodes]
            return np.round(np.concatenate(parts).astype(np.float64), 3).tolist() if parts else []

        marks = [mk.read_marks(ep.path) for ep in self.episodes]  # each marks.json read once
        return {
            "total": self.total,
            "episodes": [
                {
                    "name": ep.name,
                    "start": int(start),
                    "n": ep.n,
                    "end_reason": ep.end_reason,
                    "torn": ep.torn,
                }
                for ep, start in zip(self.episodes, self.starts[:-1], strict=True)
            ],
            "speed": joined("speed_mps"),
            "mode": [MODES.get(int(v), str(v)) for v in joined("mode")],
            "human": joined("human_action"),
            "policy": joined("policy_action"),
            "executed": joined("executed_action"),
            "flags": {name: [bool(v) for v in joined(name)] for name in FLAGS},
            "collision_label": [int(v) for ep in self.episodes for v in ep.collision],
            "excluded": [
                bool(v)
                for ep, m in zip(self.episodes, marks, strict=True)
                for v in m.excluded(ep.steps["frame_captured_at"])
            ],
            "marks": [m.describe() for m in marks],
            "suspect": self.suspect(),
            "replayed": {n: _rounded(a) for n, a in self.replayed.items()},
        }

    def suspect(self) -> list[dict[str, Any]]:
        """Each flag (carrt/episodes/flags.py) of each episode: its name, whether it is a fault
        and its [k0, k1) ranges in the slider's numbering. Found once: a recording never
        changes."""
        if not hasattr(self, "_suspect"):
            pairs = enumerate(zip(self.episodes, self.starts[:-1], strict=True))
            self._suspect = [
                {"episode": e, "name": name, "fault": suspect.is_fault(name),
                 "ranges": [[int(start) + a, int(start) + b] for a, b in ranges]}
                for e, (ep, start) in pairs
                for name, ranges in suspect.find_flags(ep).items()
            ]  # fmt: skip
        return self._suspect

    def step(self, k: int) -> dict[str, Any]:
        ep, i = self.locate(k)
        s = ep.steps[i]
        t0 = float(ep.steps["frame_captured_at"][0])
        mu = np.asarray(s["plan_mu"], np.float64)
        sigma = np.asarray(s["plan_sigma"], np.float64)
        has_plan = bool(np.isfinite(mu).all())
        laps = int(np.count_nonzero(ep.steps["lap"][: i + 1]))
        return {
            "k": k,
            "episode": ep.name,
            "i": i,
            "n": ep.n,
            "index": int(s["index"]),
            "t_s": float(s["frame_captured_at"]) - t0,
            "speed_mps": float(s["speed_mps"]),
            "encoder_ticks": int(s["encoder_ticks"]),
            "mode": MODES.get(int(s["mode"]), str(int(s["mode"]))),
            "human": np.asarray(s["human_action"], np.float64).tolist(),
            "policy": np.asarray(s["policy_action"], np.float64).tolist(),
            "executed": np.asarray(s["executed_action"], np.float64).tolist(),
            "replayed": {n: a[k].astype(np.float64).tolist() for n, a in self.replayed.items()},
            "plan": {"mu": mu.tolist(), "sigma": sigma.tolist()} if has_plan else None,
            "flags": {name: bool(s[name]) for name in FLAGS},
            "collision_label": int(ep.collision[i]),
            "lap_marks": laps,
            "end_reason": ep.end_reason,
        }

    def frame(self, k: int) -> Response:
        import cv2

        ep, i = self.locate(k)
        ok, data = cv2.imencode(".png", cv2.cvtColor(np.asarray(ep.frames[i]), cv2.COLOR_RGB2BGR))
        if not ok:
            return Response(b"", "image/png", status=500)
        return Response(data.tobytes(), "image/png")


def _rounded(actions: np.ndarray) -> list:
    return np.round(actions.astype(np.float64), 3).tolist()


def run_view(args: argparse.Namespace) -> int:
    """Serve until Ctrl-C (or SIGTERM); exits 0."""
    # errors before binding; a folder of episodes is taken as `carrt episodes ls` takes it
    episodes = [read_episode(path) for path in in_order(args.episode)]
    models = {}
    if getattr(args, "model", None):
        from carrt.policy import OnnxPolicy

        for model in args.model:
            policy = OnnxPolicy(model)  # refused as the car would refuse it
            models[policy.path.name if policy.path.name not in models else model] = policy
    server = ViewServer(args.view)
    feed = EpisodeFeed(episodes, models)
    server.serve(feed.routes(), feed.post_routes())
    total = sum(ep.n for ep in episodes)
    print(f"view: {server.url}", flush=True)
    print(f"{len(episodes)} episode(s), {total} steps; Ctrl-C to stop", flush=True)
    done = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: done.set())
                for sig in (signal.SIGINT, signal.SIGTERM)}  # fmt: skip
    try:
        while not done.wait(0.5):
            pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        server.close()
    return 0
