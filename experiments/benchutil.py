"""Timing and output helpers shared by the benchmark scripts."""

from __future__ import annotations

import csv
import os
import time

import jax
import numpy as np


def median_time(fn, *args, repeat: int = 20, clock=time.perf_counter) -> float:
    """Median time (s) of ``fn(*args)`` over ``repeat`` calls, after one warm-up (compile) call: wall
    time, or process CPU time with ``clock=time.process_time`` (for a core shared with other work)."""
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeat):
        t0 = clock()
        jax.block_until_ready(fn(*args))
        times.append(clock() - t0)
    return float(np.median(times))


def read_rows(path: str) -> list[dict]:
    """The rows of the CSV at ``path`` as dicts of strings ([] where there is no such file)."""
    if not os.path.exists(path):
        return []
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def write_rows(path: str, rows: list[dict]) -> None:
    """Write dict rows as CSV (header from the first row) and say where, with the device."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print(f"written {path}; device {jax.devices()[0].device_kind}, jax {jax.__version__}")
