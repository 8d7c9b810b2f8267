"""The simulator's episodes as the DIRL stages' tests use them, and tiny models to train on them.

The imitation (test_train_imitation.py), world-model and refinement (test_train_stages.py) and
stage-runner (test_train_trainer.py) tests all start from the same dataset views, the tiny
profile and freshly seeded networks; one copy of that set-up keeps them comparable. Needs the
train extra (torch), as every test_train_* module does.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from training.config import PRESETS, TrainingConfig
from training.data import ImitationDataset, WindowDataset, compute_normalisation, load_episodes
from training.models import PolicyNet, WorldModel


def stage_data(sim_episodes):
    """(episodes, normalisation, windows, imitation data) of the recorded simulator dataset;
    each test module wraps it in a module-scoped `data` fixture."""
    episodes = load_episodes([sim_episodes])
    norm = compute_normalisation(episodes)
    windows = WindowDataset(episodes, 10, predict_size=16)
    free = ImitationDataset(episodes, 10)
    return episodes, norm, windows, free


def tiny(**overrides) -> TrainingConfig:
    cfg = dataclasses.replace(TrainingConfig(profile="tiny"), **PRESETS["tiny"], progress=False)
    return dataclasses.replace(cfg, **overrides)


def models(norm, seed=0):
    torch.manual_seed(seed)
    profile = tiny().profile_obj
    policy, world_model = PolicyNet(profile), WorldModel(profile)
    policy.set_normalisation(norm)
    world_model.set_normalisation(norm)
    return policy, world_model


def first_last(history, key="loss", n=5):
    values = [h[key] for h in history]
    return float(np.mean(values[:n])), float(np.mean(values[-n:]))
