"""Where a Nine drawing step's Newton iterations go: residual, contact statuses and plastic Gauss points
at every iterate of the exact-contact solver.

    python experiments/nine_newton_trace.py [--u0 20] [--steps 8] [--mesh 300x3]

Runs Nine mu017 (``lcp_ssn``) to U = u0 mm, then takes ``--steps`` nominal drawing steps from the
secant predictor, each twice: with :func:`jaxfric.loadpath.step.solve_step` (the iteration count the runs
report) and pass by pass from the host through the same Newton loop (:func:`jaxfric.numerics.newton.newton_pass`
with :class:`jaxfric.contact.exact.ExactContactProblem`), recording at every evaluated point: ||R||_inf against
the tolerance, the step length (1, or 1/4 and 1/16 after a rejected trial), how many pairs changed
contact status, and how many Gauss points changed between elastic and plastic (equivalent plastic
strain grown since the step's start) since the last accepted iterate. The two iteration counts are
printed side by side: they must agree.
Writes ``results/nine_newton_trace.csv`` (one row per evaluated point).
"""

from __future__ import annotations

import argparse
import csv
import os

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxfric.contact.exact import ExactContactProblem  # noqa: E402
from jaxfric.loadpath.model import tool_positions  # noqa: E402
from jaxfric.loadpath.simulate import simulate  # noqa: E402
from jaxfric.loadpath.step import StepContext, solve_step, step_args, unknowns  # noqa: E402
from jaxfric.numerics.newton import NewtonOptions, newton_pass, newton_start  # noqa: E402
from jaxfric.numerics.results import Result  # noqa: E402
from jaxfric.scenes import nine  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
FIELDS = ("step", "U", "k", "alpha", "residual", "tolerance", "status_changes", "gauss_point_switches",
          "plastic_points", "ssn_passes", "correction", "rejected", "converged")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--u0", type=float, default=20.0, help="drawing displacement to start from (mm)")
    ap.add_argument("--steps", type=int, default=8)
    ap.add_argument("--mesh", default="300x3")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "nine_newton_trace.csv"))
    a = ap.parse_args(argv)
    nx, ny = (int(v) for v in a.mesh.lower().split("x"))

    config = nine.NineConfig(nx=nx, ny=ny)
    short = nine.build(nine.NineConfig(nx=nx, ny=ny, U_draw=a.u0), "lcp_ssn", "mu017")
    sim = eqx.filter_jit(lambda m: simulate(m, control=short.control))(short.model)
    if int(sim.code) != 0:
        raise SystemExit(f"the run to U = {a.u0} mm did not converge (code {int(sim.code)})")
    model = nine.build(config, "lcp_ssn", "mu017").model
    ctx, law, opts = StepContext.build(model), model.contact, NewtonOptions()
    dt = config.dU / config.U_draw
    # The short run ends at pseudo-time 2 = its U_draw; in the full run that state sits at u0 / U_draw.
    state = eqx.tree_at(lambda s: s.time, sim.final, jnp.asarray(1.0 + a.u0 / config.U_draw))

    problem = ExactContactProblem(law, opts)
    start = eqx.filter_jit(lambda x0, args: newton_start(problem, x0, args, opts))
    one_pass = eqx.filter_jit(lambda c, args, x_ref: newton_pass(c, args, x_ref, problem, opts))
    evaluate = eqx.filter_jit(problem.evaluate)

    step = eqx.filter_jit(lambda st, t, g: solve_step(model, st, 1, t, opts, ctx, guess=g))
    rows, prev = [], None
    # One untraced nominal step first, so that every traced step starts from the secant predictor.
    for s in range(a.steps + 1):
        t_target = float(state.time) + dt
        guess = (state.u, state.contact.q) if prev is None else \
            (2 * state.u - prev.u, 2 * state.contact.q - prev.contact.q)
        sol, new = step(state, t_target, guess)
        if int(sol.code) != 0:
            raise SystemExit(f"step {s} did not converge (code {int(sol.code)})")
        if prev is not None:
            args, _, _ = step_args(model, state, 1, t_target, ctx)
            x_ref = unknowns(model, state.u, tool_positions(state))
            eqps0 = state.material.eqps
            U = (t_target - 1.0) * config.U_draw
            # The solver's own loop, one pass at a time: each pass evaluates the pending point (the
            # initial guess first) and decides on it; the point is evaluated once more here to read it.
            c = start(unknowns(model, *guess), args)
            plastic = np.zeros(eqps0.shape, bool)
            while int(c.code) == Result.CONTINUE:
                before, c = c, one_pass(c, args, x_ref)
                k = int(before.k)
                point = evaluate(before.x_t, before.trial, args)
                plastic_t = np.asarray(point.state.it.states.eqps > eqps0)
                tol = opts.atol + opts.rtol * max(float(point.scale), 1e-6)
                rejected = k > 0 and int(c.n_acc) == int(before.n_acc)
                rows.append(dict(
                    step=s, U=U, k=k, alpha=float(before.trial.alpha) if k else "", residual=float(c.r_hist[k]),
                    tolerance=tol,
                    status_changes=int(jnp.sum(point.state.status != before.point.state.status)) if k else "",
                    gauss_point_switches=int((plastic_t != plastic).sum()) if k else "",
                    plastic_points=int(plastic_t.sum()), ssn_passes=int(before.trial.stats[1]) if k else "",
                    correction=float(jnp.max(jnp.abs(before.trial.alpha * before.trial.dx))) if k else "",
                    rejected=rejected, converged=int(c.code) == Result.SUCCESS))
                if not rejected:
                    plastic = plastic_t
            print(f"step at U = {U:.2f} mm: solve_step {int(sol.iterations)} iterations, this loop {int(c.k) - 1}; "
                  + " ".join(f"{row['residual']:.2g}" for row in rows if row["step"] == s), flush=True)
        prev, state = state, new

    os.makedirs(os.path.dirname(a.out), exist_ok=True)
    with open(a.out, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=FIELDS)
        w.writeheader()
        w.writerows(rows)
    traced = [r for r in rows if r["k"] != 0]
    for k in range(1, 7):
        at = [r for r in traced if r["k"] == k]
        if at:
            print(f"k = {k}: {len(at)} steps, median residual {np.median([r['residual'] for r in at]):.2g} N/mm, "
                  f"median Gauss-point switches {np.median([r['gauss_point_switches'] for r in at]):.0f}, "
                  f"median status changes {np.median([r['status_changes'] for r in at]):.0f}")
    print("wrote", a.out)


if __name__ == "__main__":
    main()
