"""The stages' shared loop machinery and its checkpoints, on the simulator's episodes.

An interrupted stage must resume exactly, Ctrl-C must finish the step then checkpoint, a
checkpoint must round-trip (keeping its profile's sizes) and refuse what is not one; the
imitation learning rate must follow its cosine, and a stage's final figures must average each
key over the entries that have it (report.md's validation loss).
"""

from __future__ import annotations

import signal

import pytest

torch = pytest.importorskip("torch")

from train_stage_rig import models, stage_data, tiny  # noqa: E402

from training import checkpoint as ck  # noqa: E402
from training.imitation import imitation_loss, train_imitation  # noqa: E402
from training.models import PolicyNet  # noqa: E402
from training.trainer import (  # noqa: E402
    Budget,
    Interrupted,
    RunContext,
    StopRequested,
)

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def data(sim_episodes):
    return stage_data(sim_episodes)


def test_an_interrupted_stage_resumes_exactly(data, tmp_path):
    _, norm, _, free = data
    cfg = tiny(imitation_steps=8, imitation_batch_size=4, ckpt_every=3)
    straight, _ = models(norm)
    train_imitation(cfg, straight, free)

    common = {
        "config": {}, "profile": "tiny", "normalisation": norm.to_dict(), "data_digest": "x",
        "iteration": 0, "code_version": ck.code_version(), "episodes": [],
    }  # fmt: skip
    ctx = RunContext(ckpt_dir=tmp_path, common=common, budget=Budget(5))
    interrupted, _ = models(norm)
    with pytest.raises(StopRequested):
        train_imitation(cfg, interrupted, free, ctx)
    saved = ck.load_checkpoint(tmp_path / "imitation.pt")
    assert saved["step"] == 5 and saved["optimizer"] is not None
    resumed, _ = models(norm, seed=123)  # different init: everything must come from the file
    resumed.load_state_dict(saved["policy"])
    result = train_imitation(cfg, resumed, free, RunContext(ckpt_dir=tmp_path, common=common),
                             resume=saved)  # fmt: skip
    assert [h["step"] for h in result.history] == list(range(1, 9))
    for (k, a), b in zip(straight.state_dict().items(), resumed.state_dict().values(), strict=True):
        assert torch.equal(a, b), k
    assert ck.load_checkpoint(tmp_path / "imitation.pt")["step"] == 8


def test_ctrl_c_finishes_the_step_then_checkpoints(data, tmp_path, request, monkeypatch):
    from training import imitation

    _, norm, _, free = data
    # A runner started in the background (`cmd &` in a script) inherits SIGINT ignored; Ctrl-C
    # in a terminal is what this test is about, so start from Python's own handler.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    request.addfinalizer(lambda: signal.signal(signal.SIGINT, previous))
    policy, _ = models(norm)
    common = {
        "config": {}, "profile": "tiny", "normalisation": norm.to_dict(), "data_digest": "x",
        "iteration": 0, "code_version": "x", "episodes": [],
    }  # fmt: skip
    steps = []

    def loss_fn(model, batch):
        steps.append(len(steps))
        if steps[-1] == 2:
            signal.raise_signal(signal.SIGINT)  # arrives mid-step
        return imitation_loss(model, batch)

    monkeypatch.setattr(imitation, "imitation_loss", loss_fn)  # the stage's own loop calls it
    cfg = tiny(imitation_steps=10, imitation_batch_size=4, ckpt_every=0)
    ctx = RunContext(ckpt_dir=tmp_path, common=common)
    with pytest.raises(Interrupted):
        train_imitation(cfg, policy, free, ctx)
    saved = ck.load_checkpoint(tmp_path / "imitation.pt")
    assert saved["step"] == 3 and [h["step"] for h in saved["history"]] == [1, 2, 3]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # handler restored


def test_checkpoint_round_trip_and_refusals(data, tmp_path):
    _, norm, _, _ = data
    policy, _ = models(norm)
    fields = {
        "config": {"a": 1}, "profile": "tiny", "stage": "imitation", "step": 3,
        "policy": policy.state_dict(), "world_model": None, "optimizer": None,
        "normalisation": norm.to_dict(), "data_digest": "d", "iteration": 0,
        "code_version": ck.code_version(), "episodes": ["e1"],
    }  # fmt: skip
    path = tmp_path / "c.pt"
    ck.save_checkpoint(path, **fields)
    assert [p.name for p in tmp_path.iterdir()] == ["c.pt"]  # no temporary file left behind
    loaded, c = ck.load_policy(path)
    assert c["step"] == 3 and c["format"] == ck.FORMAT and not loaded.training
    assert loaded.normalisation().speed_std == pytest.approx(norm.speed_std)
    with pytest.raises(ck.CheckpointError, match="missing fields step"):
        ck.save_checkpoint(path, **{k: v for k, v in fields.items() if k != "step"})
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ck.CheckpointError, match="unreadable"):
        ck.load_checkpoint(tmp_path / "junk.pt")
    with pytest.raises(ck.CheckpointError, match="holds no world model"):
        ck.load_world_model(path)


def test_final_averages_each_key_over_the_entries_that_have_it():
    """Defect 5: val_* is logged every eval_every steps only; dividing by every logged entry
    made report.md's validation loss ~10x too small."""
    from training.trainer import StageResult

    history = [{"step": s, "loss": 1.0} for s in range(1, 10)]
    history.append({"step": 10, "loss": 1.0, "val_loss": 0.5})
    history += [{"step": s, "loss": 3.0} for s in range(11, 20)]
    history.append({"step": 20, "loss": 3.0, "val_loss": 0.7})
    final = StageResult("imitation", 20, history).final(last=10)
    assert final["loss"] == pytest.approx(3.0)
    assert final["val_loss"] == pytest.approx(0.6)
    assert StageResult("imitation", 0, []).final() == {}


def test_imitation_lr_follows_a_cosine_to_its_final_fraction():
    from training.trainer import StageSpec

    spec = StageSpec("imitation", steps=101, batch_size=1, lr=1e-3, grad_clip=1.0,
                     ckpt_every=0, log_every=1, seed=0, final_lr_fraction=0.05)  # fmt: skip
    assert spec.lr_at(0) == pytest.approx(1e-3)
    assert spec.lr_at(50) == pytest.approx(1e-3 * (0.05 + 0.95 * 0.5))
    assert spec.lr_at(100) == pytest.approx(5e-5)
    constant = StageSpec("world_model", steps=101, batch_size=1, lr=5e-4, grad_clip=1.0,
                         ckpt_every=0, log_every=1, seed=0)  # fmt: skip
    assert constant.lr_at(100) == 5e-4


def test_a_checkpoint_carries_its_profiles_sizes(tmp_path):
    """Issue 16: a checkpoint names its profile AND keeps its fields, so changing a profile
    never breaks an old checkpoint (load_policy builds from the stored fields)."""
    import dataclasses

    from training import checkpoint as ck
    from training.data import Normalisation
    from training.profiles import get_profile

    sizes = dataclasses.replace(get_profile("tiny"), width=4)  # not any profile's sizes
    policy = PolicyNet(sizes)
    norm = Normalisation((0.5,) * 3, (0.25,) * 3, 1.0, 0.5)
    policy.set_normalisation(norm)
    path = tmp_path / "p.pt"
    ck.save_checkpoint(
        path, config={}, profile="tiny", profile_fields=dataclasses.asdict(sizes),
        stage="imitation", step=1, policy=policy.state_dict(), world_model=None, optimizer=None,
        normalisation=norm.to_dict(), data_digest="d", iteration=0,
        code_version=ck.code_version(), episodes=[],
    )  # fmt: skip
    assert get_profile("tiny").width != 4, "the stored sizes must differ from the named ones"
    loaded, _ = ck.load_policy(path)  # built from the tiny profile, this would not load
    for a, b in zip(loaded.state_dict().values(), policy.state_dict().values(), strict=True):
        assert torch.equal(a, b)
