"""carrt-train's flags for one iteration, and the TrainingConfig they make (training/config.py);
the loop's flags (training/iterate.py) extend them. Kept apart from training/training_run.py so the
run reads on its own. research/variants/train.py makes its ResearchConfig with the same flags."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from training import checkpoint as ck
from training.config import PRESETS, TrainingConfig, UsageError, apply_set
from training.profiles import PROFILES


class Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, exit 2 — not argparse's usage block
        raise UsageError(message)


class ListSettings(argparse.Action):
    """`--settings`: every setting with its doc, default (and the profiles' presets) and the
    values it allows, printed like `--help` prints the flags, then exit 0."""

    def __init__(self, option_strings, dest, config_class=TrainingConfig, **kwargs):
        self.config_class = config_class
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        from training.settings_doc import listing

        print(listing(self.config_class, parser.prog))
        parser.exit()


def add_iteration_args(p: argparse.ArgumentParser, config_class: type = TrainingConfig) -> None:
    """The flags of one iteration (carrt-train's, which iterate.py's loop flags extend);
    `config_class` is the settings dataclass --set and --settings read."""
    p.add_argument("--episodes", nargs="+", required=True, metavar="DIR")
    p.add_argument(
        "--world-episodes", nargs="+", default=[], metavar="DIR",
        help="episodes the world model learns instead of --episodes (e.g. a sloppier drive)",
    )  # fmt: skip
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--init", metavar="DIR", help="previous iteration's run directory")
    p.add_argument(
        "--pretrained", metavar="FILE",
        help="a torchvision resnet18 state_dict file: the backbones start from it (paper profile)",
    )  # fmt: skip
    p.add_argument("--profile", help=f"{' | '.join(PROFILES)} (default: --init's, else cpu)")
    p.add_argument(
        "--steps",
        type=int,
        help="optimizer steps of every stage (and of a take-over round's imitation again)",
    )
    p.add_argument("--no-uncertainty", action="store_true", help="w_unc = 0 (the -unc ablation)")
    p.add_argument("--seed", type=int)
    p.add_argument("--device", help="auto | cpu | cuda | cuda:N")
    p.add_argument(
        "--set", action="append", default=[], metavar="FIELD=VALUE",
        help="change one setting, e.g. refine_lr=1e-5 (--settings lists them all); repeatable",
    )  # fmt: skip
    p.add_argument(
        "--settings", action=ListSettings, config_class=config_class,
        help="list every --set setting with its doc, default and allowed values, and exit",
    )  # fmt: skip


def config_from(
    a: argparse.Namespace, config_class: type = TrainingConfig, prog: str = "carrt-train"
) -> TrainingConfig:
    """The `config_class` (TrainingConfig, or research's extension of it) of parsed iteration
    flags: defaults, the profile's preset, then the flags, then --set; `prog` names the
    command in a --set error."""
    profile = a.profile or (init_profile(a.init) if a.init else "cpu")
    if profile not in PROFILES:
        raise UsageError(f"unknown profile {profile!r}; choose one of {', '.join(PROFILES)}")
    cfg = config_class(
        episodes=tuple(a.episodes), world_episodes=tuple(a.world_episodes), out=a.out,
        init=a.init, profile=profile,
    )  # fmt: skip
    cfg = dataclasses.replace(cfg, **PRESETS.get(profile, {}))
    if a.steps is not None:
        cfg = dataclasses.replace(
            cfg, imitation_steps=a.steps, world_model_steps=a.steps, refine_steps=a.steps,
            reimitation_steps=a.steps,
        )  # fmt: skip
    if getattr(a, "pretrained", None) is not None:
        if not Path(a.pretrained).is_file():
            raise UsageError(f"--pretrained {a.pretrained}: no such file")
        cfg = dataclasses.replace(cfg, pretrained=a.pretrained)
    for name in ("seed", "device"):
        if getattr(a, name) is not None:
            cfg = dataclasses.replace(cfg, **{name: getattr(a, name)})
    if a.no_uncertainty:
        cfg = dataclasses.replace(cfg, no_uncertainty=True)
    cfg = apply_set(cfg, a.set, prog)
    cfg.validate()
    return cfg


def init_paths(init: str) -> tuple[Path, Path]:
    p = Path(init)
    return (
        (p / "policy.pt", p / "world_model.pt")
        if p.is_dir()
        else (p, p.with_name("world_model.pt"))
    )


def init_profile(init: str) -> str:
    try:
        return ck.load_checkpoint(init_paths(init)[0])["profile"]
    except ck.CheckpointError as exc:
        raise UsageError(f"--init {init}: {exc}") from None
