"""Crash-safe episode recording and reading (docs/episodes.md). The reader needs numpy alone."""

from carrt.episodes.format import SCHEMA, STEP_DTYPE, run_metadata, step_dtype
from carrt.episodes.reader import (
    Episode,
    collision_events,
    collision_labels,
    iter_episodes,
    list_episodes,
    read_episode,
)
from carrt.episodes.writer import EpisodeWriter

__all__ = [
    "SCHEMA",
    "STEP_DTYPE",
    "Episode",
    "EpisodeWriter",
    "collision_events",
    "collision_labels",
    "iter_episodes",
    "list_episodes",
    "read_episode",
    "run_metadata",
    "step_dtype",
]
