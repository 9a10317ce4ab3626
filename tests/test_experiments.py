"""The experiment scripts run at a tiny size (they compute when called, write only under __main__)."""

import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "experiments"))

import bench_core  # noqa: E402


def test_bench_core_runs_at_a_tiny_size():
    row = bench_core.bench(nx=12, ny=2, repeat=1)
    assert row["converged"] and row["n_steps"] >= 30 and row["newton_iters"] >= row["n_steps"]
    assert row["ms_assembly"] > 0 and row["ms_solve"] > 0 and row["compile_s"] > 0
