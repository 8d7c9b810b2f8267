"""Training honours marks (issue 60, item 1): every excluded step is out of every stage's
samples (imitation targets, world-model windows and their future frames), no window spans an
excluded range, a whole excluded episode is gone, and the frames come from the right offsets,
also when a DataLoader worker reads them again."""

from __future__ import annotations

import numpy as np
import torch
from episode_factory import image_for, make_step, run_cli, write_episode

from carrt.episodes.marks import read_marks
from training.data import ImitationDataset, WindowDataset
from training.episodes import load_episodes

STEPS = 50


def test_training_leaves_every_excluded_step_out_of_every_stage(tmp_path):
    """Two episodes: one with 1.0–2.0 s excluded, one excluded whole. Imitation samples, world
    model windows (their frames, future frames and actions) and the frame counts never hold an
    excluded step, and no window spans the cut."""
    eps = tmp_path / "eps"
    kept = write_episode(eps, [make_step(i, seed=1) for i in range(STEPS)])
    gone = write_episode(eps, [make_step(i, seed=2) for i in range(STEPS)])
    run_cli(["episodes", "mark", str(kept), "--exclude", "1.0-2.0"])
    run_cli(["episodes", "mark", str(gone), "--exclude-all"])
    episodes = load_episodes([eps])
    assert [ep.n for ep in episodes] == [10, 30] and sum(ep.n for ep in episodes) == 40
    assert [ep.name for ep in episodes] == [f"{kept.name}#0", f"{kept.name}#1"]
    excluded_speeds = {float(make_step(i, seed=1).speed_mps) for i in range(10, 20)}
    excluded_speeds |= {float(make_step(i, seed=2).speed_mps) for i in range(STEPS)}
    windows = WindowDataset(episodes, horizon=10, predict_size=16)
    batch = windows.get_batch(np.arange(len(windows)))
    seen = set(np.round(batch["speed"].numpy().ravel(), 6))
    seen |= set(np.round(batch["future_speeds"].numpy().ravel(), 6))
    assert not seen & {round(s, 6) for s in excluded_speeds}
    imitation = ImitationDataset(episodes, horizon=10, store=windows.store)
    speeds = imitation.get_batch(np.arange(len(imitation)))["speed"].numpy().ravel()
    assert not set(np.round(speeds, 6)) & {round(s, 6) for s in excluded_speeds}
    # the frames the store holds are the kept steps' frames, read from the right offsets
    store = windows.store
    assert torch.equal(store.frames[10], torch.from_numpy(image_for(20, seed=1)))
    store.__setstate__(store.__getstate__())  # as a DataLoader worker reads them again
    assert torch.equal(store.frames[10], torch.from_numpy(image_for(20, seed=1)))
    assert read_marks(kept).exclude == [(1.0, 2.0)]
