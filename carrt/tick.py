"""One tick of the control loop, and the two records made from it: the Step an episode keeps
and the LiveStatus a watcher sees.

Why here: the tick's values are named once (`Tick`, filled in stage by stage: sense → infer →
arbitrate → actuate → record), and each record is a function of them plus only what that
record adds (a step's index and wall time; the view's counts, the link's state and the last
plan), so the episode and the screen cannot spell one measured value two ways.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from carrt.interfaces import LiveStatus, Mode, Plan, Step

if TYPE_CHECKING:
    from carrt.arbitration import Decision
    from carrt.interfaces import Board
    from carrt.loop_summary import LoopSummary

NAN2 = (math.nan, math.nan)


@dataclass
class Tick:
    """One tick's values, handed from stage to stage; each stage fills in its part."""

    start: float  # when the tick started on the loop's clock (on a frame's arrival)
    now: float = math.nan  # when the arbiter decided
    frame: Any = None  # CameraFrame | None
    joystick: Any = None  # JoystickState
    telemetry: Any = None  # TelemetrySample | None
    collided: bool = False
    image: np.ndarray | None = None  # the preprocessed 96×96 frame
    speed: float = 0.0
    plan: Any = None  # Plan | None: a fresh plan this tick
    plan_action: tuple[float, float] | None = None
    fallback_action: tuple[float, float] | None = None
    decision: Decision | None = None
    rebooted: str = ""  # the board rebooted since the last tick: the line naming it
    executed: tuple[float, float] = (0.0, 0.0)
    noisy: bool = False
    sent_at: float = math.nan

    @property
    def human(self) -> tuple[float, float]:
        """What the person's sticks (or keys) said."""
        return self.joystick.steering, self.joystick.throttle

    def step(self, index: int, wall_time: float) -> Step:
        """The tick as an episode records it (a tick with an image: the loop checks)."""
        decision, telemetry, plan = self.decision, self.telemetry, self.plan
        return Step(
            index=index,
            image=self.image,
            frame_captured_at=self.frame.captured_at,
            command_sent_at=self.sent_at,
            wall_time=wall_time,
            speed_mps=self.speed,
            encoder_ticks=telemetry.telemetry.encoder_ticks if telemetry else 0,
            human_action=self.human,
            policy_action=self.plan_action if self.plan_action is not None else NAN2,
            executed_action=self.executed,
            mode=decision.mode,
            override=decision.override,
            estop=decision.mode == Mode.ESTOP,
            noise=self.noisy,
            collision=self.collided,
            lap=self.joystick.events.lap,
            plan_mu=None if plan is None else plan.mu,
            plan_sigma=None if plan is None else plan.sigma,
        )

    def live_status(
        self,
        *,
        count: int,
        estop_reason: str,
        plan: Plan | None,
        sections_s: dict[str, float],
        link: Board,
        recording: bool,
        summary: LoopSummary,
        alert: str,
        notices: tuple[tuple[float, str], ...],
    ) -> LiveStatus:
        """The tick as a watcher sees it, with what only the view adds: the tick's number, the
        e-stop's cause, the last fresh plan, the sections' timings, the link's state and the
        session's counts."""
        decision = self.decision
        return LiveStatus(
            mode=decision.mode,
            why=estop_reason if decision.mode == Mode.ESTOP else decision.reason,
            speed_mps=self.speed,
            human=self.human,
            executed=self.executed,
            recording=recording,
            episodes=summary.episodes,
            collisions=summary.collisions,
            laps=summary.laps,
            tick=count,
            deadline=self.start,
            frame=self.frame,
            image=self.image,
            policy=self.plan_action if self.plan_action is not None else self.fallback_action,
            plan=plan,
            sections_s=sections_s,
            board_state=getattr(link.board_state, "name", str(link.board_state)),
            telemetry_age_s=link.telemetry_age_s(),
            link_counters=dict(vars(link.counters)),  # a few ints: a copy costs ~1 µs
            alert=alert,
            notices=notices,
        )
