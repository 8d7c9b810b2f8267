"""The study's one documented config: every number of `python -m research.dirl_sim`, and its ranges.

Its own module because the study and the checks built on it (research/takeover_check.py,
research/outcome_check.py) all run with a StudyConfig, and each must refuse the same bad values in
the same words: `range_problems` is the one place those ranges live.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass


def usable_cores() -> int:
    """The cores this process may run on (its affinity, not the machine's count)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


@dataclass
class StudyConfig:
    """Every number of the study. The defaults are its current design, the settings of the
    runs of 2026-11-25 (research/LOG.md: "Search from iteration 2" and the noisy demonstrations
    after it); each table there gives the `--set`s it was run with."""

    out: str = "research/runs/dirl_sim"
    profile: str = "cpu"  # model sizes (training/profiles.py)
    seeds: tuple[int, ...] = (0, 1, 2)  # training seeds: model init, batch order, DIRL drives
    robustness_seeds: tuple[int, ...] = (0, 1, 2)  # seeds of the σ > 0 chains
    layout: str = "hard"  # 8 obstacles
    train_tracks: str = "1000-1039"  # demonstrations and DIRL drives
    extra_tracks: str = "1040-1099"  # the second demonstration pool (IL at equal frames)
    # held out: never recorded, never tuned on. 100 placements × 30 s: on 5 (100-104, until
    # 2026-11-24) and then 25 × 60 s (until 2026-11-25) the placements' own spread was as large
    # as the DIRL-IL differences being judged (a σ 0 "+0.06 ± 0.04" on 25 was −0.02 ± 0.06 on
    # 100-199); completion is mostly decided in the first 30 s, so this doubles driving, not more
    eval_tracks: str = "100-199"
    counterfactual_tracks: str = "200-204"  # held out, for the world model check
    counterfactual_starts: int = 6  # start states per counterfactual placement
    expert_episodes: int = 6  # per training placement, one lap each from a random place
    demo_noise: tuple[float, ...] = (0.0, 0.5, 1.0)  # σ on the expert's commands (robustness)
    # how long the imperfect person's error lasts (s; carrt.sim.pilot): 0, a fresh error every
    # command (the paper's words; measured, it made imitation better, as DART's noise does);
    # 0.5, an error that lasts about as long as a person takes to notice and correct it
    demo_noise_tau: float = 0.0
    iterations: int = 3  # DIRL iterations (σ = 0)
    robustness_iterations: int = 1  # DIRL iterations for σ > 0
    drive_seconds: float = 40.0  # simulated s per placement per DIRL iteration
    # Where iteration k drives (its exploration drives and its take-overs): entry k−1, e.g.
    # 1040-1053,1054-1067 (the placements IL at equal frames takes its extra demonstrations
    # from first: the person moved the buckets, and both arms see the new placements).
    # Empty: train_tracks, the same placements as the demonstrations every iteration.
    iteration_tracks: tuple[str, ...] = ("1040-1054", "1055-1069", "1070-1084")
    # Noise on the policy's commands in those drives (noise.during_auto): without it steering
    # is a function of the place and the world model learns its collision risk backwards
    # (docs/architecture.md at 38d191d, "what the world model can learn"); the paper's ±0.3
    # half the time was not enough, ±0.8 held 0.5-1.5 s for 80 % of the time was
    # (counterfactual check).
    drive_explore: bool = True
    explore_fraction: float = 0.8  # share of drive time perturbed (noise.fraction)
    explore_amplitude: float = 0.8  # uniform ± on steering and throttle (noise.amplitude)
    explore_hold_s: tuple[float, ...] = (0.5, 1.5)  # each value held this long (min, max)
    # Take-overs: after those drives, the policy drives the training placements again, this
    # many simulated s each, with the expert playing the person who takes over before a crash
    # (`sim_data interventions`, the same σ as the demonstrations): the override every real-car
    # drive has, whose commands label states the policy itself reached. 0: none (the paper's
    # drives, e-stop = collision, and the studies before 2026-11-24's sixth run).
    takeover_seconds: float = 21.0
    # A DIRL iteration first learns by imitation again, from the previous policy, on every
    # labelled frame (demonstrations + take-overs): iterate.py's `reimitate`, this many steps at
    # this learning rate (a fine-tune of the previous policy; IL trains 3000 steps at 1e-3).
    # Its policy is a selection candidate ("imitated") and gets its own row (the ablation: DIRL
    # without refinement). 0: the paper's Algorithm 1, imitation once.
    reimitate_steps: int = 1000
    reimitate_lr: float = 3e-4
    w_image: float = 0.1  # the world model's image-loss weight (training/config.py)
    imitation_steps: int = 3000
    world_model_steps: int = 3000  # iteration 1
    world_model_steps_next: int = 1500  # later iterations continue the previous world model
    refine_steps: int = 300
    refine_w_anchor: float = 10.0  # the safeguard (training/refine.py); 0: the paper's form
    # The second safeguard (training/refine.py): imitation's L1 on the demonstrations during
    # refinement. 50 was measured on validation placements 200-219 (seed 0, iteration 1 → 2:
    # completion 0.49 without it, 0.60 at 10, 0.68 at 50, from 0.73); 0: off.
    refine_w_imitation: float = 50.0
    # Another safeguard: the world model's gradient on the actions, centred over the batch of starts
    # (training/refine.py), so refinement cannot shift every plan alike (measured on the
    # validation placements: uncentred, iteration 2 moved every plan's steering by -0.02 to -0.04
    # and completion fell by 0.2-0.4 within 100 steps). False: the paper's gradient.
    refine_center_gradient: bool = True
    # p̂(collision) in the objective with the world model's collision class weight divided out
    # of its odds (WorldModel.imagine): class-weighted, p̂ is ~10x the true rate and the
    # collision term ~10x its weight. False: the paper's form (raw p̂).
    collision_prior_correction: bool = True
    # Refinement by search in the world model's imagination instead of its gradient
    # (research/variants/refine_search.py): μ pulled toward the imagined-best of fixed
    # alternatives where it beats the plan by the margin. False: the paper's gradient.
    refine_search: bool = True
    refine_search_margin: float = 0.0
    # With refine_search: the first DIRL iteration refined by search, the ones before it by the
    # gradient (2: iteration 1 as the gradient studies ran it, search once the world model has
    # seen the policy's own drives twice; the check's ρ rose from 0.3 to 0.5-0.6 by then).
    search_from: int = 2
    # Where iteration 1 is the gradient's (refine_search false, or search_from ≥ 2): a row "DIRL
    # search iter 1" at σ 0, iteration 1's world model and start policy refined by search,
    # selected and evaluated like the others.
    compare_search: bool = True
    # DIRL -unc (the paper's ablation) at every σ 0 iteration, each from that iteration's world
    # model and start policy; False: at iteration 1 only, as the studies before 2026-11-25 ran it.
    unc_every_iteration: bool = True
    # The third safeguard: refinement keeps a candidate every `refine_candidates_every` steps and
    # the policy it started from is one too; each is driven on validation placements and the best
    # is the iteration's policy (research/variants/select_by_driving.py). False: the last
    # step's policy.
    select_by_driving: bool = True
    refine_candidates_every: int = 100
    # Validation placements (neither trained on nor evaluated): entry k−1 for iteration k, one
    # entry for all. Each iteration its own: the start was chosen on the previous iteration's
    # placements, and its numbers there are biased upwards by that choice (winner's curse).
    select_tracks: tuple[str, ...] = ("200-219", "220-239", "240-259")
    # The policy imitation made ("imitated", with reimitate; else the start) is kept unless a
    # candidate beats it by this many standard errors of the paired per-placement score
    # (research/variants/select_by_driving.py). 0: the best score, the rule of the studies until
    # 2026-11-24's seventh run.
    select_margin_z: float = 2.0
    select_seconds: float = 30.0  # simulated s per validation placement and candidate
    eval_seconds: float = 30.0  # simulated seconds per held-out placement (a lap is ~7 s)
    # 0: every core this process may use (2 here; 16 on the GPU machine of 2026-11-25, where
    # the defaults of 2 would have left 14 idle)
    threads: int = 0  # torch threads in all
    jobs: int = 0  # simulator processes in all
    # Steps of different chains run at once, each with threads/parallel torch threads and
    # jobs/parallel simulator processes (research/study_steps.py; measured on the full study: two
    # 1-thread imitation runs side by side do 1.10× the work of one 2-thread run, two 1-process
    # evaluations 1.14×). 1: one step at a time.
    parallel: int = 2
    report_only: bool = False  # --report: tables from the finished steps, nothing run

    def all_threads(self) -> int:
        return self.threads or usable_cores()

    def all_jobs(self) -> int:
        return self.jobs or usable_cores()

    def step_threads(self) -> int:
        return max(1, self.all_threads() // max(1, self.parallel))

    def step_jobs(self) -> int:
        return max(1, self.all_jobs() // max(1, self.parallel))

    def iterate_overrides(self) -> list[str]:
        return [f"threads={self.step_threads()}", "progress=false", "figures=false"]


QUICK = dict(
    out="research/runs/dirl_sim_quick", profile="tiny", seeds=(0,), robustness_seeds=(0,),
    train_tracks="1000", extra_tracks="1001-1002", eval_tracks="100", counterfactual_tracks="200",
    counterfactual_starts=2, expert_episodes=2, demo_noise=(0.0, 0.5), iterations=2,
    drive_seconds=5.0, imitation_steps=30, world_model_steps=30, world_model_steps_next=10,
    refine_steps=10, eval_seconds=10.0, refine_candidates_every=5, select_tracks=("200",),
    select_seconds=5.0, takeover_seconds=5.0, reimitate_steps=10, iteration_tracks=(),
)  # fmt: skip


def range_problems(cfg: StudyConfig, name: Callable[[str], str] = str) -> list[str]:
    """What is out of range in `cfg`, one line each (empty when nothing is); `name` spells a
    field as the user set it (a check's `study.` prefix). Cross-field rules that only the study
    itself has (iteration_tracks and select_tracks per iteration) stay in its parser."""
    problems = []
    if cfg.threads < 0 or cfg.jobs < 0:
        problems.append(f"{name('threads')} {cfg.threads}, {name('jobs')} {cfg.jobs}: "
                        "0 (every core) or more")  # fmt: skip
    if cfg.parallel < 1:
        problems.append(f"{name('parallel')}: {cfg.parallel} (1 or more)")
    if not cfg.demo_noise or any(not 0 <= s < 10 for s in cfg.demo_noise):
        problems.append(f"{name('demo_noise')}: {cfg.demo_noise} (one or more σ in [0, 10))")
    if not (math.isfinite(cfg.demo_noise_tau) and cfg.demo_noise_tau >= 0):
        problems.append(f"{name('demo_noise_tau')}: {cfg.demo_noise_tau} (seconds, 0 or more)")
    return problems
