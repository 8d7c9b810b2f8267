"""The research variants' settings: carrt-train's TrainingConfig and ten more, declared alike.

research/variants/train.py builds this config (carrt-train builds TrainingConfig, which lacks
these fields and refuses each by name: training/config.py RESEARCH_SETTINGS, kept equal to the
fields below by a test). Each is a `setting()` (training/setting.py), so `research/variants/
train.py --settings` lists them with their docs and the same checks refuse a bad value.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from training.config import TrainingConfig
from training.setting import setting


@dataclass
class ResearchConfig(TrainingConfig):
    """TrainingConfig with the research variants' settings (research/variants/). Every one off
    (refine_search, refine_outcomes false, counterfactual_starts 0) is carrt-train's run."""

    GROUPS: ClassVar[tuple[tuple[str, str], ...]] = (
        *TrainingConfig.GROUPS,
        ("Research: refinement by search among fixed alternatives "
         "(research/variants/refine_search.py)", "refine_search"),
        ("Research: refinement from the drives' recorded outcomes "
         "(research/variants/refine_outcomes.py)", "refine_outcomes"),
        ("Research: the world model's counterfactual check in the report (simulator only: "
         "research/variants/counterfactual.py)", "counterfactual_starts"),
    )  # fmt: skip

    refine_search: bool = setting(
        False, "refinement pulls μ toward the imagined-best of fixed alternatives instead of "
        "following the gradient",
    )  # fmt: skip
    refine_search_margin: float = setting(
        0.0, "how much better an alternative must be (objective units)", lo=0
    )
    refine_w_search: float = setting(50.0, "weight of the L1 toward the chosen alternative", lo=0)
    refine_outcomes: bool = setting(
        False, "refinement from the drives' recorded outcomes instead of imagination"
    )
    outcome_advantage: bool = setting(True, "off: every window weighs 1 (the control: no outcome)")
    outcome_temperature: float = setting(1.0, "τ, in standard deviations of the advantage", above=0)
    outcome_weight_max: float = setting(20.0, "cap on a window's weight", above=0)
    counterfactual_starts: int = setting(
        0, "start states per placement; 0: off (a real car's data)", lo=0
    )
    counterfactual_layout: str = setting("hard", "simulator layout of the held-out placements")
    counterfactual_tracks: str = setting(
        "200-204", "held-out placements (never 100-199, the test sets)"
    )
