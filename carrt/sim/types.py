"""The simulator's shared data: what a track is, where the car is, how the camera sits.

Coordinates: metres, x to the right along the arena's long side, y up along the short side,
origin at the arena's lower-left corner; yaw in radians, counter-clockwise from +x. The arena
is the paper's fenced 6.7 m × 3.8 m floor.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

ARENA_W = 6.7
ARENA_H = 3.8

RGB = tuple[int, int, int]


@dataclass(frozen=True)
class Obstacle:
    """A cylinder standing on the floor (a bucket or cone, as on the paper's track)."""

    x: float
    y: float
    radius: float
    height: float
    colour: RGB


@dataclass(frozen=True)
class Track:
    """A closed track inside the fenced arena, with obstacles placed on it.

    centerline and racing_line are closed polylines (first point not repeated at the end),
    sampled densely (every few centimetres) so consumers can treat them as curves.
    """

    name: str  # layout name: "empty", "easy", "hard" or "mixed"
    seed: int
    centerline: np.ndarray  # (N, 2) float64
    width: float  # drivable width in metres (boundary markings at ±width/2)
    racing_line: np.ndarray  # (M, 2) float64, inside the track, obstacles not considered
    obstacles: tuple[Obstacle, ...] = ()
    arena: tuple[float, float] = (ARENA_W, ARENA_H)
    fence_height: float = 0.3
    fence_colour: RGB = (235, 235, 235)
    floor_colour: RGB = (70, 70, 75)
    marking_colour: RGB = (250, 250, 250)
    centre_marking_colour: RGB = (240, 200, 40)
    length: float = field(default=0.0)  # centerline length in metres (filled by the builder)


@dataclass
class CarState:
    """The simulated car. Speeds in m/s, angles in radians."""

    x: float
    y: float
    yaw: float
    v: float = 0.0  # forward speed
    yaw_rate: float = 0.0
    steer: float = 0.0  # front wheel angle reached (servo lag), + left (CCW), = −command
    motor: float = 0.0  # drive command actually reached (ESC/motor lag), [-1, 1]
    sliding: bool = False  # asked for more lateral grip than the tyres have
    odometer: float = 0.0  # wheel distance travelled (drives the encoder)
    encoder_ticks: int = 0


@dataclass(frozen=True)
class CameraParams:
    """The car's camera: mounted on the car's centreline, looking forward and down."""

    height_m: float = 0.12
    pitch_deg: float = 20.0  # downwards from horizontal
    fov_deg: float = 100.0  # horizontal field of view
    forward_m: float = 0.05  # ahead of the rear axle-centre reference point
    width: int = 96
    height: int = 96
