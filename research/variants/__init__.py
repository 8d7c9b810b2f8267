"""Research-only variants of the training stages and their diagnostics (not installed).

refine_search, refine_outcomes: other refinements than the paper's; counterfactual, refine_drift:
checks of a world model against the simulator and of where refinement moved the plan;
select_by_driving: choose among refinement candidates by driving them. `train.py` is
carrt-train with these plugged in (training.training_run.Variants); the study runs it. `config.py`
holds their settings (ResearchConfig: carrt-train's and theirs).
"""
