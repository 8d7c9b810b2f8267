"""Every number of a training iteration, in one documented dataclass, and how `--set` changes it.

The stages (imitation, world model, refinement), iterate.py and iteration.py, the benchmarks
and the study all read this one config, and none of them imports it back from a command, so
the stages stand alone. A profile name picks model sizes (training/profiles.py) and a preset
of steps and batch sizes (PRESETS); `--set field=value` overrides any field. Each field is a
`setting()` (training/setting.py): its doc and the values it allows stand beside its default,
and the checks, `carrt-train --settings` and docs/training.md's table are read from them.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import ClassVar

from carrt.errors import UserError
from carrt.settings import apply_sets
from training.profiles import PROFILES, WORLD_ACTION_INPUTS, Profile, get_profile
from training.setting import groups, problems, setting


class UsageError(UserError):
    """Bad input from the user: printed as one line, exit status 2."""


@dataclass
class TrainingConfig:
    """Everything one iteration does. Defaults are the paper's numbers where it gives them
    (the DIRL paper; "our choice" where it gives none). carrt's safeguards are one group: all of
    them off is the paper's pure form. The research variants' settings extend this class in
    research/variants/config.py; carrt-train refuses them. What was measured behind a default:
    research/LOG.md.
    """

    # the headings of `carrt-train --settings` and the docs' table: (title, its first field)
    GROUPS: ClassVar[tuple[tuple[str, str], ...]] = (
        ("Data and run", "episodes"),
        ("Stage 1: imitation (L1 between μ and a*, collision-free windows)", "imitation_steps"),
        ("Stage 2: world model (evidential image and speed regression, collision "
         "classification)", "world_model_steps"),
        ("Stage 3: refinement in imagination (the paper's objective; training/refine.py)",
         "refine_steps"),
        ("carrt's safeguards on refinement (training/refine.py says why each; all off is the "
         "paper's pure form)", "collision_prior_correction"),
        ("Every stage", "grad_clip"),
    )  # fmt: skip

    # -- data and run
    episodes: tuple[str, ...] = setting((), "episode directories, or directories of them")
    dirl: bool = setting(
        False, "train the world model and refine the policy in it (stages 2 and 3) after "
        "imitation; off, a run is imitation alone and writes no world model. carrt-train's "
        "--dirl runs them into OUT/refined/, beside the imitated policy, never over it",
    )  # fmt: skip
    world_episodes: tuple[str, ...] = setting(
        (), "episodes the world model learns instead of `episodes`, e.g. a sloppier person's "
        "drives, whose errors show what steering off the line does (imitation and refinement "
        "still read `episodes`); empty: the world model learns `episodes` (the paper's)",
    )  # fmt: skip
    out: str = setting("", "run directory: checkpoints, policy.pt, policy.onnx, report.md, figures")
    init: str | None = setting(None, "previous iteration's run directory (none: iteration 1)")
    pretrained: str | None = setting(
        None, "a torchvision resnet18 state_dict file you have (never downloaded): the policy's "
        "and the world model's backbones start from it; its shapes must fit the profile "
        "(ImageNet weights are width 64, the paper profile)",
    )  # fmt: skip
    profile: str = setting(
        "cpu", "model sizes and presets: tiny (tests), cpu (a laptop), paper (GPU)",
        choices=tuple(PROFILES),
    )  # fmt: skip
    val_fraction: float = setting(
        0.1, "share of placements held out (data.split_by_placement)", lo=0, below=1
    )
    seed: int = setting(0, "seeds model init, batch order and refinement noise")
    device: str = setting("auto", "auto (cuda if available), cpu, cuda, cuda:N")
    num_workers: int = setting(0, "DataLoader worker processes per training process", lo=0)
    threads: int = setting(0, "torch intra-op threads per process (0: torch's default)", lo=0)
    # -- stage 1: imitation
    imitation_steps: int = setting(
        20000, "optimizer steps (the paper gives none; our choice)", lo=0
    )
    imitation_batch_size: int = setting(128, "global batch (paper: 128)", above=0)
    imitation_lr: float = setting(1e-3, "Adam learning rate (paper: 1e-3)", above=0)
    imitation_lr_final: float = setting(
        0.05, "cosine decay to lr·this at the last step (1: constant)", above=0
    )
    intervention_weight: float = setting(
        1.0, "weight of a* from a person's take-over in AUTO", lo=0
    )
    augment: bool = setting(
        False, "per-sample colour jitter of imitation frames (training/augment.py)"
    )
    augment_hue: float = setting(
        0.5, "max hue rotation, share of a half turn (obstacle colours vary)", lo=0
    )
    augment_saturation: float = setting(0.3, "max relative saturation change", lo=0)
    augment_brightness: float = setting(0.2, "max brightness shift, share of full scale", lo=0)
    augment_contrast: float = setting(0.2, "max relative contrast change", lo=0)
    mirror_imitation: bool = setting(
        False, "mirror half of each batch, steering negated (training/augment.py)"
    )
    reimitate: bool = setting(
        False, "with `dirl`, a later iteration (--init) learns by imitation again before the "
        "world model: from the previous policy, imitation_steps on every labelled frame given "
        "(DAgger-style); off: the paper's Algorithm 1, imitation once. carrt-train's --init "
        "always imitates again (a take-over round)",
    )  # fmt: skip
    reimitation_steps: int = setting(
        1000, "carrt-train's take-over round (--init, and each --iterations round): imitation "
        "again from the previous policy, this many steps in place of imitation_steps (the "
        "setting the rounds were measured with: research/README.md row 2)", lo=0,
    )  # fmt: skip
    reimitation_lr: float = setting(
        3e-4, "the take-over round's learning rate, in place of imitation_lr", above=0
    )
    # -- stage 2: world model
    world_model_steps: int = setting(30000, "optimizer steps (our choice)", lo=0)
    world_model_batch_size: int = setting(32, "global batch (paper: 32)", above=0)
    world_model_lr: float = setting(5e-4, "Adam learning rate (paper: 5e-4)", above=0)
    w_image: float = setting(1.0, "weight of L_image in L_w (the cpu preset: 0.1, see PRESETS)")
    w_speed: float = setting(1.0, "weight of L_speed in L_w")
    w_collision: float = setting(1.0, "weight of L_collision in L_w")
    collision_weight: float = setting(
        0.0, "weight of the collision class; 0: n_safe/n_collision", lo=0
    )
    takeovers_as_collisions: bool = setting(
        False, "label the 0.5 s before a person's take-over a collision for the world model, "
        "as the paper counts its e-stops; off: a take-over is followed by the person's own "
        "braking, and those labels can teach 'fast = collision' rather than what caused it",
    )  # fmt: skip
    world_model_fresh: bool = setting(
        False, "with --init: the world model starts from its own (seeded) initialisation "
        "instead of the previous run's (the policy still from --init)",
    )  # fmt: skip
    evidential_lambda: float = setting(0.01, "λ of the evidential regulariser |y−γ|(2ν+α)")
    mirror_world_model: bool = setting(
        False, "mirror half of each batch left↔right, steering negated (training/augment.py): "
        "steering tied to the place on a one-way track cannot stand in for what the image shows",
    )  # fmt: skip
    world_action_inputs: str = setting(
        "first", "where the world model's actions enter: first, the paper's Reveries-net (the "
        "first GRU layer only); all, every GRU layer and every head. Saved in the checkpoint; "
        "a later --init run must give the same", choices=WORLD_ACTION_INPUTS,
    )  # fmt: skip
    # -- stage 3: refinement in imagination
    refine_steps: int = setting(5000, "optimizer steps (our choice)", lo=0)
    refine_batch_size: int = setting(36, "global batch of start frames (paper: 36)", above=0)
    refine_lr: float = setting(1e-5, "Adam learning rate (paper: 1e-5)", above=0)
    refine_w_speed: float = setting(1.0, "reward per imagined m/s, per step")
    refine_w_collision: float = setting(10.0, "cost of imagined collision probability, per step")
    refine_w_uncertainty: float = setting(1.0, "cost of u_i + u_s + u_c, per step")
    uncertainty_clip: float = setting(
        10.0, "each u is clipped here in the refinement loss", above=0
    )
    no_uncertainty: bool = setting(False, "the paper's -unc ablation: w_unc = 0")
    refine_candidates_every: int = setting(
        0, "every N refinement steps the policy is also kept as a candidate "
        "(OUT/candidates/refine<step>.pt), so how far to refine can be chosen by driving; "
        "0: the final policy only", lo=0,
    )  # fmt: skip
    # -- carrt's safeguards on refinement; all off is the paper's pure form:
    # collision_prior_correction=false refine_w_anchor=0 refine_w_imitation=0
    # refine_center_gradient=false (refine_steering stays true)
    collision_prior_correction: bool = setting(
        True, "p̂(collision) with the world model's collision class weight divided back out of "
        "its odds",
    )  # fmt: skip
    refine_w_anchor: float = setting(
        10.0, "weight of Σ|μ−μ_start|²: the plan stays near its start", lo=0
    )
    refine_w_imitation: float = setting(
        50.0, "weight of imitation's L1 on demonstrations, each step", lo=0
    )
    refine_center_gradient: bool = setting(
        True, "the world model's gradient on the actions less its mean over the batch of start "
        "frames",
    )  # fmt: skip
    refine_steering: bool = setting(True, "off: the world model's gradient moves the throttle only")
    # -- every stage
    grad_clip: float = setting(1.0, "max global gradient norm", above=0)
    log_every: int = setting(
        10, "steps between logged scalars (TensorBoard, loss history)", above=0
    )
    ckpt_every: int = setting(
        500, "steps between checkpoints (also one at the end of each stage)", lo=0
    )
    eval_every: int = setting(0, "steps between held-out losses during training (0: off)", lo=0)
    eval_windows: int = setting(2048, "held-out windows used by the final metrics", above=0)
    stop_after: int = setting(
        0, "stop after this many steps in this invocation (0: never); resumable", lo=0
    )
    export: bool = setting(
        True, "write policy.onnx (carrt-export, run as a process after training)"
    )
    figures: bool = setting(True, "write figures/*.png")
    progress: bool = setting(True, "tqdm bars on rank 0")

    @property
    def profile_obj(self) -> Profile:
        """The named profile's sizes with this run's world_action_inputs."""
        return replace(get_profile(self.profile), world_action_inputs=self.world_action_inputs)

    def validate(self) -> None:
        """Each setting against its declaration (the first refused one, in one line), then the
        one rule between two settings."""
        if self.profile not in PROFILES:
            raise UsageError(
                f"unknown profile {self.profile!r}; choose one of {', '.join(PROFILES)}"
            )
        found = problems(self)
        if found:
            raise UsageError(found[0])
        if self.world_episodes and self.world_model_steps == 0:
            raise UsageError(
                "--world-episodes given but world_model_steps is 0: the world model would not "
                "learn them"
            )


# Steps and batches per profile, applied before --steps/--set: the paper's numbers need a GPU.
PRESETS: dict[str, dict] = {
    "tiny": dict(imitation_steps=30, world_model_steps=30, refine_steps=20, reimitation_steps=30,
                 imitation_batch_size=16, world_model_batch_size=8, refine_batch_size=8,
                 refine_lr=1e-4, log_every=1, ckpt_every=10, eval_windows=256),
    "cpu": dict(imitation_steps=2000, world_model_steps=3000, refine_steps=500,
                imitation_batch_size=64, world_model_batch_size=32, refine_batch_size=16,
                log_every=10, ckpt_every=250, eval_every=500, augment=True,
                # at 1.0 the per-pixel NLL's gradients drown the small model's collision term
                w_image=0.1),
    "paper": dict(eval_every=1000, augment=True),
}  # fmt: skip

FROZEN = ("episodes", "world_episodes", "out", "dirl")  # given as --episodes etc., not --set
# The research variants' settings (ResearchConfig, research/variants/config.py; a test keeps
# this list equal to its fields): carrt-train refuses each by name instead of "unknown field".
RESEARCH_SETTINGS = (
    "refine_search", "refine_search_margin", "refine_w_search", "refine_outcomes",
    "outcome_advantage", "outcome_temperature", "outcome_weight_max", "counterfactual_starts",
    "counterfactual_layout", "counterfactual_tracks",
)  # fmt: skip


def apply_set(cfg: TrainingConfig, items: list[str], prog: str = "carrt-train") -> TrainingConfig:
    """`--set field=value` (carrt/settings.py: the parser the study shares); errors are
    UsageErrors (one line, exit 2). `prog` is the command whose `--settings` lists the fields."""
    names = {f.name for f in fields(cfg)}
    for item in items:
        name = item.partition("=")[0].strip()
        if name == "dirl":
            raise UsageError("--set dirl: use --dirl (it writes the refined policy into "
                             "OUT/refined/, beside the imitated one)")  # fmt: skip
        if name in RESEARCH_SETTINGS and name not in names:
            raise UsageError(f"{name} is a research variant: run it with "
                             "research/variants/train.py (a repository checkout), not "
                             f"{prog}")  # fmt: skip
    try:
        return apply_sets(cfg, items, f"{prog} --settings", frozen=FROZEN)
    except UserError as exc:
        raise UsageError(str(exc)) from None


def dirl_fields() -> tuple[str, ...]:
    """The settings only the world model, refinement and the research variants read: stage 2,
    stage 3 and the safeguards, and RESEARCH_SETTINGS. A run without them (not `dirl`) leaves
    them out of its report."""
    read = ("Stage 2", "Stage 3", "carrt's safeguards")
    names = [spec.name for title, specs in groups(TrainingConfig) if title.startswith(read)
             for spec in specs]  # fmt: skip
    return (*names, *RESEARCH_SETTINGS)
