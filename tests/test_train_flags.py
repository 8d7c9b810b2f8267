"""Training never sees the steps `carrt episodes mark --exclude-flag` excludes (issue 68, item
3): the episode is read as the segments around a frozen camera's steps."""

from __future__ import annotations

import numpy as np
from episode_factory import image_for, make_step, run_cli, write_episode

from training.episodes import load_episodes


def test_training_reads_around_the_steps_a_flag_excluded(tmp_path):
    eps = tmp_path / "eps"
    steps = [make_step(i, image=image_for(10) if 10 <= i < 20 else image_for(i)) for i in range(40)]
    path = write_episode(eps, steps)
    assert run_cli(["episodes", "mark", str(path), "--exclude-flag", "frozen-camera"]) == 0
    episodes = load_episodes([eps])
    assert [(ep.name, ep.start, ep.n) for ep in episodes] == [
        (f"{path.name}#0", 0, 10),
        (f"{path.name}#1", 20, 20),
    ]
    frozen = image_for(10)
    kept = [frame for ep in episodes for frame in ep.frames]
    assert not any(np.array_equal(frame, frozen) for frame in kept)  # all ten copies out
