"""What is in an episode, as numbers: the summary behind `carrt episodes ls` and `show`.

These exist so a human can check a recording before it goes into training: that the e-stops and
collisions are where they remember them, that the noise injection was on for about half of the
time. Numpy only, so the car lists its episodes without OpenCV.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

import numpy as np

from carrt.episodes import flags as suspect
from carrt.episodes.marks import read_marks
from carrt.episodes.reader import Episode, collision_events, estop_count, speed_stats
from carrt.interfaces import Mode


def summarize(ep: Episode) -> dict[str, Any]:
    steps = ep.steps
    avg, top = speed_stats(steps["speed_mps"], steps["mode"])
    counts = ep.meta.get("counts") or {}
    model = ep.meta.get("model") or {}
    n = ep.n
    marks = read_marks(ep.path)
    excluded = marks.excluded(steps["frame_captured_at"]) if n else np.zeros(0, dtype=bool)
    found = suspect.find_flags(ep)
    return {
        "name": ep.name,
        "path": str(ep.path),
        "command": ep.meta.get("command") or ep.meta.get("session"),
        "start": (ep.meta.get("start") or {}).get("time"),
        "duration_s": ep.duration_s,
        "frames": n,
        "avg_speed_mps": avg,
        "top_speed_mps": top,
        "interventions": int(np.count_nonzero(steps["override"])),
        "estops": estop_count(steps),
        "noise_share": float(np.count_nonzero(steps["noise"]) / n) if n else 0.0,
        "auto_share": float(np.count_nonzero(steps["mode"] == int(Mode.AUTO)) / n) if n else 0.0,
        "collisions": len(collision_events(steps, (ep.meta.get("end") or {}).get("reason"))),
        "collision_frames": int(ep.collision.sum()),
        "laps_marked": int(np.count_nonzero(steps["lap"])),
        "dropped": counts.get("dropped"),
        "end_reason": ep.end_reason,
        "torn_tail": ep.torn,
        "damage": None if ep.damage is None else asdict(ep.damage),
        "marks": marks.describe(),
        "excluded_steps": int(excluded.sum()),
        # name: [[start, end), ...] steps; with each range's wording for show
        "flags": {name: [list(r) for r in ranges] for name, ranges in found.items()},
        "flag_lines": [
            _flag_line(n, r, steps["frame_captured_at"], excluded) for n, r in found.items()
        ],
        "model_sha256": model.get("sha256"),
    }


def _flag_line(name: str, ranges: suspect.Ranges, t: np.ndarray, excluded: np.ndarray) -> str:
    counted = "" if suspect.is_fault(name) else f"{len(ranges)} (counted, not a fault), "
    line = f"{name}: {counted}{suspect.describe_ranges(ranges, t)}"
    if all(b > a and excluded[a:b].all() for a, b in ranges):
        line += " (excluded)"
    return line


def format_summary(summary: dict[str, Any]) -> str:
    dropped = "unknown (no end metadata)" if summary["dropped"] is None else summary["dropped"]
    damage = summary.get("damage")
    lines = [
        f"episode        {summary['name']}  ({summary['path']})",
        f"recorded by    {summary['command'] or '?'} at {summary['start'] or '?'}",
        f"duration       {summary['duration_s']:.1f} s, {summary['frames']} frames",
        f"speed          average {summary['avg_speed_mps']:.2f} m/s, "
        f"top {summary['top_speed_mps']:.2f} m/s (while driving)",
        f"interventions  {summary['interventions']}, e-stops {summary['estops']}, "
        f"collisions {summary['collisions']} ({summary['collision_frames']} frames labelled)",
        f"noise          {summary['noise_share']:.0%} of steps; AUTO {summary['auto_share']:.0%}",
        f"laps marked    {summary['laps_marked']}",
        f"dropped        {dropped}",
        f"end            {summary['end_reason']}"
        + ("  (torn tail ignored)" if summary["torn_tail"] else "")
        + (f"  (CORRUPTED at step {damage['step']}: {damage['where']})" if damage else "")
        + ("  (empty: no step was written before the run ended)" if not summary["frames"] else ""),
        f"model          {summary['model_sha256'] or '-'}",
        f"marks          {summary['marks']}"
        + (
            f" ({summary['excluded_steps']} steps out of training)"
            if summary["excluded_steps"]
            else ""
        ),
    ]
    flag_lines = summary.get("flag_lines") or ["none"]
    lines += [f"{'flags' if i == 0 else '':<15}{line}" for i, line in enumerate(flag_lines)]
    return "\n".join(lines)
