"""Episodes as a Rerun recording (.rrd), for people who look at robot data in Rerun.

    carrt episodes rerun episodes/20261123-* -o run.rrd && rerun run.rrd

Each episode is one entity tree (`/<episode name>/…`) on two timelines: `step` (the record's
index) and `time` (seconds since the episode's first frame, what `carrt episodes show`, the
scrubber and marks count). Logged per step: the camera frame, speed, the person's, the policy's
and the executed actions (steering and throttle each a scalar series), the policy's plan μ over
its horizon (a line of steering against throttle), the mode, collision labels, laps and the
marks (excluded steps as a 0/1 series; notes as a text log). Written with the Rerun SDK's own
file sink; a test reads it back with Rerun's chunk reader.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from carrt.episodes.marks import read_marks
from carrt.episodes.reader import Episode
from carrt.interfaces import Mode

ACTIONS = (("person", "human_action"), ("policy", "policy_action"), ("executed", "executed_action"))


def write_rrd(episodes: list[Episode], out: str | Path) -> int:
    """Every step of every episode into `out`; returns the steps written."""
    import rerun as rr

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream("carrt")
    rec.save(str(out))
    written = 0
    for ep in episodes:
        written += _log_episode(rr, rec, ep)
    rec.flush()
    rec.disconnect()
    return written


def _log_episode(rr, rec, ep: Episode) -> int:
    root, steps = ep.name, ep.steps
    marks = read_marks(ep.path)
    t = np.asarray(steps["frame_captured_at"], dtype=np.float64)
    rel = t - t[0] if len(t) else t
    excluded = marks.excluded(t) if len(t) else np.zeros(0, bool)
    rec.log(f"{root}/info", rr.TextDocument(_info(ep, marks.describe())), static=True)
    for i in range(ep.n):
        rec.set_time("step", sequence=int(steps["index"][i]))
        rec.set_time("time", duration=float(rel[i]))
        rec.log(f"{root}/camera", rr.Image(np.asarray(ep.frames[i])))
        rec.log(f"{root}/speed", rr.Scalars(float(steps["speed_mps"][i])))
        for who, column in ACTIONS:
            action = np.asarray(steps[column][i], dtype=np.float64)
            if np.all(np.isfinite(action)):  # the policy's is NaN where the person drove
                rec.log(f"{root}/action/{who}/steering", rr.Scalars(float(action[0])))
                rec.log(f"{root}/action/{who}/throttle", rr.Scalars(float(action[1])))
        mu = np.asarray(steps["plan_mu"][i], dtype=np.float64)
        if mu.size and np.all(np.isfinite(mu)):
            rec.log(f"{root}/plan/mu", rr.LineStrips2D([mu.reshape(-1, 2)]))
        rec.log(f"{root}/mode", rr.Scalars(float(steps["mode"][i])))
        rec.log(f"{root}/collision", rr.Scalars(float(ep.collision[i])))
        rec.log(f"{root}/excluded", rr.Scalars(float(excluded[i])))
        if steps["lap"][i]:
            rec.log(f"{root}/events", rr.TextLog("lap"))
        if steps["estop"][i] and (i == 0 or not steps["estop"][i - 1]):
            rec.log(f"{root}/events", rr.TextLog("e-stop", level="WARN"))
    return ep.n


def _info(ep: Episode, marks: str) -> str:
    modes = {int(m): Mode(int(m)).name for m in np.unique(ep.steps["mode"])} if ep.n else {}
    return (
        f"episode {ep.name}: {ep.n} steps, {ep.duration_s:.1f} s, end {ep.end_reason}\n"
        f"modes: {', '.join(f'{k} = {v}' for k, v in sorted(modes.items()))}\n"
        f"marks: {marks}"
    )
