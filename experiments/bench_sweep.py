"""Cost of a vmapped friction sweep against single runs (issue: batched sweeps).

    python experiments/bench_sweep.py [--scene flat_die] [--variant const_force] [--members 16]
                                      [--mesh NXxNY] [--set NAME=VALUE ...]

Runs ``members`` friction coefficients evenly spaced in [0.05, 0.3] as one compiled vmapped simulation
(:func:`jaxfric.sweep.sweep`) and as single runs (:func:`jaxfric.run.run`, compiled once), checks that
the histories agree to 1e-10 of each column's scale, and writes
``experiments/results/bench_sweep_<scene>.csv`` with compile and solve times and their ratios.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from benchutil import write_rows  # noqa: E402

import jaxfric as jf  # noqa: E402
from jaxfric import scenes  # noqa: E402
from jaxfric.sweep import sweep  # noqa: E402


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="flat_die")
    p.add_argument("--variant", default=None)
    p.add_argument("--members", type=int, default=16)
    p.add_argument("--mesh", default=None)
    p.add_argument("--set", dest="overrides", action="append", default=[])
    a = p.parse_args(argv)
    extra = dict(s.split("=", 1) for s in a.overrides)
    if a.mesh:
        extra["mesh"] = a.mesh
    mus = np.linspace(0.05, 0.3, a.members)
    built = [scenes.make(a.scene, a.variant, "penalty", {**extra, "mu": float(m)}) for m in mus]
    out = sweep([s.model for s in built], control=built[0].control, observe=built[0].observe)
    singles, compile_single, worst = [], None, 0.0
    for i, s in enumerate(built):
        r = jf.run(s.model, control=s.control, observe=s.observe, progress=False)
        compile_single = r.compile_s if compile_single is None else compile_single
        singles.append(r.wall_s)
        h = out.history(i)
        for name in ("drawing_force", "clamping_force", "time"):
            scale = max(float(np.max(np.abs(r.history[name]))), 1e-300)
            worst = max(worst, float(np.max(np.abs(h[name] - r.history[name]))) / scale)
    mean_single = float(np.mean(singles))
    row = {"scene": a.scene, "variant": built[0].variant, "mesh": f"{built[0].model.mesh.nx}x{built[0].model.mesh.ny}",
           "members": a.members, "sweep_compile_s": round(out.compile_s, 3), "sweep_wall_s": round(out.wall_s, 3),
           "single_compile_s": round(compile_single, 3), "single_wall_s_mean": round(mean_single, 3),
           "single_wall_s_max": round(max(singles), 3), "looped_wall_s": round(sum(singles), 3),
           "sweep_over_single": round(out.wall_s / mean_single, 2),
           "sweep_over_looped": round(out.wall_s / sum(singles), 2), "max_rel_diff": f"{worst:.1e}"}
    for k, v in row.items():
        print(f"{k:>20}: {v}")
    write_rows(os.path.join(os.path.dirname(__file__), "results", f"bench_sweep_{a.scene}.csv"), [row])


if __name__ == "__main__":
    main()
