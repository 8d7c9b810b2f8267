"""Every number of a training iteration, in one documented dataclass, and how `--set` changes it.

The stages (imitation, world model, refinement), iterate.py and iteration.py, the benchmarks
and the study all read this one config, and none of them imports it back from a command, so
the stages stand alone. A profile name picks model sizes (training/profiles.py) and a preset
of steps and batch sizes (PRESETS); `--set field=value` overrides any field.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

from carrt.errors import UserError
from carrt.settings import apply_sets
from training.profiles import PROFILES, WORLD_ACTION_INPUTS, Profile, get_profile


class UsageError(UserError):
    """Bad input from the user: printed as one line, exit status 2."""


@dataclass
class IterateConfig:
    """Everything one iteration does. Defaults are the paper's numbers where it gives them
    (the DIRL paper; "our choice" where it gives none). carrt's safeguards are one group below:
    all of them off is the paper's pure form. Research variants (research/variants/) are the
    last group; carrt-train refuses them. What was measured behind a default: research/LOG.md.
    """

    # -- data and run
    episodes: tuple[str, ...] = ()  # episode directories, or directories of them
    # This run trains the world model and refines the policy in it (stages 2 and 3) after
    # imitation; off, a run is imitation alone (stage 1) and writes no world model. Not a --set
    # field: carrt-train's --dirl runs those stages into OUT/refined/, beside the imitated
    # OUT/policy.* and never over it (training/iterate.py); research/variants/train.py sets it
    # on every run, its policy.* the last stage's. What they were measured to do: research/
    dirl: bool = False
    # episodes the world model learns INSTEAD of `episodes` (--world-episodes), e.g. a sloppier
    # person's drives, whose errors show what steering off the line does; imitation and
    # refinement still read `episodes`. Empty: the world model learns `episodes` (the paper's)
    world_episodes: tuple[str, ...] = ()
    out: str = ""  # run directory: checkpoints, policy.pt, policy.onnx, report.md, figures
    init: str | None = None  # previous iteration's run directory (None: iteration 1)
    # a torchvision resnet18 state_dict file the user has (never downloaded): the policy's and
    # the world model's backbones start from it instead of a random initialisation (--pretrained;
    # its shapes must fit the profile: ImageNet resnet18 weights are width 64, the paper profile)
    pretrained: str | None = None
    profile: str = "cpu"  # model sizes and presets: tiny (tests), cpu (a laptop), paper (GPU)
    val_fraction: float = 0.1  # share of PLACEMENTS held out (data.split_by_placement)
    seed: int = 0  # seeds model init, batch order and refinement noise
    device: str = "auto"  # auto (cuda if available), cpu, cuda, cuda:N
    num_workers: int = 0  # DataLoader worker processes per training process
    threads: int = 0  # torch intra-op threads per process (0: torch's default)
    # -- stage 1: imitation (L1 between μ and a*, collision-free windows)
    imitation_steps: int = 20000  # optimizer steps (the paper gives none; our choice)
    imitation_batch_size: int = 128  # global batch (paper: 128)
    imitation_lr: float = 1e-3  # Adam (paper: 1e-3)
    imitation_lr_final: float = 0.05  # cosine decay to lr·this at the last step (1: constant)
    intervention_weight: float = 1.0  # weight of a* from a person's take-over in AUTO
    augment: bool = False  # per-sample colour jitter of imitation frames (training/augment.py)
    augment_hue: float = 0.5  # max hue rotation, share of a half turn (obstacle colours vary)
    augment_saturation: float = 0.3  # max relative saturation change
    augment_brightness: float = 0.2  # max brightness shift, share of full scale
    augment_contrast: float = 0.2  # max relative contrast change
    mirror_imitation: bool = False  # mirror half of each batch, steering negated (augment.py)
    # With `dirl` (research/variants/train.py's runs), a later iteration (--init) learns by
    # imitation again before the world model: from the previous policy, imitation_steps on every
    # labelled frame given, the demonstrations and the person's take-overs in the new drives
    # (states the policy itself reached, DAgger-style). False: the paper's Algorithm 1,
    # imitation once. carrt-train's --init always imitates again (a take-over round, below).
    reimitate: bool = False
    # carrt-train's take-over round (--init, and each of --iterations' rounds): imitation again
    # from the previous policy, a fine-tune of this many steps at this learning rate in place of
    # imitation_steps and imitation_lr, the setting the rounds were measured with (cpu profile,
    # +0.057 ± 0.031 completion against imitation at equal frames after three rounds:
    # research/README.md row 2, research/results/takeover_5seeds_rerun.json.gz)
    reimitation_steps: int = 1000
    reimitation_lr: float = 3e-4
    # -- stage 2: world model (evidential image/speed regression + collision classification)
    world_model_steps: int = 30000  # optimizer steps (our choice)
    world_model_batch_size: int = 32  # global batch (paper: 32)
    world_model_lr: float = 5e-4  # Adam (paper: 5e-4)
    w_image: float = 1.0  # weight of L_image in L_w (the cpu preset: 0.1, see PRESETS)
    w_speed: float = 1.0  # weight of L_speed in L_w
    w_collision: float = 1.0  # weight of L_collision in L_w
    collision_weight: float = 0.0  # weight of the collision class; 0 = n_safe/n_collision
    # True: the 0.5 s before a person's take-over is labelled a collision for the world model
    # too, as the paper counts its e-stops. Off: a take-over is followed by the person's own
    # braking, and those labels can teach "fast = collision" rather than what caused it
    takeovers_as_collisions: bool = False
    # with --init: the world model starts from its own (seeded) initialisation instead of the
    # previous run's (the policy still from --init): a member of an ensemble trained apart
    world_model_fresh: bool = False
    evidential_lambda: float = 0.01  # λ of the evidential regulariser |y−γ|(2ν+α)
    # mirror half of each batch left↔right, steering negated (training/augment.mirror_batch):
    # steering tied to the place on a one-way track cannot stand in for what the image shows
    mirror_world_model: bool = False
    # where the world model's actions enter (training/models.WorldModel): "first", the paper's
    # Reveries-net (the first GRU layer only); "all", every GRU layer and every head. Saved in
    # the checkpoint's profile_fields; a later --init run must give the same
    world_action_inputs: str = "first"
    # -- stage 3: refinement in imagination (the paper's objective; training/refine.py)
    refine_steps: int = 5000  # optimizer steps (our choice)
    refine_batch_size: int = 36  # global batch of start frames (paper: 36)
    refine_lr: float = 1e-5  # Adam (paper: 1e-5)
    refine_w_speed: float = 1.0  # reward per imagined m/s, per step
    refine_w_collision: float = 10.0  # cost of imagined collision probability, per step
    refine_w_uncertainty: float = 1.0  # cost of u_i + u_s + u_c, per step
    uncertainty_clip: float = 10.0  # each u is clipped here in the refinement loss
    no_uncertainty: bool = False  # the paper's "-unc" ablation: w_unc = 0
    # every N refinement steps the policy is also kept as a candidate (OUT/candidates/
    # refine<step>.pt), so how far to refine can be chosen by driving; 0: the final policy only
    refine_candidates_every: int = 0
    # -- carrt's safeguards on refinement (training/refine.py says why each). All off is the
    # paper's pure form: collision_prior_correction=false refine_w_anchor=0
    # refine_w_imitation=0 refine_center_gradient=false (refine_steering stays true).
    # p̂(collision) with the world model's collision class weight divided back out of its odds
    collision_prior_correction: bool = True
    refine_w_anchor: float = 10.0  # weight of Σ|μ−μ_start|²: the plan stays near its start
    refine_w_imitation: float = 50.0  # weight of imitation's L1 on demonstrations, each step
    # the world model's gradient on the actions less its mean over the batch of start frames
    refine_center_gradient: bool = True
    refine_steering: bool = True  # False: the world model's gradient moves the throttle only
    # -- research variants (research/variants/, run by research/variants/train.py; carrt-train
    # refuses them): refinement by search among fixed alternatives (refine_search.py)
    refine_search: bool = False
    refine_search_margin: float = 0.0  # how much better an alternative must be (objective units)
    refine_w_search: float = 50.0  # weight of the L1 toward the chosen alternative
    # refinement from the drives' recorded outcomes instead of imagination (refine_outcomes.py)
    refine_outcomes: bool = False
    outcome_advantage: bool = True  # False: every window weighs 1 (the control: no outcome)
    outcome_temperature: float = 1.0  # τ, in standard deviations of the advantage
    outcome_weight_max: float = 20.0  # cap on a window's weight
    # the world model's counterfactual check in the report (simulator only: counterfactual.py)
    counterfactual_starts: int = 0  # start states per placement; 0: off (a real car's data)
    counterfactual_layout: str = "hard"  # simulator layout of the held-out placements
    counterfactual_tracks: str = "200-204"  # held-out placements (never 100-199, the test sets)
    # -- every stage
    grad_clip: float = 1.0  # max global gradient norm
    log_every: int = 10  # steps between logged scalars (TensorBoard, loss history)
    ckpt_every: int = 500  # steps between checkpoints (also one at the end of each stage)
    eval_every: int = 0  # steps between held-out losses during training (0: off)
    eval_windows: int = 2048  # held-out windows used by the final metrics
    stop_after: int = 0  # stop after this many steps in this invocation (0: never); resumable
    export: bool = True  # write policy.onnx (carrt-export, run as a process after training)
    figures: bool = True  # write figures/*.png
    progress: bool = True  # tqdm bars on rank 0

    @property
    def profile_obj(self) -> Profile:
        """The named profile's sizes with this run's world_action_inputs."""
        return replace(get_profile(self.profile), world_action_inputs=self.world_action_inputs)

    def validate(self) -> None:
        if self.profile not in PROFILES:
            raise UsageError(
                f"unknown profile {self.profile!r}; choose one of {', '.join(PROFILES)}"
            )
        positive = [
            "imitation_batch_size", "world_model_batch_size", "refine_batch_size", "log_every",
            "imitation_lr", "world_model_lr", "refine_lr", "grad_clip", "uncertainty_clip",
            "imitation_lr_final", "reimitation_lr",
            "eval_windows", "outcome_temperature", "outcome_weight_max",
        ]  # fmt: skip
        for name in positive:
            if not getattr(self, name) > 0:
                raise UsageError(f"{name} must be > 0, got {getattr(self, name)}")
        non_negative = [
            "imitation_steps", "world_model_steps", "refine_steps", "ckpt_every", "eval_every",
            "stop_after", "num_workers", "collision_weight", "threads", "intervention_weight",
            "augment_hue", "augment_saturation", "augment_brightness", "augment_contrast",
            "counterfactual_starts", "refine_w_anchor", "refine_w_imitation",
            "refine_candidates_every", "refine_search_margin", "refine_w_search",
            "reimitation_steps",
        ]  # fmt: skip
        for name in non_negative:
            if getattr(self, name) < 0:
                raise UsageError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.world_action_inputs not in WORLD_ACTION_INPUTS:
            raise UsageError(
                f"world_action_inputs must be one of {', '.join(WORLD_ACTION_INPUTS)}, "
                f"got {self.world_action_inputs!r}"
            )
        if self.world_episodes and self.world_model_steps == 0:
            raise UsageError(
                "--world-episodes given but world_model_steps is 0: the world model would not "
                "learn them"
            )
        if not 0.0 <= self.val_fraction < 1.0:
            raise UsageError(f"val_fraction must be in [0, 1), got {self.val_fraction}")


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


def apply_set(cfg: IterateConfig, items: list[str]) -> IterateConfig:
    """`--set field=value` (carrt/settings.py: the parser the study shares); errors are
    UsageErrors (one line, exit 2)."""
    if any(item.partition("=")[0].strip() == "dirl" for item in items):
        raise UsageError("--set dirl: use --dirl (it writes the refined policy into OUT/refined/, "
                         "beside the imitated one)")  # fmt: skip
    try:
        return apply_sets(cfg, items, "IterateConfig in training/config.py", frozen=FROZEN)
    except UserError as exc:
        raise UsageError(str(exc)) from None


FROZEN = ("episodes", "world_episodes", "out", "dirl")  # given as --episodes etc., not --set


def dirl_fields() -> tuple[str, ...]:
    """The settings only the world model, refinement and the research variants read: the fields
    from world_model_steps to counterfactual_tracks, in their order above. A run without them
    (not `dirl`) leaves them out of its report."""
    names = [f.name for f in fields(IterateConfig)]
    return tuple(names[names.index("world_model_steps") : names.index("counterfactual_tracks") + 1])
