"""The four numbers the world-model check judges, and the issue's targets for them (issue 59,
item 3), from research/variants/counterfactual.score's result: one place, so the check
(world_model_check.py) and a single model's check (ground_model.py's `check`) judge alike."""

from __future__ import annotations

# The targets on held-out starts; a form passes when it meets all four.
TARGETS = {"steering_sign_agreement": 0.8, "ordered_right": 0.8, "collision_auroc": 0.9,
           "rank_correlation": 0.6}  # fmt: skip
# The near alternatives refinement chooses between (±0.3 steering, the throttle's): "ordered
# right" is the mean over them of the share of starts where the imagined objective orders the
# alternative against the plan as the true one does (ties in the truth left out).
NEAR = ("steer-0.3", "steer+0.3", "lift", "brake", "full")


def summary(result: dict) -> dict:
    """The four numbers the targets judge (and what explains them) from research/variants/
    counterfactual.score's result."""
    grads = result.get("gradient_agreement") or {}
    rows = result.get("by_sequence") or {}
    near = [rows[n]["orders_like_truth"] for n in NEAR
            if n in rows and rows[n]["orders_like_truth"] is not None]  # fmt: skip
    out = {
        "steering_sign_agreement": grads.get("steering"),
        "ordered_right": sum(near) / len(near) if near else None,
        "collision_auroc": result["collision_auroc"],
        "rank_correlation": result["rank_correlation"],
        "steering_sign_agreement_centred": grads.get("steering_centred"),
        "throttle_sign_agreement": grads.get("throttle"),
        "ordered_right_each": {n: rows[n]["orders_like_truth"] for n in NEAR if n in rows},
        "speed_mae": result["speed_mae"],
        "speed_mae_constant": result["speed_mae_constant"],
        # a steering-blind head shows as the plan's risk on a steering shift that truly crashes
        "risk_plan_vs_steer+0.6": {
            k: [rows[n][k] for n in ("plan", "steer+0.6") if n in rows]
            for k in ("true_collision", "imagined_risk")
        },
    }
    out["meets"] = {k: out[k] is not None and out[k] >= t for k, t in TARGETS.items()}
    out["passes"] = all(out["meets"].values())
    return out
