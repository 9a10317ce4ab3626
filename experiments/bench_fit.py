"""Wall time of the identification issue's fit of mu alone on the Nine, cold and with its programs cached:
``python experiments/bench_fit.py [--repeats 2] [--code DIR ...] [--out CSV]``.

The fit is the command a user runs on a curve the fitting model did not make (the accuracy tests'
reference, 1200 x 3 with exact contact at half the nominal increments)::

    jaxfric fit nine --data experiments/results/fit_bias_mesh/reference.csv --param mu --mesh 100x2 \\
        --set U_draw=10 --set mu=0.12 --window 1

Each fit runs in a new process, cold (a new, empty ``JAXFRIC_CACHE_DIR``) and then again with the programs
that fit put in that cache (``warm``). ``--code DIR``: the package from ``DIR`` (another checkout, first on
``PYTHONPATH``) instead of this one; with several, the versions take turns in each repeat, so that they
are compared within one sitting (single fits on the 2-core machine vary by 10 to 20 %). The wall time is
``fit.json``'s ``wall_s`` (the fit alone: the process's start and imports are not in it); ``process_s`` is
the whole command's. Writes ``results/bench_fit.csv``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

from benchutil import write_rows

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
DATA = os.path.join(HERE, "results", "fit_bias_mesh", "reference.csv")
FIT = ["fit", "nine", "--data", DATA, "--param", "mu", "--mesh", "100x2", "--set", "U_draw=10", "--set", "mu=0.12",
       "--window", "1", "--quiet"]


def one_fit(code: str, cache: str, out: str) -> dict:
    """The fit in a new process with the package from ``code``, compiling into (or reading) ``cache``."""
    env = {**os.environ, "JAXFRIC_CACHE_DIR": cache, "PYTHONPATH": code}
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "jaxfric", *FIT, "--out", out], env=env, cwd=code,
                          capture_output=True, text=True)
    process_s = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"the fit with {code} failed:\n{done.stderr[-2000:]}")
    with open(os.path.join(out, "fit.json")) as fh:
        summary = json.load(fh)
    return {"wall_s": round(summary["wall_s"], 2), "process_s": round(process_s, 2),
            "simulations": summary["n_simulations"], "mu": summary["params"]["mu"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--code", nargs="+", default=[ROOT], help="package checkouts to compare (default: this one)")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "bench_fit.csv"))
    args = ap.parse_args()
    rows = []
    for repeat in range(args.repeats):
        for code in args.code:
            with tempfile.TemporaryDirectory(prefix="jaxfric-bench-fit-") as tmp:
                cache = os.path.join(tmp, "cache")
                for state in ("cold", "warm"):
                    row = {"package": os.path.abspath(code), "repeat": repeat, "cache": state,
                           **one_fit(code, cache, os.path.join(tmp, state))}
                    print(row, flush=True)
                    rows.append(row)
    write_rows(args.out, rows)


if __name__ == "__main__":
    main()
