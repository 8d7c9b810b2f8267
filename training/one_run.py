"""One training run called from code or the command line, what can go wrong turned into one
line and an exit status.

carrt-train (training/iterate.py) runs one or two per iteration through `run_iteration`, and
so does research/variants/train.py; `main` is one run of the iteration's flags as they are
given (no imitation/refined split, no loop), what the tests call. The run itself is
training/training_run.py's `run`.

Exit status: 0 done (or stopped by stop_after), 1 diverged or export refused, 2 bad input, 130
interrupted.
"""

from __future__ import annotations

import dataclasses
import sys

from carrt.errors import UserError
from training import checkpoint as ck
from training import training_run
from training.config import TrainingConfig, UsageError
from training.trainer import Interrupted, StopRequested, init_distributed, shutdown_distributed
from training.training_args import Parser, add_iteration_args, config_from


def main(argv: list[str] | None = None, *, dirl: bool = False) -> int:
    """One run of carrt-train's iteration flags (`dirl`: with the world model and refinement,
    its policy.* the last stage's, as research/variants/train.py runs it)."""
    try:
        p = Parser(prog="carrt-train", description=__doc__.split("\n")[0])
        add_iteration_args(p)
        cfg = dataclasses.replace(config_from(p.parse_args(argv)), dirl=dirl)
    except UserError as exc:
        return bad_input(exc)
    return run_iteration(cfg)[0]


def bad_input(exc: Exception) -> int:
    """A config that cannot run, in one line: exit status 2."""
    print(f"carrt-train: error: {exc}", file=sys.stderr)
    return 2


def run_iteration(
    cfg: TrainingConfig, variants: training_run.Variants | None = None
) -> tuple[int, bool]:
    """Run the iteration `cfg` describes (in this process's torchrun job, if any): its exit
    status, and whether it got to its end (not when it stopped at stop_after, failed or was
    interrupted)."""
    dist = None
    try:
        try:
            dist = init_distributed(cfg.device)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        summary = training_run.run(cfg, dist, variants)
        if dist.is_main:
            for line in summary.get("lines", []):
                print(line)
        code = summary.get("exit_code", 0)
        return code, code == 0
    except (UserError, ck.CheckpointError) as exc:
        if dist is None or dist.is_main:
            bad_input(exc)
        return 2, False
    except StopRequested as exc:
        if dist is None or dist.is_main:
            print(f"carrt-train: stopped at {exc} (stop_after); run the same command to resume")
        return 0, False
    except FloatingPointError as exc:
        print(
            f"carrt-train: training diverged: {exc}; the last checkpoint is intact", file=sys.stderr
        )
        return 1, False
    except Interrupted as exc:
        if dist is None or dist.is_main:
            print(f"carrt-train: interrupted at {exc}; checkpoint saved, run the same command "
                  "to resume", file=sys.stderr)  # fmt: skip
        return 130, False
    except KeyboardInterrupt:
        print("carrt-train: interrupted; run the same command to resume from the last checkpoint",
              file=sys.stderr)  # fmt: skip
        return 130, False
    finally:
        shutdown_distributed()
