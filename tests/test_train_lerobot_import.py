"""Episodes imported from carrt's LeRobotDataset export train as the recorded ones do: the same
windows, the same targets, the same normalisation but for the frames' codec error, and the
imitation stage's loss falls on them as on the recorded ones (tiny profile, 40 steps)."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from train_stage_rig import first_last, models, stage_data, tiny  # noqa: E402

from carrt.episodes.lerobot_export import export_lerobot  # noqa: E402
from carrt.episodes.lerobot_import import import_lerobot  # noqa: E402
from training.imitation import train_imitation  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def test_imported_episodes_train_like_the_recorded_ones(sim_episodes, tmp_path):
    export_lerobot([str(sim_episodes)], tmp_path / "lerobot")
    import_lerobot(tmp_path / "lerobot", tmp_path / "imported")
    recorded = stage_data(sim_episodes)
    imported = stage_data(tmp_path / "imported")
    assert [ep.n for ep in imported[0]] == [ep.n for ep in recorded[0]]
    assert len(imported[2]) == len(recorded[2]) and len(imported[3]) == len(recorded[3])
    for i in range(0, len(recorded[3]), 7):  # the imitation targets: a* exactly
        a, b = recorded[3][i], imported[3][i]
        assert torch.equal(a["expert_actions"], b["expert_actions"])
        assert (a["image"].int() - b["image"].int()).abs().max() <= 2  # levels of 255
    losses = []
    for _, norm, _, free in (recorded, imported):
        policy, _ = models(norm)
        cfg = tiny(imitation_steps=40, imitation_batch_size=8, imitation_lr=3e-3)
        first, last = first_last(train_imitation(cfg, policy, free).history)
        assert last < 0.9 * first, (first, last)
        losses.append(last)
    assert np.isclose(losses[0], losses[1], rtol=0.1), losses
