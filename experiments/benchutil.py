"""Timing and output helpers shared by the benchmark scripts."""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import time

import equinox as eqx
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


def on_leaves(fn, *args):
    """``(compiled, leaves)``: ``fn(*args)`` compiled as a function of the array leaves of ``args`` (their other
    leaves static), and those leaves, for ``median_time(compiled, leaves)``. A call then passes one flat list
    of arrays, which ``jax.jit`` dispatches in microseconds, where ``eqx.filter_jit`` partitions and flattens
    every module of its arguments again at each call: about a millisecond for a step's arguments, which a
    part of a Newton iteration timed on its own would count as its cost."""
    dynamic, static = eqx.partition(args, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(dynamic)
    compiled = jax.jit(lambda flat: fn(*eqx.combine(jax.tree_util.tree_unflatten(treedef, flat), static)))
    return compiled, leaves


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


def run_cases_main(argv, doc: str, cases, run_one, default_root: str, csv_path: str) -> int:
    """The command line of a study of named run cases, each a run directory under ``--root`` (read back when
    it is there): ``--only CASE ...`` runs some (to spread them over processes; no CSV then), ``--table``
    only reads back what is on disk; prints one line per case and writes the rows to ``csv_path``.
    ``run_one(name, root)`` returns a case's row with 'case', 'steady_drawing_force', 'n_steps',
    'newton_iters_total', 'wall_s' and 'converged'."""
    p = argparse.ArgumentParser(description=doc.splitlines()[0])
    p.add_argument("--root", default=default_root)
    p.add_argument("--only", nargs="*", choices=sorted(cases), help="run these cases only")
    p.add_argument("--table", action="store_true", help="read back the cases on disk, run none")
    a = p.parse_args(argv)
    names = a.only or list(cases)
    if a.table:
        names = [n for n in cases if os.path.exists(os.path.join(a.root, n, "summary.json"))]
    rows = [run_one(n, a.root) for n in names]
    width = max(len(n) for n in names) + 1 if names else 1
    for r in rows:
        print(f"{r['case']:<{width}} {r['steady_drawing_force']:.3f} N/mm  {r['n_steps']} steps  "
              f"{r['newton_iters_total']} it.  {r['wall_s']:.0f} s  converged {r['converged']}")
    if not a.only and rows:   # nothing on disk: the CSV stays as it is
        write_rows(csv_path, rows)
    return 0


def run_or_read(out: str, build, tag: str, label: str, figures: bool = False) -> dict:
    """The summary of the run directory ``out``, running it first where it is not there: ``build()`` gives
    the scene (``jaxfric.scenes.Scene``), run to its end (or its failure, which is written too: remove the
    directory to run it again) and written with the run's figures where ``figures``; ``label`` is printed
    to stderr when it runs."""
    import jaxfric as jf  # here: the scripts that use only the timing and CSV helpers do without the package
    from jaxfric.io import output
    from jaxfric.io.instants import InstantRows

    path = os.path.join(out, "summary.json")
    if not os.path.exists(path):
        scene = build()
        print(label, file=sys.stderr, flush=True)
        result = jf.run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                        snapshot=scene.snapshot, keep_snapshots=InstantRows(scene.name), progress=False,
                        raise_on_failure=False)
        output.write_run(scene, result, out, tag=tag, figures=figures)
    with open(path) as fh:
        return json.load(fh)
