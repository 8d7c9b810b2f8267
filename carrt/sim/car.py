"""The 1/20-scale car: a kinematic bicycle with servo and ESC lag, a tyre grip limit and an encoder.

Kinematic rather than dynamic: at this scale and these speeds the tyres barely slip until they
saturate, and a kinematic model stays stable at any step size, where a dynamic tyre model at
0.14 m wheelbase would need sub-millisecond steps. What the kinematic model misses is the
saturation, so it is added explicitly: past the grip limit the yaw rate is capped at what the
tyres can give (the car understeers wide) and the slide scrubs speed.

Steering follows the protocol: command −1 (a `steer_left_us` pulse) is full LEFT lock, which in
the arena's x-right/y-up frame is a counter-clockwise turn (positive yaw rate). `CarState.steer`
is the physical front-wheel angle, positive to the left like yaw, so it is minus the command's
sign; only `step_car` converts between the two.

The reference point is the rear axle's centre (where a kinematic bicycle's velocity points
along the heading); the body extends `rear_overhang` behind it.

Pure Python floats, no numpy: one step is a few dozen float operations, and numpy's per-call
overhead would cost more than the arithmetic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from carrt.sim.types import CarState

_STOPPED = 1e-9


@dataclass(frozen=True)
class CarParams:
    """Physical constants; the defaults are a 1/20-scale brushed RC car on a smooth floor."""

    wheelbase: float = 0.14
    width: float = 0.10
    length: float = 0.20
    rear_overhang: float = 0.03  # body behind the rear axle
    max_steer: float = 0.45  # front wheel angle at full lock, rad
    steer_tau: float = 0.08  # servo: first-order time constant, s
    motor_tau: float = 0.25  # ESC + motor spin-up: first-order time constant, s
    top_speed: float = 2.5  # where full throttle settles, m/s
    max_accel: float = 5.0  # full throttle from standstill, m/s²
    max_brake: float = 7.0  # full reverse command while rolling forward, m/s²
    reverse_speed: float = 1.0  # where full reverse settles, m/s
    rolling_decel: float = 0.3  # rolling resistance, m/s² (a small command does not move it)
    mu: float = 0.75  # tyre grip: lateral acceleration limit mu·g ≈ 7.4 m/s²
    g: float = 9.81
    scrub: float = 0.35  # sliding: deceleration per m/s² of lateral demand the tyres cannot meet
    ticks_per_metre: float = 200.0
    max_substep: float = 0.005  # internal integration step, s

    @property
    def drag(self) -> float:
        """Linear drag per m/s, chosen so full throttle settles exactly at top_speed."""
        return (self.max_accel - self.rolling_decel) / self.top_speed

    @property
    def max_lateral_accel(self) -> float:
        return self.mu * self.g

    @property
    def min_turn_radius(self) -> float:
        """Rear-axle radius at full lock, below the grip limit."""
        return self.wheelbase / math.tan(self.max_steer)


def step_car(
    state: CarState, params: CarParams, dt: float, steering_cmd: float, throttle_cmd: float
) -> CarState:
    """Advance the car by dt seconds holding the commands (both clipped to [-1, 1]).

    steering_cmd −1 is full left lock (the protocol's sign; +1 full right). throttle_cmd > 0
    drives forward; < 0 brakes while rolling forward and drives in reverse once stopped (a car
    ESC's brake-then-reverse).
    """
    if dt <= 0:
        return _copy(state, sliding=state.sliding)
    p = params
    n = max(1, math.ceil(dt / p.max_substep - 1e-9))
    h = dt / n
    steer_target = -_clip(steering_cmd) * p.max_steer  # command −1 (left) → wheels left (+)
    motor_target = _clip(throttle_cmd)
    k_steer = 1.0 - math.exp(-h / p.steer_tau) if p.steer_tau > 0 else 1.0
    k_motor = 1.0 - math.exp(-h / p.motor_tau) if p.motor_tau > 0 else 1.0
    drag = p.drag
    a_lat_max = p.max_lateral_accel
    x, y, yaw, v = state.x, state.y, state.yaw, state.v
    steer, motor, odometer = state.steer, state.motor, state.odometer
    yaw_rate = 0.0
    sliding = False
    for _ in range(n):
        steer += (steer_target - steer) * k_steer
        motor += (motor_target - motor) * k_motor
        v = _longitudinal(v, motor, h, p, drag)
        yaw_rate = v * math.tan(steer) / p.wheelbase
        demand = abs(v * yaw_rate)
        if demand > a_lat_max:
            sliding = True
            yaw_rate = math.copysign(a_lat_max / abs(v), yaw_rate)
            loss = p.scrub * (demand - a_lat_max) * h
            v = math.copysign(max(abs(v) - loss, 0.0), v)
        mid = yaw + 0.5 * yaw_rate * h
        x += v * math.cos(mid) * h
        y += v * math.sin(mid) * h
        yaw += yaw_rate * h
        odometer += abs(v) * h
    yaw = (yaw + math.pi) % (2 * math.pi) - math.pi
    return CarState(
        x=x,
        y=y,
        yaw=yaw,
        v=v,
        yaw_rate=yaw_rate,
        steer=steer,
        motor=motor,
        sliding=sliding,
        odometer=odometer,
        encoder_ticks=math.floor(odometer * p.ticks_per_metre),
    )


def _longitudinal(v: float, motor: float, h: float, p: CarParams, drag: float) -> float:
    """Speed after h seconds; resistances and brakes stop the car, they never reverse it."""
    if v > _STOPPED:
        push = p.max_accel * motor if motor >= 0 else p.max_brake * motor
        new = v + (push - drag * v - p.rolling_decel) * h
        return new if new > 0 or push > 0 else 0.0
    if v < -_STOPPED:
        reverse_accel = drag * p.reverse_speed + p.rolling_decel
        push = reverse_accel * motor if motor <= 0 else p.max_brake * motor
        new = v + (push - drag * v + p.rolling_decel) * h
        return new if new < 0 or push < 0 else 0.0
    # standing: it moves only when the push beats rolling resistance
    push = p.max_accel * motor if motor >= 0 else (drag * p.reverse_speed + p.rolling_decel) * motor
    if abs(push) <= p.rolling_decel:
        return 0.0
    return (push - math.copysign(p.rolling_decel, push)) * h


def footprint(state: CarState, params: CarParams) -> list[tuple[float, float]]:
    """The body's four corners (rear-right, front-right, front-left, rear-left) in the arena."""
    c, s = math.cos(state.yaw), math.sin(state.yaw)
    back, front = -params.rear_overhang, params.length - params.rear_overhang
    half = params.width / 2
    return [
        (state.x + c * lon - s * lat, state.y + s * lon + c * lat)
        for lon, lat in ((back, -half), (front, -half), (front, half), (back, half))
    ]


def body_centre(state: CarState, params: CarParams) -> tuple[float, float]:
    forward = params.length / 2 - params.rear_overhang
    return state.x + forward * math.cos(state.yaw), state.y + forward * math.sin(state.yaw)


def _clip(value: float) -> float:
    value = float(value)
    if value != value:  # NaN: a broken command is no command
        return 0.0
    return -1.0 if value < -1.0 else 1.0 if value > 1.0 else value


def _copy(state: CarState, **changes) -> CarState:
    fields = dict(state.__dict__)
    fields.update(changes)
    return CarState(**fields)
