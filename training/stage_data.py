"""The data one iteration reads: the episodes split by placement, and the datasets every stage
trains on, over frames decoded once into RAM (data.FrameStore).

Split from iteration.py so that file reads as the run, top to bottom. The world model may learn
other episodes than the policy imitates and is refined on (--world-episodes, WorldEpisodes):
refinement always starts from the policy's own windows, the states it is refined in.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from training.config import TrainingConfig, UsageError
from training.data import (
    FrameStore,
    ImitationDataset,
    WindowDataset,
    load_episodes,
    split_by_placement,
)


def read_episodes(cfg: TrainingConfig) -> tuple[list, list, list]:
    """(all, train, validation): validation holds out whole placements."""
    episodes = _load(cfg.episodes, "--episodes")
    train_eps, val_eps = split_by_placement(episodes, cfg.val_fraction, cfg.seed)
    return episodes, train_eps, val_eps


def _load(dirs: tuple[str, ...], option: str) -> list:
    """The episodes under `dirs`; a missing directory or none with steps is a UsageError."""
    missing = [e for e in dirs if not Path(e).exists()]
    if missing:
        raise UsageError(f"{option} {missing[0]}: no such directory")
    episodes = load_episodes(list(dirs)) if dirs else []
    if not episodes:
        raise UsageError(f"no episodes with steps under {', '.join(dirs) or '(none given)'}")
    return episodes


@dataclass
class WorldEpisodes:
    """The episodes the world model learns when they are not the policy's (--world-episodes):
    split by placement like the policy's, so its held-out losses are on placements it never saw."""

    all: list
    train: list
    val: list


def read_world_episodes(cfg: TrainingConfig) -> WorldEpisodes | None:
    """None when the world model learns --episodes (the default)."""
    if not cfg.world_episodes:
        return None
    episodes = _load(cfg.world_episodes, "--world-episodes")
    return WorldEpisodes(episodes, *split_by_placement(episodes, cfg.val_fraction, cfg.seed))


class StageData:
    """The datasets every stage reads, over frames decoded once into RAM (data.FrameStore)."""

    def __init__(
        self,
        cfg: TrainingConfig,
        train_eps: list,
        val_eps: list,
        world: WorldEpisodes | None = None,
    ) -> None:
        self.cfg, self.train_eps, self.val_eps = cfg, train_eps, val_eps
        self.horizon = cfg.profile_obj.horizon
        self.store = FrameStore(train_eps)
        self.windows, self.val_windows, self.val_store = self._windows(train_eps, val_eps,
                                                                       self.store)  # fmt: skip
        if len(self.windows) == 0:
            raise UsageError("no training windows: every training episode has fewer than 2 steps")
        # the world model's windows: the policy's, or --world-episodes' (refinement still
        # starts from the policy's windows: the states the policy is refined in)
        self.world_windows, self.world_val_windows = self.windows, self.val_windows
        if world is not None:
            self.world_windows, self.world_val_windows, _ = self._windows(world.train, world.val)
            if len(self.world_windows) == 0:
                raise UsageError("no world-model windows: every --world-episodes training "
                                 "episode has fewer than 2 steps")  # fmt: skip

    def _windows(self, train_eps: list, val_eps: list, store: FrameStore | None = None):
        """(training windows, held-out windows or None, the held-out frames' store)."""
        h, size = self.horizon, self.cfg.profile_obj.predict_size
        takeovers = self.cfg.takeovers_as_collisions
        store = store or FrameStore(train_eps)
        windows = WindowDataset(
            train_eps, h, predict_size=size, takeovers_as_collisions=takeovers, store=store
        )
        val_store = FrameStore(val_eps) if val_eps else None
        val = (
            WindowDataset(val_eps, h, predict_size=size, takeovers_as_collisions=takeovers,
                          store=val_store) if val_eps else None
        )  # fmt: skip
        return windows, val, val_store

    def demonstrations(self) -> ImitationDataset:
        """The training windows a person drove (imitation's targets; refinement's safeguard)."""
        iw, h = self.cfg.intervention_weight, self.horizon
        return ImitationDataset(self.train_eps, h, intervention_weight=iw, store=self.store)

    def imitation(self):
        iw, h = self.cfg.intervention_weight, self.horizon
        free = self.demonstrations()
        val = None
        if self.val_eps:
            val = ImitationDataset(self.val_eps, h, intervention_weight=iw, store=self.val_store)
        if len(free) == 0 and self.cfg.imitation_steps > 0:
            raise UsageError("no collision-free MANUAL steps in the training episodes to imitate")
        return free, val
