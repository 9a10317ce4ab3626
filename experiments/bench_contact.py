"""Contact performance: ``python experiments/bench_contact.py [--stroke 3] [--draw 3]``.

A 300 x 3 strip (the Nine test's strip, material and cylinders A, B, C of benchmark Table 3) in
contact with three cylinders: B is pushed down by ``stroke`` mm, then the strip is drawn ``draw`` mm,
with mu = 0.17 and eps_n = 1e5, eps_t = mu eps_n. For each contact algorithm available, prints and
writes to ``experiments/results/bench_contact.csv``: steps, Newton iterations per step, augmentations
per step (AL), semismooth Newton iterations and Lemke pivots per step (exact contact), wall time per
Newton iteration of the whole run, and one Newton iteration (residual, tangent, linear solve;
contact included) at the converged final state against the same strip's iteration without tools
(``--band`` nodes in the condensed exact contact problem, default 96, 0 for all 602 candidate nodes).
"""

from __future__ import annotations

import argparse
import os

import jax
import jax.numpy as jnp
import numpy as np

import jaxfric as jf
from benchutil import median_time, write_rows
from jaxfric.contact import exact_active_set, exact_condensed, exact_iterate
from jaxfric.contact.formulations import AugmentedLagrangian, Complementarity, Penalty
from jaxfric.contact.rigid import Move, RigidTool
from jaxfric.contact.tools import Tool
from jaxfric.loadpath.step import StepContext, step_args, unknowns
from jaxfric.numerics.linalg import linear_solve

R1, PITCH, E_SHEET = 5.5, 11.97, 0.97


def three_cylinders(law, stroke=3.0, draw=3.0, nx=300, ny=3, mu=0.17) -> jf.StripModel:
    mesh = jf.strip_mesh(-50.0, 50.0, 0.0, E_SHEET, nx, ny)
    mat = jf.J2Material(E=200000.0, nu=0.3, sigma_y=171.0, A=121.74485, n=0.23)
    below = dict(drive=(0.0, 1.0), candidates=mesh.bottom, controls=(Move(), Move()), mu=mu)
    tools = (RigidTool("A", Tool.circle((0.0, -R1), R1), **below),
             RigidTool("B", Tool.circle((PITCH, E_SHEET + R1), R1, seam=np.pi / 2), drive=(0.0, -1.0),
                       candidates=mesh.top, controls=(Move(0.0, stroke), Move()), mu=mu),
             RigidTool("C", Tool.circle((2 * PITCH, -R1), R1), **below))
    hold = jf.DirichletBC(mesh.right)
    pull = jf.DirichletBC(mesh.right, motion=jf.Ramp((0.0, 0.0), (draw, 0.0)))
    phases = (jf.Phase("clamp", [hold], n_steps=int(round(stroke / 0.1))),
              jf.Phase("draw", [pull], n_steps=int(round(draw / 0.1))))
    return jf.StripModel(mesh, mat, phases, tools=tools, contact=law)


def iteration_ms(model: jf.StripModel, state, repeat: int) -> float:
    """One Newton iteration at the converged ``state`` (zero increment): residual, tangent and linear
    solve, contact included; with exact contact, its whole iteration (for "ssn" the bulk
    linearisation with the pairs' geometry and its derivatives, one active-set pass and the line
    search's merit; for the condensed solvers the band's condensation and the contact problem)."""
    if isinstance(model.contact, Complementarity):
        def iteration(m, s):
            args, _, _ = step_args(m, s, s.phase, s.time, StepContext.build(m))
            x = unknowns(m, s.u, s.contact.q)
            p = jnp.stack([s.contact.rn, s.contact.rt], -1)
            it = exact_iterate.linearize_iterate(x, args)
            if m.contact.solver != "ssn":
                return exact_condensed.contact_newton_step(it, args, x, p, m.contact, p)[:2]
            # The in-loop solver's iteration also evaluates its line search's merit function.
            merit = exact_active_set.semismooth_merit(x, it, args, p, exact_active_set.contact_frames(it, args)[0])
            return exact_active_set.active_set_step(it, args, x, p, m.contact, p)[:2], merit
    else:
        def iteration(m, s):
            lin = jf.linearize_step(m, s, s.phase, s.time)
            return linear_solve(lin.jacobian, -lin.residual)
    return 1e3 * median_time(jax.jit(iteration), model, state, repeat=repeat)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stroke", type=float, default=3.0)
    parser.add_argument("--draw", type=float, default=3.0)
    parser.add_argument("--repeat", type=int, default=20)
    parser.add_argument("--band", type=int, default=96, help="exact contact: nodes in the LCP (0: all)")
    parser.add_argument("--only", default="", help="comma-separated algorithms (default: all four)")
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "bench_contact.csv"))
    args = parser.parse_args()
    laws = {"penalty": Penalty(1e5, 0.17e5), "auglag": AugmentedLagrangian(1e5, 0.17e5, target_gap=1e-5),
            "lcp_ssn": Complementarity("ssn", args.band or None),
            "lcp_lemke": Complementarity("lemke", args.band or None, search=False)}  # the CSV's: full Newton steps
    if args.only:
        laws = {k: v for k, v in laws.items() if k in args.only.split(",")}
    rows = []
    for name, law in laws.items():
        model = three_cylinders(law, args.stroke, args.draw)
        res = jf.run(model, progress=False, raise_on_failure=False)
        h = res.history
        n_steps, iters = len(h["time"]) - 1, int(h["newton_iters"].sum())
        state = jax.tree_util.tree_map(jnp.asarray, res.final)
        with_c = iteration_ms(model, state, args.repeat)
        bare = jf.StripModel(model.mesh, model.material, model.phases)  # the same strip, no tools
        without = iteration_ms(bare, jf.SimState(state.u, state.material, state.f_int, state.time,
                                                     state.phase), args.repeat)
        row = dict(algorithm=name, band=getattr(law, "band", None), converged=res.converged, n_steps=n_steps,
                   newton_iters=iters,
                   iters_per_step=iters / n_steps, augmentations_per_step=h["augmentations"].sum() / n_steps,
                   ssn_iters_per_step=h.get("ssn_iters", np.zeros(1)).sum() / n_steps,
                   lemke_pivots_per_step=h.get("lcp_pivots", np.zeros(1)).sum() / n_steps,
                   ssn_fallbacks=int(h.get("ssn_fallbacks", np.zeros(1)).sum()), cutbacks=int(h["cutbacks"].sum()),
                   compile_s=res.compile_s, wall_s=res.wall_s, ms_per_iteration_run=1e3 * res.wall_s / iters,
                   ms_iteration_contact=with_c, ms_iteration_no_contact=without,
                   contact_overhead=with_c / without - 1.0, max_penetration=float(h["max_penetration"].max()),
                   n_active_final=int(h["n_active"][-1]))
        rows.append(row)
        print(f"{name:>8}: {n_steps} steps, {row['iters_per_step']:.2f} it/step, "
              f"{row['augmentations_per_step']:.2f} aug/step, {row['ssn_iters_per_step']:.1f} ssn it/step, "
              f"{row['lemke_pivots_per_step']:.0f} pivots/step, {row['cutbacks']} cutbacks, run {res.wall_s:.2f} s = "
              f"{row['ms_per_iteration_run']:.2f} ms/iteration (compile {res.compile_s:.1f} s); "
              f"one iteration at the end {with_c:.2f} ms with contact vs {without:.2f} ms without "
              f"(+{100 * row['contact_overhead']:.0f} %), max penetration {row['max_penetration']:.2e} mm",
              flush=True)
    write_rows(args.out, rows)


if __name__ == "__main__":
    main()
