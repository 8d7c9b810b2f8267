"""The simulator's obstacle layouts, by name: how many obstacles, and which random stream their
placements come from. The one place to add a layout (the CLI's choices are read from here). It
lives outside carrt/sim/ so the car's CLI can list the names without importing the simulator.

Each layout names its own stream number. Placements used to be seeded from a layout's position
in the list, so inserting a layout silently moved every later layout's obstacles, the held-out
evaluation placements included; the streams below are those positions, frozen, so every
placement measured so far stays where it was and a new layout takes a new number.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Layout:
    obstacles: int | tuple[int, int]  # a fixed count, or (low, high) drawn per placement seed
    stream: int  # the rng stream of this layout's placements: never reuse or renumber


# "mixed" is the paper's training setting (random positions, colours AND numbers); "hard" stays
# fixed for evaluation.
LAYOUTS: dict[str, Layout] = {
    "empty": Layout(0, stream=0),
    "easy": Layout(2, stream=1),
    "hard": Layout(8, stream=2),
    "mixed": Layout((4, 10), stream=3),
}
NAMES = tuple(LAYOUTS)
