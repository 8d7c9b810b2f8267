"""What the loop does with a plan when the policy is late: its next step once, then neutral.

Kept apart from carrt.policy (onnxruntime) so the loop, and teleop without a model, import no
inference runtime.
"""

from __future__ import annotations

from carrt.interfaces import Plan


class PlanBuffer:
    """The loop's rule: on an overrun, the next step of the previous plan may be used once; then
    neutral. A plan is a prediction from an older frame, so it is trusted for one extra
    period at most (the paper's horizon exists for training, not for driving blind).
    """

    def __init__(self) -> None:
        self._plan: Plan | None = None
        self._spent = True

    @property
    def plan(self) -> Plan | None:
        """The last fresh plan (for recording plan_mu / plan_sigma)."""
        return self._plan

    def fresh(self, plan: Plan) -> tuple[float, float]:
        """Store a new plan; return its first step, the action to execute now."""
        self._plan = plan
        self._spent = False
        return float(plan.mu[0, 0]), float(plan.mu[0, 1])

    def fallback(self) -> tuple[float, float] | None:
        """The previous plan's next step, the first time after a fresh plan; else None
        (the caller sends neutral)."""
        if self._spent or self._plan is None or len(self._plan.mu) < 2:
            self._spent = True
            return None
        self._spent = True
        return float(self._plan.mu[1, 0]), float(self._plan.mu[1, 1])

    def clear(self) -> None:
        """Forget the plan (mode change, disarm, e-stop): nothing stale survives it."""
        self._plan = None
        self._spent = True
