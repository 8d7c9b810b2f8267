"""Every number of a training iteration, in one documented dataclass, and how `--set` changes it.

The stages (imitation, world model, refinement), iterate.py, the benchmarks and the study all
read this one config, and none of them imports it back from iterate.py, so the stages stand
alone. A profile name picks model sizes (training/profiles.py) and a preset of steps and batch
sizes (PRESETS); `--set field=value` overrides any field.
"""

from __future__ import annotations

from dataclasses import dataclass

from carrt.errors import UserError
from carrt.settings import apply_sets
from training.profiles import PROFILES, Profile, get_profile


class UsageError(UserError):
    """Bad input from the user: printed as one line, exit status 2."""


@dataclass
class IterateConfig:
    """Everything one iteration does. Defaults are the paper's numbers where it gives them."""

    # -- data and run
    episodes: tuple[str, ...] = ()  # episode directories, or directories of them
    # episodes the world model learns INSTEAD of `episodes` (carrt-train --world-episodes);
    # imitation and refinement still read `episodes`. Empty: the world model learns `episodes`
    # (the paper's). Why: a world model of a careful driver's frames learns to ignore the
    # steering (the image already says where it goes); one of a sloppier person's drives, whose
    # errors last and end in crashes, sees what steering off the line does, and refinement in
    # it took collisions away on validation and on fresh seeds (docs/dirl_study.md, 2026-11-27)
    world_episodes: tuple[str, ...] = ()
    out: str = ""  # run directory: checkpoints, policy.pt, policy.onnx, report.md, figures
    init: str | None = None  # previous iteration's run directory (None: iteration 1)
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
    # A later iteration (--init) learns by imitation again before the world model: from the
    # previous policy, imitation_steps on every labelled frame given, the demonstrations and the
    # person's take-overs in the new drives (states the policy itself reached, DAgger-style).
    # False: the paper's Algorithm 1, imitation once.
    reimitate: bool = False
    # -- stage 2: world model (evidential image/speed regression + collision classification)
    world_model_steps: int = 30000  # optimizer steps (our choice)
    world_model_batch_size: int = 32  # global batch (paper: 32)
    world_model_lr: float = 5e-4  # Adam (paper: 5e-4)
    w_image: float = 1.0  # weight of L_image in L_w (the cpu preset: 0.1, see PRESETS)
    w_speed: float = 1.0  # weight of L_speed in L_w
    w_collision: float = 1.0  # weight of L_collision in L_w
    collision_weight: float = 0.0  # weight of the collision class; 0 = n_safe/n_collision
    # True: the 0.5 s before a person's take-over (override edge) is labelled a collision for the
    # world model too, as the paper counts its e-stops (drives where the person takes over in
    # time hold the policy's near-crashes only as take-overs). Off by default, measured: on the
    # counterfactual check (docs/dirl_study.md, "Refinement on top of the take-over rounds")
    # the same world model ranked action sequences backwards with it (ρ −0.27, −0.24, +0.01,
    # a lifted throttle imagined safest from 73-90 % of the starts) and forwards without it;
    # the take-over labels teach "fast = collision" because the expert brakes after each
    takeovers_as_collisions: bool = False
    # with --init: the world model starts from its own (seeded) initialisation instead of the
    # previous run's, the policy still from --init: a member of an ensemble of world models on
    # the same frames, trained apart (carrt-refine-drift --members asks whether their spread
    # grows where refinement moved the plan; members that continue one run would agree)
    world_model_fresh: bool = False
    evidential_lambda: float = 0.01  # λ of the evidential regulariser |y−γ|(2ν+α)
    # mirror half of each batch left↔right, steering negated (training/augment.mirror_batch):
    # steering tied to the place on a one-way track cannot stand in for what the image shows
    mirror_world_model: bool = False
    # -- stage 3: refinement in imagination
    refine_steps: int = 5000  # optimizer steps (our choice)
    refine_batch_size: int = 36  # global batch of start frames (paper: 36)
    refine_lr: float = 1e-5  # Adam (paper: 1e-5)
    refine_w_speed: float = 1.0  # reward per imagined m/s, per step
    refine_w_collision: float = 10.0  # cost of imagined collision probability, per step
    refine_w_uncertainty: float = 1.0  # cost of u_i + u_s + u_c, per step
    uncertainty_clip: float = 10.0  # each u is clipped here in the refinement loss
    no_uncertainty: bool = False  # the paper's "-unc" ablation: w_unc = 0
    # safeguard: p̂(collision) in the objective with the collision class weight of the world
    # model's training divided back out of its odds (WorldModel.imagine): class-weighted, p̂
    # averages ~0.4 per step against ~0.04 true; measured on the counterfactual check
    # (2026-11-24, 3 seeds): rank correlation 0.28/0.54/0.63 for iterations 1-3 against
    # 0.31/0.35/0.30 uncorrected; False: the paper's form
    collision_prior_correction: bool = True
    # safeguard: Σ|μ−μ_start|² per start; 10 chosen by driving on validation placements
    # (docs/dirl_anchor_validation.json: without it refinement took completion 0.84 → 0.18);
    # 0: the paper's form
    refine_w_anchor: float = 10.0
    # safeguard: weight of imitation's L1 on demonstration frames during refinement (refine.py);
    # 50 measured on validation placements 200-219 (seed 0, iteration 1 → 2: completion 0.49
    # without it, 0.60 at 10, 0.68 at 50, from 0.73) and what every study, check and the demo
    # policy's refinement ran with (bench/study_config.py); 0: off (the paper's form)
    refine_w_imitation: float = 50.0
    # safeguard: the world model's gradient on the actions less its mean over the batch of
    # start frames (refine.py), so refinement changes what the policy does in one situation
    # against another and cannot shift every plan alike; measured on validation placements
    # 200-219 (2026-11-24): uncentred, iteration 2's collision term moved every plan's steering
    # by -0.02 to -0.04 and completion fell 0.80/0.81/0.76 -> 0.61/0.44/0.62 in 100 steps;
    # False: the paper's form
    refine_center_gradient: bool = True
    # safeguard: False keeps the world model's gradient off the steering channel, so refinement
    # moves only the throttle through it (steering is then held by the anchor and imitation
    # terms). Why: on the counterfactual check the gradient's sign at the plan agreed with the
    # truth for throttle 0.67/0.57/0.60 (s11 iteration 1, seeds 0-2) and for steering
    # 0.50/0.42/0.38, and full throttle was the truly best alternative at ~80 % of starts.
    # Measured by driving (docs/dirl_study.md, "null candidates", 3 seeds): no better than
    # random moves of its size, so the safeguard stays off by default (True, the paper's form)
    refine_steering: bool = True
    # safeguard: refinement by search instead of the gradient (training/refine_search.py):
    # from each start the world model imagines the plan and fixed alternatives (steering ±0.3 /
    # ±0.6, lift, brake, full throttle) and μ is pulled by L1 toward the best where it beats the
    # plan by more than refine_search_margin (objective units); why: the gradient at the plan
    # had the true sign 0.47-0.63 of the time on the counterfactual check, the ordering of
    # whole alternatives 0.86-0.93 for most; False: the paper's gradient
    refine_search: bool = False
    refine_search_margin: float = 0.0
    refine_w_search: float = 50.0  # weight of the L1 toward the chosen alternative
    # refinement from the drives' real outcomes instead of imagination (training/
    # refine_outcomes.py): the policy imitates its own executed actions in the AUTO steps of
    # the drives, weighted exp(A/(τ·std A)) by the advantage of the recorded return (the
    # objective above with recorded speeds and collisions, take-overs counted as collisions)
    # over a ridge baseline on the policy's features; the world model is not used. Why: the
    # world models' judgement of small changes to a plan drove no better than random moves
    # (docs/dirl_study.md, "null candidates"). False: the paper's refinement in imagination.
    refine_outcomes: bool = False
    outcome_advantage: bool = True  # False: every window weighs 1 (the control: no outcome)
    outcome_temperature: float = 1.0  # τ, in standard deviations of the advantage
    outcome_weight_max: float = 20.0  # cap on a window's weight
    # every N refinement steps the policy is also kept as a candidate (OUT/candidates/
    # refine<step>.pt) so that how far to refine can be chosen by driving
    # (training/select_by_driving.py); 0: only the final policy
    refine_candidates_every: int = 0
    # -- the world model's counterfactual check (simulator only: training/counterfactual.py)
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
    export: bool = True  # write policy.onnx through export.export_policy
    figures: bool = True  # write figures/*.png
    progress: bool = True  # tqdm bars on rank 0

    @property
    def profile_obj(self) -> Profile:
        return get_profile(self.profile)

    def validate(self) -> None:
        if self.profile not in PROFILES:
            raise UsageError(
                f"unknown profile {self.profile!r}; choose one of {', '.join(PROFILES)}"
            )
        positive = [
            "imitation_batch_size", "world_model_batch_size", "refine_batch_size", "log_every",
            "imitation_lr", "world_model_lr", "refine_lr", "grad_clip", "uncertainty_clip",
            "imitation_lr_final",
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
        ]  # fmt: skip
        for name in non_negative:
            if getattr(self, name) < 0:
                raise UsageError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.world_episodes and self.world_model_steps == 0:
            raise UsageError(
                "--world-episodes given but world_model_steps is 0: the world model would not "
                "learn them"
            )
        if not 0.0 <= self.val_fraction < 1.0:
            raise UsageError(f"val_fraction must be in [0, 1), got {self.val_fraction}")


# Steps and batches per profile, applied before --steps/--set: the paper's numbers need a GPU.
PRESETS: dict[str, dict] = {
    "tiny": dict(imitation_steps=30, world_model_steps=30, refine_steps=20,
                 imitation_batch_size=16, world_model_batch_size=8, refine_batch_size=8,
                 refine_lr=1e-4, log_every=1, ckpt_every=10, eval_windows=256),
    "cpu": dict(imitation_steps=2000, world_model_steps=3000, refine_steps=500,
                imitation_batch_size=64, world_model_batch_size=32, refine_batch_size=16,
                log_every=10, ckpt_every=250, eval_every=500, augment=True,
                # measured on the counterfactual check (issue 14): at 1.0 the per-pixel NLL's
                # gradients drown the collision term and the head never learns what steering does
                w_image=0.1),
    "paper": dict(eval_every=1000, augment=True),
}  # fmt: skip


def apply_set(cfg: IterateConfig, items: list[str]) -> IterateConfig:
    """`--set field=value` (carrt/settings.py: the parser the study shares); errors are
    UsageErrors (one line, exit 2)."""
    try:
        return apply_sets(cfg, items, "IterateConfig in training/config.py", frozen=FROZEN)
    except UserError as exc:
        raise UsageError(str(exc)) from None


FROZEN = ("episodes", "world_episodes", "out")  # given as --episodes etc., not --set
