"""One chain of research/takeover_check.py run without driving or training: every step's command is
recorded instead, the policies are never evaluated, and every episode directory holds 1,000
frames. The rounds' tests (test_research_takeover_check.py) and the refinements' tests
(test_research_takeover_check_refine.py) both read the commands it records."""

from __future__ import annotations

import json

from research import dirl_steps, takeover_check, takeover_refine


def record_chain(monkeypatch, tmp_path, *sets, sigma=0.0, seed=0):
    """Run one chain of the check with `--set`s, recording its steps instead of running them:
    ({step name: argv}, the chain's result rows)."""
    cfg = takeover_check.parse(["--set", f"out={tmp_path}", *sets])
    steps = []
    monkeypatch.setattr(takeover_check, "evaluate", lambda *a: {"runs": [], "aggregate": {}})
    # every episode directory holds 1,000 frames; the second pool is handed out 1,000 at a time
    for module in (takeover_check, takeover_refine):
        monkeypatch.setattr(module, "frames_in", lambda paths: 1000 * len(paths))
    monkeypatch.setattr(
        dirl_steps, "top_up", lambda pool, frames: [pool / f"{i}" for i in range(frames // 1000)]
    )
    rows = []
    takeover_check.chain(
        cfg, lambda name, argv, marker: steps.append((name, argv)), sigma, seed, rows
    )
    return dict(steps), rows


def world_model_runs(runs, *names, counterfactual=lambda name: {"of": name}):
    """The world-model run directories `names` under `runs`, each with a metrics.json holding its
    counterfactual check (by default one naming the run, so a row shows which one it read)."""
    for name in names:
        (runs / name).mkdir(parents=True)
        (runs / name / "metrics.json").write_text(
            json.dumps({"counterfactual": counterfactual(name)})
        )
