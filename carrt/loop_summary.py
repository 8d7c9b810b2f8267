"""What one driving session did, as the loop reports it at exit: rate, overruns, section
timings, frame → command latency, tick lateness, and the counts `carrt report` agrees with.

Its own module so the loop reads as the tick and nothing else; `--summary-json` writes
`to_dict()`, which the benchmarks and tests read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

SECTIONS = ("capture", "preprocess", "inference", "arbitration", "actuation", "logging")


@dataclass
class LoopSummary:
    steps: int = 0
    duration_s: float = 0.0
    overruns: int = 0
    skipped_inferences: int = 0
    sections_ms: dict[str, tuple[float, float]] = field(default_factory=dict)
    frame_to_command_ms: tuple[float, float] = (math.nan, math.nan)
    tick_lateness_ms: tuple[float, float] = (math.nan, math.nan)  # tick start - its frame
    max_tick_lateness_ms: float = math.nan
    interventions: int = 0
    collisions: int = 0
    laps: int = 0  # by carrt/laps.py's rule, the same count as the simulator's and carrt report's
    estops: int = 0
    episodes: int = 0
    recorded_steps: int = 0
    dropped_steps: int = 0
    write_error: str | None = None  # the episode writer's one line when recording failed
    modes_s: dict[str, float] = field(default_factory=dict)

    @property
    def achieved_hz(self) -> float:
        return self.steps / self.duration_s if self.duration_s > 0 else 0.0

    def render(self) -> str:
        lines = [
            f"loop: {self.steps} ticks in {self.duration_s:.1f} s = {self.achieved_hz:.2f} Hz, "
            f"{self.overruns} overruns, {self.skipped_inferences} late inferences skipped",
            "  section        p50 ms   p99 ms",
        ]
        for name in SECTIONS:
            p50, p99 = self.sections_ms.get(name, (math.nan, math.nan))
            lines.append(f"  {name:<12} {p50:8.2f} {p99:8.2f}")
        p50, p99 = self.frame_to_command_ms
        lines.append(f"  frame→command {p50:7.2f} {p99:8.2f}")
        p50, p99 = self.tick_lateness_ms
        lines.append(
            f"  tick lateness {p50:7.2f} {p99:8.2f}   (max {self.max_tick_lateness_ms:.2f})"
        )
        lines.append(
            f"  collisions {self.collisions}, interventions {self.interventions}, laps "
            f"{self.laps}, e-stops {self.estops}, episodes "
            f"{self.episodes}, steps recorded {self.recorded_steps}, dropped {self.dropped_steps}"
        )
        if self.write_error:
            lines.append(f"  RECORDING FAILED: {self.write_error}")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        return {**self.__dict__, "achieved_hz": self.achieved_hz}


def percentiles(values: list[float]) -> tuple[float, float]:
    if not values:
        return (math.nan, math.nan)
    p50, p99 = np.percentile(np.asarray(values) * 1e3, [50, 99])
    return (float(p50), float(p99))
