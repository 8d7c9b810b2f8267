"""Windows, splits, digest and normalisation over episodes recorded by the real stack."""

import json
import pickle

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from training.data import (
    FrameStore,
    ImitationDataset,
    Normalisation,
    WindowDataset,
    compute_normalisation,
    data_digest,
    load_episodes,
    placement_key,
    split_by_episode,
    split_by_placement,
)

H = 10


@pytest.fixture(scope="module")
def episodes(sim_episodes):
    eps = load_episodes(sim_episodes)
    assert len(eps) == 7
    assert any(ep.collision.any() for ep in eps), "the fixture should hold collisions"
    return eps


@pytest.fixture(scope="module")
def windows(episodes):
    return WindowDataset(episodes, H, predict_size=16)


def locate(ds, i, t):
    rows = np.flatnonzero((ds.index[:, 0] == i) & (ds.index[:, 1] == t))
    assert len(rows) == 1
    return ds[int(rows[0])]


def test_one_window_per_step_with_a_future(episodes, windows):
    assert len(windows) == sum(ep.n - 1 for ep in episodes)
    item = windows[0]
    expected = {
        "image": ((96, 96, 3), torch.uint8),
        "speed": ((1,), torch.float32),
        "expert_actions": ((H, 2), torch.float32),
        "actions": ((H, 2), torch.float32),
        "future_images": ((H, 16, 16, 3), torch.uint8),
        "future_speeds": ((H, 1), torch.float32),
        "collisions": ((H,), torch.float32),
        "mask": ((H,), torch.float32),
        "action_mask": ((H,), torch.float32),
    }
    for key, (shape, dtype) in expected.items():
        assert item[key].shape == shape and item[key].dtype == dtype, key


def test_window_contents_match_the_episode(episodes):
    ds = WindowDataset(episodes, H, predict_size=96)
    small = WindowDataset(episodes, H, predict_size=16)
    for i, ep in enumerate(episodes):
        last_full = ep.n - 1 - H  # the last start with a whole future
        for t in sorted({0, last_full // 2, last_full}):
            item = locate(ds, i, t)
            steps = ep.steps
            assert np.array_equal(item["image"].numpy(), ep.frames[t])
            assert item["speed"].item() == pytest.approx(float(steps["speed_mps"][t]))
            assert np.allclose(item["expert_actions"].numpy(), steps["human_action"][t : t + H])
            assert np.allclose(item["actions"].numpy(), steps["executed_action"][t : t + H])
            future = slice(t + 1, t + 1 + H)
            assert np.array_equal(item["future_images"].numpy(), ep.frames[future])
            assert np.allclose(item["future_speeds"].numpy()[:, 0], steps["speed_mps"][future])
            assert np.array_equal(item["collisions"].numpy(), ep.collision[future])
            assert item["mask"].sum().item() == H
            # 16 × 16: the area mean of 6 × 6 blocks
            blocks = ep.frames[future].reshape(H, 16, 6, 16, 6, 3).astype(np.float64).mean((2, 4))
            got = locate(small, i, t)["future_images"].numpy().astype(np.float64)
            assert np.abs(got - blocks).max() <= 1.0


def test_masks_and_padding_at_an_episode_end(episodes, windows):
    i, ep = next((i, ep) for i, ep in enumerate(episodes) if ep.collision.any())
    last = locate(windows, i, ep.n - 2)  # one future step left
    assert last["mask"].tolist() == [1.0] + [0.0] * (H - 1)
    assert last["action_mask"].tolist() == [1.0, 1.0] + [0.0] * (H - 2)
    assert last["collisions"][0].item() == ep.collision[-1] == 1  # ended by a collision
    assert np.allclose(last["actions"][1:].numpy(), ep.steps["executed_action"][-1])
    assert np.allclose(last["future_speeds"][:, 0].numpy(), ep.steps["speed_mps"][-1])
    three = locate(windows, i, ep.n - 4)
    assert three["mask"].tolist() == [1.0] * 3 + [0.0] * (H - 3)
    assert not any(t == ep.n - 1 for j, t in windows.index if j == i)  # nothing to predict


def test_collision_free_windows_touch_no_collision_label(episodes, windows):
    free = WindowDataset(episodes, H, predict_size=16, collision_free_only=True)
    assert 0 < len(free) < len(windows)
    expected = 0
    for ep in episodes:
        for t in range(ep.n - 1):
            expected += not ep.collision[t : t + H + 1].any()
    assert len(free) == expected
    for i, t in free.index:
        assert not episodes[i].collision[t : t + H + 1].any()
    for k in range(0, len(free), 7):
        assert free[k]["collisions"].sum().item() == 0


def test_split_is_by_episode_and_seeded(episodes):
    train, val = split_by_episode(episodes, 0.34, seed=3)
    names_t, names_v = {e.name for e in train}, {e.name for e in val}
    assert len(val) == 2 and len(train) == 5  # round(7 · 0.34)
    assert not names_t & names_v and names_t | names_v == {e.name for e in episodes}
    again = split_by_episode(list(reversed(episodes)), 0.34, seed=3)
    assert {e.name for e in again[1]} == names_v  # the input order does not matter
    splits = {frozenset(e.name for e in split_by_episode(episodes, 0.34, s)[1]) for s in range(8)}
    assert len(splits) > 1  # the seed does
    assert split_by_episode(episodes, 0.01, 0)[1]  # a tiny fraction still validates on one
    assert split_by_episode(episodes, 0.0, 0)[1] == []


def test_normalisation_is_sane_and_round_trips(episodes):
    norm = compute_normalisation(episodes)
    assert all(0.0 < m < 1.0 for m in norm.image_mean)
    assert all(0.0 < s < 0.5 for s in norm.image_std)
    assert 0.0 < norm.speed_mean < 3.0 and norm.speed_std >= 0.1
    d = json.loads(json.dumps(norm.to_dict()))
    assert Normalisation.from_dict(d) == norm
    few = compute_normalisation(episodes, max_frames=16)
    assert few.image_mean == pytest.approx(norm.image_mean, abs=0.05)


def test_digest_is_stable_and_names_the_episode_set(episodes):
    d = data_digest(episodes)
    assert len(d) == 64 and int(d, 16) >= 0
    assert data_digest(list(reversed(episodes))) == d
    assert data_digest(episodes[:-1]) != d
    assert data_digest(episodes[1:]) != data_digest(episodes[:-1])


def test_dataloader_iterates(windows):
    loader = DataLoader(windows, batch_size=8, shuffle=True, num_workers=0)
    for k, b in enumerate(loader):
        assert b["image"].shape == (8, 96, 96, 3) and b["image"].dtype == torch.uint8
        assert b["future_images"].shape == (8, H, 16, 16, 3)
        if k == 2:
            break


def test_pickled_dataset_reopens_frames_instead_of_copying_them(windows):
    blob = pickle.dumps(windows)
    assert len(blob) < 200_000  # ~300 frames would be 8 MB
    clone = pickle.loads(blob)
    for k in (0, len(windows) - 1):
        for key, value in windows[k].items():
            assert torch.equal(clone[k][key], value), key


# ------------------------------------------------------------ synthetic episodes (factory)
def _episode(root, seed, modes, *, meta=None, overrides=(), collisions=()):
    from episode_factory import make_step, metadata, write_episode

    from carrt.episodes.reader import read_episode

    steps = [
        make_step(t, seed=seed, mode=m, override=t in overrides, collision=t in collisions)
        for t, m in enumerate(modes)
    ]
    return read_episode(write_episode(root, steps, meta=metadata(**(meta or {}))))


def test_split_holds_out_whole_placements(tmp_path):
    """Defect 4: episodes of one placement are near-duplicates; validation must not see any
    placement that training saw."""
    from carrt.interfaces import Mode

    eps = [
        _episode(tmp_path / f"p{p}e{e}", 10 * p + e, [Mode.MANUAL] * 3,
                 meta={"sim": {"layout": "hard", "track_seed": 1000 + p}})
        for p in range(5) for e in range(3)
    ]  # fmt: skip
    train, val = split_by_placement(eps, 0.2, seed=0)
    key = {id(ep): placement_key(ep) for ep in eps}
    held = {key[id(ep)] for ep in val}
    assert len(held) == 1 and len(val) == 3 and len(train) == 12
    assert not held & {key[id(ep)] for ep in train}
    assert placement_key(eps[0]) == "sim:hard:1000"
    # one placement only: nothing to hold out by placement, whole episodes instead
    one = [ep for ep in eps if key[id(ep)] == "sim:hard:1000"]
    t1, v1 = split_by_placement(one, 0.34, seed=0)
    assert len(v1) == 1 and len(t1) == 2
    # a real car: a session id groups its episodes; without one, each episode stands alone
    real = _episode(tmp_path / "real", 99, [Mode.MANUAL] * 3, meta={"session_id": "s1"})
    assert placement_key(real) == "session:s1"
    bare = _episode(tmp_path / "bare", 98, [Mode.MANUAL] * 3)
    assert placement_key(bare) == f"episode:{bare.name}"


def test_imitation_targets_manual_steps_and_interventions(tmp_path):
    """a* is a target only where a person drove (MANUAL): in AUTO the sticks are untouched.
    A take-over in AUTO (override, then MANUAL) labels states the policy reached, weighted."""
    from carrt.interfaces import Mode

    A, M, D = Mode.AUTO, Mode.MANUAL, Mode.DISARMED
    modes = [M] * 4 + [A] * 4 + [M] * 4 + [D] * 2
    ep = _episode(tmp_path, 1, modes, overrides={8})
    ds = ImitationDataset([ep], H, intervention_weight=3.0)
    starts = [int(t) for _, t in ds.index]
    assert starts == [0, 1, 2, 3, 8, 9, 10, 11]
    assert ds.interventions == 4
    item = ds[0]  # t = 0: steps 0..3 manual, 4..7 auto, 8, 9 intervention
    assert item["weight"].tolist() == [1.0] * 4 + [0.0] * 4 + [3.0] * 2
    assert np.allclose(item["expert_actions"].numpy(), ep.steps["human_action"][:H])
    last = ds[starts.index(11)]
    assert last["weight"].tolist() == [3.0] + [0.0] * (H - 1)  # then DISARMED, then the end
    assert "future_images" not in item  # imitation reads no future frames


def test_imitation_leaves_out_windows_into_a_collision(tmp_path):
    from carrt.interfaces import Mode

    ep = _episode(tmp_path, 2, [Mode.MANUAL] * 30, collisions={20})
    ds = ImitationDataset([ep], H)
    assert all(not (t <= 20 <= t + H) for _, t in ds.index)
    assert max(t for _, t in ds.index) == 29  # the last step is a start too


def test_world_model_labels_the_half_second_before_a_takeover_a_collision(tmp_path):
    """The paper counts a person's e-stop as a collision: with takeovers_as_collisions the
    world model's `collisions` are 1 in the 0.5 s (5 steps at 10 Hz) up to each take-over edge,
    as for a crash; without it, and for imitation's collision-free filter, only crashes count."""
    from carrt.interfaces import Mode
    from training.world_model_stage import collision_class_weight

    A, M = Mode.AUTO, Mode.MANUAL
    modes = [A] * 12 + [M] * 8
    ep = _episode(tmp_path, 3, modes, overrides={12, 13})  # one take-over, held two steps
    on = WindowDataset([ep], H, predict_size=16, takeovers_as_collisions=True)
    off = WindowDataset([ep], H, predict_size=16)
    assert np.flatnonzero(on.step_labels()).tolist() == [8, 9, 10, 11, 12]
    assert not off.step_labels().any()
    window = on[5]  # future steps 6..15
    assert window["collisions"].tolist() == [0, 0, 1, 1, 1, 1, 1, 0, 0, 0]
    assert not off[5]["collisions"].any()
    assert collision_class_weight(on.step_labels()) == 3.0  # 15 safe / 5
    assert collision_class_weight(off.step_labels()) == 1.0
    assert len(ImitationDataset([ep], H)) == 8  # the take-over's labels are all kept


def test_get_batch_matches_items_and_store_is_shared(episodes):
    store = FrameStore(episodes)
    a = WindowDataset(episodes, H, predict_size=16, store=store)
    b = ImitationDataset(episodes, H, store=store)
    assert a.store.frames.data_ptr() == b.store.frames.data_ptr()
    rows = [0, 5, len(a) - 1]
    batch = a.get_batch(rows)
    for j, r in enumerate(rows):
        for k, v in a[r].items():
            assert torch.equal(batch[k][j], v), k


def test_augmentation_is_seeded_and_changes_colours_only():
    from training.augment import augment_images

    rng = np.random.default_rng(0)
    images = torch.from_numpy(rng.integers(0, 256, (6, 96, 96, 3), dtype=np.uint8))
    one = augment_images(images, torch.Generator().manual_seed(1))
    two = augment_images(images, torch.Generator().manual_seed(1))
    assert one.dtype == torch.uint8 and one.shape == images.shape
    assert torch.equal(one, two) and not torch.equal(one, images)
    same = augment_images(images, torch.Generator().manual_seed(1), hue=0, saturation=0,
                          brightness=0, contrast=0)  # fmt: skip
    assert (same.int() - images.int()).abs().max() <= 1  # zero jitter is the identity
    grey = torch.full((2, 8, 8, 3), 100, dtype=torch.uint8)
    g = augment_images(grey, torch.Generator().manual_seed(3), brightness=0, contrast=0)
    assert (g.int() - 100).abs().max() <= 1  # hue and saturation leave grey alone


def test_training_stops_before_a_record_whose_crc_fails(tmp_path, caplog):
    """Issue 15 (8): the car's reader trusts the fsynced region; training checks every CRC, so
    a byte flipped inside it never reaches a batch."""
    import shutil

    from carrt.episodes import format as fmt
    from carrt.interfaces import Mode

    ep = _episode(tmp_path / "eps" / "a", 7, [Mode.MANUAL] * 12)
    copy = tmp_path / "copy"
    shutil.copytree(ep.path.parent, copy)
    (damaged,) = [p for p in copy.iterdir() if p.is_dir()]
    frames = bytearray((damaged / fmt.FRAMES).read_bytes())
    frames[5 * fmt.FRAME_BYTES + 100] ^= 0x40  # one bit of frame 5
    (damaged / fmt.FRAMES).write_bytes(bytes(frames))
    assert load_episodes(ep.path.parent)[0].n == 12
    with caplog.at_level("WARNING", logger="training.data"):
        (loaded,) = load_episodes(copy)
    assert loaded.n == 5, "cut before the damaged record"
    assert "fails its CRC" in caplog.text and damaged.name in caplog.text


def test_mirroring_flips_images_and_steering_and_nothing_else():
    from training.augment import mirror_batch

    rng = np.random.default_rng(0)
    batch = {
        "image": torch.from_numpy(rng.integers(0, 256, (64, 8, 8, 3), dtype=np.uint8)),
        "future_images": torch.from_numpy(rng.integers(0, 256, (64, 4, 6, 6, 3), dtype=np.uint8)),
        "actions": torch.from_numpy(rng.uniform(-1, 1, (64, 4, 2)).astype(np.float32)),
        "expert_actions": torch.from_numpy(rng.uniform(-1, 1, (64, 4, 2)).astype(np.float32)),
        "speed": torch.rand(64, 1),
        "collisions": torch.randint(0, 2, (64, 4)).float(),
    }
    out = mirror_batch(batch, torch.Generator().manual_seed(5))
    again = mirror_batch(batch, torch.Generator().manual_seed(5))
    flipped = out["actions"][:, 0, 0] != batch["actions"][:, 0, 0]
    assert 16 < int(flipped.sum()) < 48, "about half the samples"
    for k in batch:
        assert torch.equal(out[k], again[k]), "deterministic in the generator"
    for i in range(64):
        f = bool(flipped[i])
        want = batch["image"][i].flip(1) if f else batch["image"][i]
        assert torch.equal(out["image"][i], want)
        want = batch["future_images"][i].flip(2) if f else batch["future_images"][i]
        assert torch.equal(out["future_images"][i], want)
        for key in ("actions", "expert_actions"):
            sign = -1.0 if f else 1.0
            assert torch.equal(out[key][i, :, 0], sign * batch[key][i, :, 0])
            assert torch.equal(out[key][i, :, 1], batch[key][i, :, 1]), "throttle kept"
    assert torch.equal(out["speed"], batch["speed"])
    assert torch.equal(out["collisions"], batch["collisions"])
    same = mirror_batch(batch, torch.Generator().manual_seed(5), share=0.0)
    assert all(torch.equal(same[k], batch[k]) for k in batch)
