"""Where a Nine drawing step's Newton iterations go: residual, contact statuses and plastic Gauss points
at every iterate of the exact-contact solver.

    python experiments/nine_newton_trace.py [--u0 20] [--steps 8] [--mesh 300x3]

Runs Nine mu017 (``lcp_ssn``) to U = u0 mm, then takes ``--steps`` nominal drawing steps from the
secant predictor, each twice: with :func:`jaxfric.step.solve_step` (the iteration count the runs
report) and with a host-driven copy of the loop of :func:`jaxfric.exact.exact_solve` built from the
same pieces (linearisation, semismooth direction, merit, status), which records at every evaluated
point: ||R||_inf against the tolerance, the step length (1, or 1/4 and 1/16 after a rejected trial),
how many pairs changed contact status, and how many Gauss points changed between elastic and plastic
(equivalent plastic strain grown since the step's start) since the last accepted iterate (at the first
iterate the statuses are compared with all-open, the loop's start, as the solver's own test does). The two
iteration counts are printed side by side: they must agree, or the copy no longer follows the solver.
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

from jaxfric import exact_active_set, exact_iterate  # noqa: E402
from jaxfric.contact import pair_mu  # noqa: E402
from jaxfric.model import tool_positions  # noqa: E402
from jaxfric.newton import NewtonOptions  # noqa: E402
from jaxfric.scenes import nine  # noqa: E402
from jaxfric.simulate import simulate  # noqa: E402
from jaxfric.step import StepContext, solve_step, step_args, unknowns  # noqa: E402

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

    @eqx.filter_jit
    def evaluate(x, args, p_new, frames):
        # The trial's merit takes the forces its direction predicts as hint, as the solver's does.
        it = exact_iterate.linearize_iterate(x, args)
        R, _ = exact_iterate.iterate_residual(x, it, p_new, args)
        merit = jnp.nan if frames is None else exact_active_set.semismooth_merit(x, it, args, p_new, frames)
        return it, jnp.max(jnp.abs(R)), jnp.max(jnp.abs(it.f_int)), merit

    @eqx.filter_jit
    def direction(it, args, x, hint):
        frames = exact_active_set.contact_frames(it, args)
        dx, p_new, _, stats, _ = exact_active_set.active_set_step(it, args, x, None, law, hint, frames=frames)
        return dx, p_new, stats, exact_active_set.semismooth_merit(x, it, args, hint, frames[0]), frames[0]

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
            mu_pairs = pair_mu(args.contact.tools, args.contact.mu)
            m = mu_pairs.shape[0]
            x_ref = unknowns(model, state.u, tool_positions(state))
            x = unknowns(model, *guess)
            eqps0 = state.material.eqps
            c = args.contact
            p_step = jnp.stack([jnp.concatenate(c.lam_n), jnp.concatenate(c.lam_t)], -1)
            it, r, _, _ = evaluate(x, args, jnp.zeros((m, 2)), None)
            p, status = jnp.zeros((m, 2)), jnp.zeros(m, jnp.int8)
            plastic = np.asarray(it.states.eqps > eqps0)
            U = (t_target - 1.0) * config.U_draw
            rows.append(dict(step=s, U=U, k=0, alpha="", residual=float(r), tolerance="", status_changes="",
                             gauss_point_switches="", plastic_points=int(plastic.sum()), ssn_passes="",
                             correction="", rejected="", converged=""))
            dx, p_new, stats, merit, frames = direction(it, args, x, p_step)
            alpha, k = 1.0, 0
            while k < opts.max_iterations:
                k += 1
                x_t = x + alpha * dx
                it_t, r, scale, merit_t = evaluate(x_t, args, p_new, frames)
                status_t = exact_iterate.pair_status(p_new, mu_pairs)
                plastic_t = np.asarray(it_t.states.eqps > eqps0)
                tol = opts.atol + opts.rtol * max(float(scale), 1e-6)
                correction = float(jnp.max(jnp.abs(alpha * dx)))
                changes = int(jnp.sum(status_t != status))
                dx_ok = correction <= opts.du_atol + opts.du_rtol * float(jnp.max(jnp.abs(x_t - x_ref)))
                done = float(r) <= tol and dx_ok and changes == 0 and int(stats[2]) == 0 and alpha == 1.0
                rejected = k > 1 and not (float(merit_t) <= float(merit)) and alpha > 1 / 16 and not done
                rows.append(dict(step=s, U=U, k=k, alpha=alpha, residual=float(r), tolerance=tol,
                                 status_changes=changes, gauss_point_switches=int((plastic_t != plastic).sum()),
                                 plastic_points=int(plastic_t.sum()), ssn_passes=int(stats[1]),
                                 correction=correction, rejected=rejected, converged=done))
                if done:
                    break
                if rejected:
                    alpha *= 0.25
                    continue
                x, it, p, status, plastic, alpha = x_t, it_t, p_new, status_t, plastic_t, 1.0
                dx, p_new, stats, merit, frames = direction(it, args, x, p)
            print(f"step at U = {U:.2f} mm: solve_step {int(sol.iterations)} iterations, this copy {k}; "
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
