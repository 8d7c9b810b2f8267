"""Synthetic steps and episodes for tests: deterministic from (seed, index), so a test (or a
killed child process) can regenerate exactly what was written and compare it."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from carrt.episodes import EpisodeWriter, run_metadata
from carrt.episodes import cli as episodes_cli
from carrt.interfaces import Mode, Step
from carrt.model_contract import HORIZON, IMAGE_SHAPE


def image_for(index: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng([seed, index])
    return rng.integers(0, 256, size=IMAGE_SHAPE, dtype=np.uint8)


def make_step(
    index: int,
    *,
    seed: int = 0,
    t0: float = 1000.0,
    period: float = 0.1,
    mode: Mode = Mode.MANUAL,
    **overrides: Any,
) -> Step:
    """Step `index` of a synthetic episode; every numeric field differs per step."""
    rng = np.random.default_rng([seed, index, 1])
    t = t0 + index * period
    auto = mode == Mode.AUTO
    fields: dict[str, Any] = dict(
        index=index,
        image=image_for(index, seed),
        frame_captured_at=t,
        command_sent_at=t + 0.0123 + 1e-9 * index,
        wall_time=1.7e9 + t,
        speed_mps=float(rng.uniform(0, 2.5)),
        encoder_ticks=int(index * 37 + seed),
        human_action=(float(rng.uniform(-1, 1)), float(rng.uniform(0, 1))),
        policy_action=(0.25, 0.5) if auto else (float("nan"), float("nan")),
        executed_action=(float(rng.uniform(-1, 1)), float(rng.uniform(0, 1))),
        mode=mode,
        override=False,
        estop=False,
        noise=bool(index % 3 == 0),
        collision=False,
        lap=False,
        plan_mu=rng.uniform(-1, 1, (HORIZON, 2)).astype(np.float32) if auto else None,
        plan_sigma=rng.uniform(0.01, 1, (HORIZON, 2)).astype(np.float32) if auto else None,
    )
    fields.update(overrides)
    return Step(**fields)


def mixed_steps(n: int = 30, seed: int = 0) -> list[Step]:
    """Every mode and flag appears; AUTO steps carry a plan."""
    modes = [Mode.DISARMED, Mode.MANUAL, Mode.AUTO, Mode.AUTO, Mode.MANUAL, Mode.ESTOP]
    steps = []
    for i in range(n):
        mode = modes[i % len(modes)]
        steps.append(
            make_step(
                i,
                seed=seed,
                mode=mode,
                override=i % 7 == 3,
                estop=mode == Mode.ESTOP,
                collision=i == 17,
                lap=i % 10 == 5,
            )
        )
    return steps


def metadata(**extra: Any) -> dict[str, Any]:
    return run_metadata(command="test", car_config={"loop": {"rate_hz": 10.0}}, **extra)


def write_episode(
    root: Path,
    steps: list[Step],
    *,
    reason: str = "stopped",
    meta: dict[str, Any] | None = None,
    **writer_kwargs: Any,
) -> Path:
    """Record `steps` as one finished episode and return its directory."""
    writer_kwargs.setdefault("queue_steps", max(2, len(steps) + 1))
    with EpisodeWriter(root, **writer_kwargs) as writer:
        writer.begin(meta if meta is not None else metadata())
        for step in steps:
            assert writer.write(step)
        writer.end(reason)
        assert writer.flush()
        assert writer.error is None, writer.error
        return writer.last_episode_path


def assert_step_matches(record: np.void, frame: np.ndarray, step: Step) -> None:
    """Every stored field equals what was written (floats at their stored precision)."""
    assert np.array_equal(frame, step.image)
    assert int(record["index"]) == step.index
    assert float(record["frame_captured_at"]) == step.frame_captured_at  # measured: exact
    assert float(record["command_sent_at"]) == step.command_sent_at
    assert float(record["wall_time"]) == step.wall_time
    assert record["speed_mps"] == np.float32(step.speed_mps)
    assert int(record["encoder_ticks"]) == step.encoder_ticks
    for name in ("human_action", "policy_action", "executed_action"):
        np.testing.assert_array_equal(record[name], np.float32(getattr(step, name)))
    assert int(record["mode"]) == int(step.mode)
    for name in ("override", "estop", "noise", "collision", "lap"):
        assert bool(record[name]) == getattr(step, name), name
    for name in ("plan_mu", "plan_sigma"):
        plan = getattr(step, name)
        if plan is None:
            assert np.isnan(record[name]).all()
        else:
            np.testing.assert_array_equal(record[name], plan.astype(np.float32))


def run_cli(argv: list[str]) -> int:
    """`carrt episodes ...` in-process (argv starts with "episodes"), its errors raised rather
    than turned into exit code 2: the one-line error handling is carrt.cli.main's, tested on its
    own."""
    parser = argparse.ArgumentParser(prog="carrt")
    episodes_cli.add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)
