"""`carrt episodes rerun` (issue 60, item 3): episodes into a Rerun recording, read back with
Rerun's own chunk reader: the entities, their row counts and values are the episode's."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import rerun.chunk as rerun_chunk
from episode_factory import mixed_steps, run_cli, write_episode

from carrt.episodes import read_episode
from carrt.interfaces import Mode


def _read(path) -> dict[str, list]:
    """Entity path → its chunks' record batches (static properties left out)."""
    out: dict[str, list] = {}
    for chunk in rerun_chunk.RrdReader(path).store().stream():
        out.setdefault(str(chunk.entity_path), []).append(chunk.to_record_batch())
    return out


def _column(batches: list, name: str, step_order: bool = True) -> list:
    table = pa.Table.from_batches(batches)
    names = [n for n in table.column_names if n.endswith(name)]
    assert names, table.column_names
    rows = list(zip(table.column("step").to_pylist(), table.column(names[0]).to_pylist(),
                    strict=True))  # fmt: skip
    return [value for _, value in sorted(rows)] if step_order else [v for _, v in rows]


def test_episodes_read_back_from_the_rrd_with_rerun(tmp_path, capsys):
    first = write_episode(tmp_path / "eps", mixed_steps(30, seed=1))
    second = write_episode(tmp_path / "eps", mixed_steps(12, seed=2))
    run_cli(["episodes", "mark", str(first), "--exclude", "1.0-1.5"])
    out = tmp_path / "run.rrd"
    assert run_cli(["episodes", "rerun", str(tmp_path / "eps"), "-o", str(out)]) == 0
    assert f"wrote {out} (2 episode(s), 42 steps)" in capsys.readouterr().out
    entities = _read(out)
    for path in (first, second):
        ep = read_episode(path)
        root = f"/{ep.name}"
        camera = pa.Table.from_batches(entities[f"{root}/camera"])
        assert camera.num_rows == ep.n
        speeds = [v[0] for v in _column(entities[f"{root}/speed"], "Scalars:scalars")]
        assert np.allclose(speeds, ep.steps["speed_mps"])
        steering = _column(entities[f"{root}/action/person/steering"], "Scalars:scalars")
        assert np.allclose([v[0] for v in steering], ep.steps["human_action"][:, 0])
        auto = int(np.sum(ep.steps["mode"] == int(Mode.AUTO)))
        policy = pa.Table.from_batches(entities[f"{root}/action/policy/throttle"])
        assert policy.num_rows == auto  # the policy's action only where it drove
        assert pa.Table.from_batches(entities[f"{root}/plan/mu"]).num_rows == auto
        collision = [v[0] for v in _column(entities[f"{root}/collision"], "Scalars:scalars")]
        assert np.array_equal(collision, ep.collision.astype(float))
    excluded = [v[0] for v in _column(entities[f"/{read_episode(first).name}/excluded"],
                                       "Scalars:scalars")]  # fmt: skip
    assert sum(excluded) == 5 and excluded[10:15] == [1.0] * 5


def test_a_file_that_is_not_rrd_is_one_line(tmp_path, capsys):
    from carrt.cli import main

    write_episode(tmp_path / "eps", mixed_steps(3))
    assert main(["episodes", "rerun", str(tmp_path / "eps"), "-o", str(tmp_path / "x.mp4")]) == 2
    assert "a Rerun recording ends in .rrd" in capsys.readouterr().err
