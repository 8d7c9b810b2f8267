"""`carrt-train --pretrained FILE` (issue 60, item 4): the policy's and the world model's
backbones start from a torchvision-named resnet18 state dict the user has (nothing is
downloaded); a file that does not fit the profile, or is not a state dict, ends with one line.

The files here are made from a randomly initialised backbone with torchvision's names (and the
fc layer torchvision's files carry), sized for the profile under test: no ImageNet weights are
available offline, so whether they help at small data is not measured here."""

from __future__ import annotations

import torch

from training import checkpoint as ck
from training.backbone import ResNet18Backbone
from training.iterate import main
from training.profiles import PROFILES

SMALL = [
    "--profile", "tiny", "--set", "threads=1", "--set", "progress=false",
    "--set", "imitation_batch_size=8", "--set", "world_model_batch_size=4",
    "--set", "refine_batch_size=4", "--set", "eval_windows=64", "--set", "export=false",
    "--set", "figures=false", "--set", "imitation_steps=0", "--set", "world_model_steps=0",
    "--set", "refine_steps=0",
]  # fmt: skip


def _state_file(path, width: int, seed: int = 1):
    torch.manual_seed(seed)
    state = dict(ResNet18Backbone(width).state_dict())
    state["fc.weight"], state["fc.bias"] = torch.randn(1000, 8 * width), torch.randn(1000)
    torch.save(state, path)
    return state


def test_both_backbones_start_from_the_file(sim_episodes, tmp_path):
    before = torch.get_num_threads()
    path = tmp_path / "resnet18.pth"
    state = _state_file(path, PROFILES["tiny"].width)
    out = tmp_path / "run"
    argv = ["--episodes", str(sim_episodes), "--out", str(out), "--pretrained", str(path)]
    assert main([*argv, *SMALL, "--dirl"]) == 0
    torch.set_num_threads(before)
    policy, _ = ck.load_policy(out / "policy.pt")
    world_model, _ = ck.load_world_model(out / "refined" / "world_model.pt")  # --dirl's run
    for model in (policy, world_model):  # no steps: the weights are the file's
        for name, value in model.backbone.state_dict().items():
            assert torch.equal(value, state[name]), name


def test_a_file_that_does_not_fit_is_one_line(sim_episodes, tmp_path, capsys):
    before = torch.get_num_threads()
    wide, junk = tmp_path / "resnet18_imagenet.pth", tmp_path / "notes.txt"
    _state_file(wide, 64)  # ImageNet's resnet18 size, for the tiny profile
    junk.write_text("not weights")
    base = ["--episodes", str(sim_episodes), "--out", str(tmp_path / "run"), *SMALL]
    assert main([*base, "--pretrained", str(wide)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--pretrained:" in err and "need width 64" in err
    assert main([*base, "--pretrained", str(junk)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--pretrained:" in err
    assert main([*base, "--pretrained", str(tmp_path / "missing.pth")]) == 2
    assert "--pretrained " + str(tmp_path / "missing.pth") + ": no such file" in (
        capsys.readouterr().err
    )
    torch.set_num_threads(before)
