"""The imitation stage on the simulator's episodes (tiny profile, a few dozen steps each).

Its loss must fall; it must learn a* (never the executed a), braking included, on
collision-free windows only, with the steps past an episode's end masked and the episode's
last action still a target.
"""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from train_stage_rig import first_last, models, stage_data, tiny  # noqa: E402

from training.imitation import imitation_loss, train_imitation  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def data(sim_episodes):
    return stage_data(sim_episodes)


def test_imitation_loss_falls(data):
    _, norm, _, free = data
    policy, _ = models(norm)
    cfg = tiny(imitation_steps=40, imitation_batch_size=8, imitation_lr=3e-3)
    result = train_imitation(cfg, policy, free)
    assert result.steps == 40 and len(result.history) == 40
    first, last = first_last(result.history)
    assert last < 0.9 * first, (first, last)


class _Relabelled(torch.utils.data.Dataset):
    """Real windows whose a* and executed a are set far apart, to see which one is learned."""

    def __init__(self, base, n=48):
        self.base, self.n = base, min(n, len(base))

    def __len__(self):
        return self.n

    def __getitem__(self, i):
        item = dict(self.base[i])
        item["expert_actions"] = torch.tensor([0.6, 0.9]).expand(10, 2).clone()
        item["actions"] = torch.tensor([-0.6, 0.1]).expand(10, 2).clone()
        return item


def test_imitation_learns_expert_actions_not_executed_ones(data):
    _, norm, _, free = data
    policy, _ = models(norm)
    cfg = tiny(imitation_steps=25, imitation_batch_size=8, imitation_lr=1e-2)
    train_imitation(cfg, policy, _Relabelled(free))
    batch = torch.utils.data.default_collate([free[i] for i in range(8)])
    policy.eval()
    with torch.no_grad():
        mu, _ = policy(batch["image"], batch["speed"])
    mean = mu.mean(dim=(0, 1))
    to_expert = (mean - torch.tensor([0.6, 0.9])).abs().max()
    to_executed = (mean - torch.tensor([-0.6, 0.1])).abs().max()
    assert to_expert < 0.2 < to_executed, mean


def test_imitation_loss_masks_steps_past_the_episode_end(data):
    _, norm, _, free = data
    policy, _ = models(norm)
    batch = torch.utils.data.default_collate([free[i] for i in range(4)])
    base, _ = imitation_loss(policy, batch)
    batch["weight"][:, 5:] = 0
    batch["expert_actions"][:, 5:] = 1e6  # would dominate if it were not masked
    masked, _ = imitation_loss(policy, batch)
    assert torch.isfinite(masked) and masked < 10 and masked != base


def test_the_last_action_of_an_episode_is_an_imitation_target(data):
    """Defect 6: the loss masked with `mask` (t+1+k < n), so a*_{n−1} was never a target."""
    episodes, norm, windows, free = data
    policy, _ = models(norm)
    i, ep = 0, episodes[0]
    row = int(np.flatnonzero((windows.index[:, 0] == i) & (windows.index[:, 1] == ep.n - 2))[0])
    batch = torch.utils.data.default_collate([windows[row]])  # no `weight`: action_mask
    assert batch["mask"][0, :2].tolist() == [1.0, 0.0]
    base, _ = imitation_loss(policy, batch)
    batch["expert_actions"][0, 1] = 100.0  # a*_{n−1}, the episode's last action
    assert imitation_loss(policy, batch)[0] > base + 1.0
    last = [k for k, (j, t) in enumerate(free.index) if j == i and t == ep.n - 1]
    if last:  # the last step itself is a start of the imitation data (when labelled)
        assert free[last[0]]["weight"][0] == 1.0


def test_imitation_learns_to_brake(data):
    """Defect 2: a* with negative throttle (the expert brakes) is learnable (tanh head)."""
    _, norm, _, free = data

    class Braking(_Relabelled):
        def __getitem__(self, i):
            item = dict(self.base[i])
            item["expert_actions"] = torch.tensor([0.0, -0.6]).expand(10, 2).clone()
            return item

    policy, _ = models(norm)
    train_imitation(tiny(imitation_steps=25, imitation_batch_size=8, imitation_lr=1e-2), policy,
                    Braking(free))  # fmt: skip
    batch = torch.utils.data.default_collate([free[i] for i in range(8)])
    policy.eval()
    with torch.no_grad():
        mu, _ = policy(batch["image"], batch["speed"])
    assert mu[..., 1].mean() < -0.4, mu[..., 1].mean()
