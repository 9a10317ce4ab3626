"""What the Nine test's Newton iteration count depends on: residual tolerance and nominal increments.

    python experiments/nine_iteration_budget.py [--mesh 300x3] [--variant mu017] [--set NAME=VALUE ...]
        [--cases SPEC ...] [--out CSV]

Runs ``nine mu017`` with ``lcp_ssn`` (the ``make run`` case; ``--variant`` and ``--set`` change it as
``jaxfric run`` does) once per case, a case being
``dU,dq_clamp,rtol`` (the nominal increments of the draw and of the clamp in mm, and Newton's
relative residual tolerance; the spec's are 0.1, 0.1, 1e-8). Writes ``results/nine_iteration_budget.csv``
(steps, cutbacks, Newton iterations per phase, steady drawing force, wall and compile time) and prints
each row as it finishes. The step error of each row is estimated against a Richardson extrapolation of
the steady force to zero increment, from the spec's increments and their half (both at rtol 1e-8,
where the step error is first order: ``results`` of the same-mesh accuracy tests).
"""

from __future__ import annotations

import argparse
import csv
import os
import sys

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from jaxfric.loadpath.run import run  # noqa: E402
from jaxfric.numerics.newton import NewtonOptions  # noqa: E402
from jaxfric.scenes import make  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_CASES = ("0.1,0.1,1e-8", "0.05,0.05,1e-8", "0.1,0.1,1e-6", "0.1,0.1,1e-5", "0.1,0.1,1e-4",
                 "0.1,0.1,1e-3", "0.15,0.15,1e-5", "0.2,0.2,1e-8", "0.2,0.2,1e-5", "0.3,0.3,1e-5",
                 "0.4,0.4,1e-5", "0.4,0.4,1e-8")
FIELDS = ("dU", "dq_clamp", "rtol", "converged", "n_steps", "cutbacks", "newton_iters_total", "iters_clamp",
          "iters_draw", "iters_per_draw_step", "steady_drawing_force", "step_error_estimate", "wall_s",
          "compile_s", "message")


def one(variant: str, overrides: dict, dU: float, dq: float, rtol: float) -> dict:
    scene = make("nine", variant, "lcp_ssn", {**overrides, "dU": dU, "dq_clamp": dq})
    r = run(scene.model, newton=NewtonOptions(rtol=rtol), control=scene.control, observe=scene.observe,
            progress=False, raise_on_failure=False)
    h = r.history
    draw = h["phase_name"] == "draw"
    U = h["drawing_displacement"]
    window = draw & (U >= scene.steady_window[0]) & (U <= scene.steady_window[1])
    its = h["newton_iters"]
    return dict(dU=dU, dq_clamp=dq, rtol=rtol, converged=bool(r.converged), n_steps=len(U) - 1,
                cutbacks=int(h["cutbacks"].sum()), newton_iters_total=int(its.sum()),
                iters_clamp=int(its[h["phase_name"] == "clamp"].sum()), iters_draw=int(its[draw].sum()),
                iters_per_draw_step=round(float(its[draw].sum()) / max(int(draw.sum()), 1), 2),
                steady_drawing_force=float(np.mean(h["drawing_force"][window])) if window.any() else float("nan"),
                step_error_estimate=float("nan"), wall_s=round(r.wall_s, 2), compile_s=round(r.compile_s, 2),
                message=r.message)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default="300x3")
    ap.add_argument("--variant", default="mu017")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="config field override")
    ap.add_argument("--cases", nargs="+", default=list(DEFAULT_CASES), metavar="DU,DQ,RTOL")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "nine_iteration_budget.csv"))
    a = ap.parse_args(argv)
    overrides = {"mesh": a.mesh, **dict(item.split("=", 1) for item in a.set)}
    rows = []
    for case in a.cases:
        dU, dq, rtol = (float(v) for v in case.split(","))
        row = one(a.variant, overrides, dU, dq, rtol)
        rows.append(row)
        print({k: row[k] for k in FIELDS if k != "message"}, row["message"], flush=True)
    # Richardson (first order) from the spec's increments and their half, both at the spec's tolerance.
    by = {(r["dU"], r["dq_clamp"], r["rtol"]): r["steady_drawing_force"] for r in rows}
    if (0.1, 0.1, 1e-8) in by and (0.05, 0.05, 1e-8) in by:
        limit = 2.0 * by[(0.05, 0.05, 1e-8)] - by[(0.1, 0.1, 1e-8)]
        for r in rows:
            r["step_error_estimate"] = (r["steady_drawing_force"] - limit) / limit
        print(f"steady force extrapolated to zero increment: {limit:.4f} N/mm")
    os.makedirs(os.path.dirname(a.out), exist_ok=True)
    with open(a.out, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=FIELDS)
        w.writeheader()
        w.writerows(rows)
    print("wrote", a.out)


if __name__ == "__main__":
    sys.exit(main())
