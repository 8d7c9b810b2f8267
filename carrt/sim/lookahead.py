"""What a person watching the car sees coming: will it hit something if it carries on like this?

The simulated safety driver (SimPilot with intervene=True) takes the sticks when this says yes.
It sweeps the car's body along the arc it is on now (its speed and yaw rate held) and checks
each pose against the obstacles and the fence, with a margin: a person reacts to "about to
hit", not to "touching". Ground truth is fine here: it decides WHEN the stand-in person takes
over, it is never a training input.
"""

from __future__ import annotations

import math

from carrt.sim.types import CarState

HORIZON_S = 0.6  # how far ahead a person judges a crash as imminent
MARGIN_M = 0.03  # closer than this counts as a hit
MIN_SPEED = 0.3  # a car creeping towards a bucket still gets there: judge it at least this fast
STEP_S = 0.05


def collision_ahead(
    world, horizon_s: float = HORIZON_S, margin: float = MARGIN_M, state: CarState | None = None
) -> bool:
    """True when the car's body, swept forward on its current arc, comes within `margin` of an
    obstacle or the fence within `horizon_s` seconds."""
    car = world.car if state is None else state
    v = max(car.v, MIN_SPEED)
    yaw_rate = car.yaw_rate if car.v > 1e-6 else 0.0
    x, y, yaw = car.x, car.y, car.yaw
    for k in range(1, math.ceil(horizon_s / STEP_S) + 1):
        t = k * STEP_S
        heading = yaw + yaw_rate * t
        if abs(yaw_rate) > 1e-6:
            px = x + v / yaw_rate * (math.sin(heading) - math.sin(yaw))
            py = y - v / yaw_rate * (math.cos(heading) - math.cos(yaw))
        else:
            px, py = x + v * t * math.cos(yaw), y + v * t * math.sin(yaw)
        obstacle, fence = world.body_gaps(CarState(px, py, heading))
        if fence < margin or obstacle <= margin:
            return True
    return False
