"""The simulator's worker pools: one math thread per worker (carrt/sim/pool.py)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from carrt.sim.pool import worker_pool


def blas_threads() -> dict[str, int]:
    """In a worker: each loaded BLAS/OpenMP library's thread count."""
    import numpy  # noqa: F401  (loads OpenBLAS, as every simulator worker does)
    from threadpoolctl import threadpool_info

    return {info["internal_api"]: info["num_threads"] for info in threadpool_info()}


@pytest.mark.parametrize("start_method", ["spawn", "forkserver"])
def test_each_worker_runs_one_blas_thread_where_the_parent_runs_several(start_method, monkeypatch):
    # the parent's default, forced above one so the check means something on any machine
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "2")
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    with worker_pool(2, start_method) as pool:
        got = [pool.submit(blas_threads).result() for _ in range(4)]
    assert all(g.get("openblas") == 1 for g in got), got
    assert all(n == 1 for g in got for n in g.values()), got


def test_the_limit_also_holds_for_a_library_loaded_before_the_worker_started(monkeypatch):
    # a spawned worker imports its parent's main module (numpy with it) before the initializer
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "2")
    code = (
        "import json, numpy\n"
        "from threadpoolctl import threadpool_info\n"
        "from carrt.sim.pool import limit_worker_threads\n"
        "before = {i['internal_api']: i['num_threads'] for i in threadpool_info()}\n"
        "limit_worker_threads()\n"
        "after = {i['internal_api']: i['num_threads'] for i in threadpool_info()}\n"
        "print(json.dumps([before, after]))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    before, after = json.loads(out.stdout)
    assert before.get("openblas") == 2 and after.get("openblas") == 1, (before, after)
