"""Where one Newton iteration of the Nine's exact-contact run goes: its parts timed one by one.

    python experiments/bench_iteration.py [--u0 20] [--mesh 300x3 ...] [--variant mu017] [--steps 6]
                                          [--set KEY=VALUE ...] [--out CSV]

With several meshes (``--mesh 300x3 600x3 --u0 2``) the rows of each, with its elements, unknowns and
candidate pairs: the cost per iteration against the problem's size (``results/bench_iteration_scaling.csv``
holds one process per mesh: more than three meshes in one process ran LLVM out of memory; and
``bench_scaling.py`` times the size-dependent parts of every mesh in alternation, in one process).

Runs the Nine (``lcp_ssn``, the scene's defaults) to U = u0 mm, then times, at the state of a drawing
step's converged solution (the program pieces compiled apart, each called on the flat list of its arguments'
arrays, :func:`benchutil.on_leaves`, so that the time is the computation's and not the dispatch of the
step's modules; median process CPU time of 15 calls):

- ``elements``: the element forces and consistent tangents, assembled (block-tridiagonal);
- ``elements_force``: the element forces alone (what a line search's trial needs);
- ``pairs``: the pairs' projections and their derivatives (``evaluated_pairs`` of the ``pairs``
  candidates: those the step's pre-selection keeps, :mod:`jaxfric.contact.preselection`);
- ``evaluate``: one point of the Newton loop (elements, pairs, residual, the line search's merit);
- ``direction``: one direction of the semismooth Newton (the frames, the active-set passes, each a
  block-Thomas solve, and the merit at its start), taken at the converged point with its own forces as
  the hint, and ``direction_per_pass``: that time over its active-set passes (``passes``);
- ``frames``, ``merit``: the candidates' frames and the line search's merit, parts of the direction;
- ``solve``: one block-Thomas solve of the bare tangent;
- ``step``: a whole nominal drawing step (solve_step) over its Newton iterations, for ``--steps`` steps
  from the secant predictor (``per_iteration``: the step's time over its iterations; ``passes``: the
  active-set passes per Newton iteration of these steps; ``dU``: the timed increment, the nominal one, or
  half of it, up to three times, where a timed step does not converge at the nominal one).

The columns are milliseconds; ``share`` is the part's time over the whole step's time per iteration.
One XLA thread is assumed (``XLA_FLAGS=--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1``,
pinned with ``taskset``): the parts are then timed as they run inside the step.
Writes ``results/bench_iteration.csv``.
"""

from __future__ import annotations

import argparse
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from benchutil import median_time, on_leaves, write_rows  # noqa: E402
from jaxfric import scenes  # noqa: E402
from jaxfric.contact.exact import ExactContactProblem  # noqa: E402
from jaxfric.contact.exact_active_set import contact_frames, semismooth_merit  # noqa: E402
from jaxfric.contact.exact_iterate import _geometry  # noqa: E402
from jaxfric.fem.assembly import internal_force, internal_force_and_tangent  # noqa: E402
from jaxfric.loadpath.model import tool_positions  # noqa: E402
from jaxfric.loadpath.simulate import simulate  # noqa: E402
from jaxfric.loadpath.step import StepContext, solve_step, step_args, unknowns  # noqa: E402
from jaxfric.numerics.linalg import block_tridiag_solve  # noqa: E402
from jaxfric.numerics.newton import NewtonOptions, newton_pass, newton_start  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--u0", type=float, default=20.0, help="drawing displacement to start from (mm)")
    ap.add_argument("--mesh", nargs="+", default=["300x3"])
    ap.add_argument("--variant", default="mu017")
    ap.add_argument("--steps", type=int, default=6, help="drawing steps timed whole")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--label", default="", help="written in the CSV's first column")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "bench_iteration.csv"))
    a = ap.parse_args(argv)
    extra = {}
    for text in a.overrides:
        field, _, value = text.partition("=")
        extra[field] = scenes.parse_override("nine", field, value)
    rows = []
    for mesh in a.mesh:
        try:
            rows += bench(a.variant, {"mesh": mesh, **extra}, a.u0, a.steps, a.label)
        except RuntimeError as err:   # a mesh whose timed steps do not converge: said, and the others kept
            print(f"{mesh}: {err}", flush=True)
            continue
        write_rows(a.out, rows)   # after every mesh: a long scaling run keeps what it measured
    if not rows:
        raise SystemExit("no mesh was measured")


#: halvings of the timed increment where a timed step does not converge at the nominal one
HALVINGS = 3


def size_parts(args, u, q, K=None) -> tuple[dict, object]:
    """The parts whose cost grows with the mesh, as ``{name: (compiled function, its arguments)}``
    (:func:`benchutil.on_leaves`), at the step arguments ``args``, displacements ``u`` and tool positions
    ``q``: the element forces and tangents, assembled (``elements``), the pairs' projections and derivatives
    (``pairs``) and one block-Thomas solve of ``K`` (``solve``; default: the assembled tangent); and ``K``."""
    def elements(ar, u):
        return internal_force_and_tangent(ar.mesh, ar.material, ar.formulation, ar.geo, u, ar.states)

    element_part = on_leaves(elements, args, u)
    if K is None:
        compiled, leaves = element_part
        K = compiled(leaves).tangent
    return {"elements": element_part,
            "pairs": on_leaves(lambda ar, u, q: _geometry(ar.contact, ar.mesh.nodes, u, q), args, u, q),
            "solve": on_leaves(block_tridiag_solve, K, jnp.ones(K.diag.shape[0] * K.diag.shape[1]))}, K


def bench(variant: str, overrides: dict, u0: float, steps: int, label: str = "") -> list[dict]:
    """The rows of one mesh (module docstring)."""
    scene = scenes.make("nine", variant, "lcp_ssn", overrides)
    config, model = scene.config, scene.model
    short = scenes.make("nine", variant, "lcp_ssn", {**overrides, "U_draw": u0})
    sim = eqx.filter_jit(lambda m: simulate(m, control=short.control))(short.model)
    if int(sim.code) != 0:
        raise RuntimeError(f"the run to U = {u0} mm did not converge (code {int(sim.code)})")
    ctx, opts = StepContext.build(model), NewtonOptions()
    dt = config.dU / config.U_draw
    state = eqx.tree_at(lambda s: s.time, sim.final, jnp.asarray(1.0 + u0 / config.U_draw))

    # Whole steps from the secant predictor, at the nominal increment; where a step does not converge at
    # it (Newton's iteration limit on a fine mesh), the timed sequence starts again from the same state
    # at half the increment, as the step controller would cut it, at most HALVINGS times.
    step = eqx.filter_jit(lambda st, t, g: solve_step(model, st, 1, t, opts, ctx, guess=g))
    start = state
    for halving in range(HALVINGS + 1):
        state, prev, iters, step_ms, passes = start, None, [], [], []
        for s in range(steps + 2):
            t_target = float(state.time) + dt
            guess = (state.u, state.contact.q) if prev is None else \
                (2 * state.u - prev.u, 2 * state.contact.q - prev.contact.q)
            jax.block_until_ready(step(state, t_target, guess))   # compiled on the first call
            t0 = time.process_time()
            sol, new = jax.block_until_ready(step(state, t_target, guess))
            if int(sol.code) != 0:
                break
            if s >= 2:   # the first two steps: compilation and the predictor's start
                step_ms.append(1e3 * (time.process_time() - t0))
                iters.append(int(sol.iterations))
                passes.append(int(sol.stats[1]))
            prev, state = state, new
        else:
            break
        if halving == HALVINGS:
            raise RuntimeError(f"the timed step {s} did not converge (code {int(sol.code)}) at {dt * config.U_draw:g} "
                               f"mm; try another --u0")
        dt = 0.5 * dt
    per_iteration = float(np.sum(step_ms) / np.sum(iters))

    # The parts, at the last step's converged solution, as data of the step that follows it.
    t_target = float(state.time) + dt
    args, _, _ = step_args(model, state, 1, t_target, ctx)
    x = unknowns(model, state.u, tool_positions(state))
    problem = ExactContactProblem(model.contact, opts)
    c0 = newton_start(problem, x, args, opts)
    c1 = eqx.filter_jit(lambda c, ar: newton_pass(c, ar, x, problem, opts))(c0, args)   # evaluated x
    u = state.u
    sized, _ = size_parts(args, u, tool_positions(state), c1.point.state.it.K)
    point = c1.point
    parts = {
        "elements": sized["elements"],
        "elements_force": on_leaves(lambda ar, u: internal_force(ar.mesh, ar.material, ar.formulation, ar.geo, u,
                                                                 ar.states), args, u),
        "pairs": sized["pairs"],
        "evaluate": on_leaves(lambda ar, x, trial: problem.evaluate(x, trial, ar), args, x, c1.trial),
        "direction": on_leaves(lambda ar, x, pt: problem.direction(x, pt, ar, jnp.array(False)), args, x, point),
        "frames": on_leaves(lambda ar, pt: contact_frames(pt.state.it, ar), args, point),
        "merit": on_leaves(lambda ar, x, pt: semismooth_merit(x, pt.state.it, ar, pt.state.p,
                                                              contact_frames(pt.state.it, ar)[0]), args, x, point),
        "solve": sized["solve"],
    }

    n_passes = int(eqx.filter_jit(lambda ar: problem.direction(x, c1.point, ar, jnp.array(False)).stats[1])(args))
    m = int(sum(len(t.candidates) for t in model.tools))
    evaluated = int(sum(t.capacity or len(t.candidates) for t in model.tools))   # jaxfric.contact.preselection
    size = {"mesh": f"{model.mesh.nx}x{model.mesh.ny}", "elements": int(model.mesh.n_elements),
            "dofs": int(model.mesh.n_dofs), "pairs": m, "evaluated_pairs": evaluated,
            "dU": round(dt * config.U_draw, 6)}
    rows = [{"label": label, **size, "part": "step", "ms": round(float(np.mean(step_ms)), 3),
             "per_iteration": round(per_iteration, 3), "share": 1.0,
             "iterations": round(float(np.mean(iters)), 2), "passes": round(np.sum(passes) / np.sum(iters), 2)}]
    for name, (fn, *fn_args) in parts.items():
        ms = 1e3 * median_time(fn, *fn_args, repeat=15, clock=time.process_time)
        rows.append({"label": label, **size, "part": name, "ms": round(ms, 3), "per_iteration": "",
                     "share": round(ms / per_iteration, 3), "iterations": "",
                     "passes": n_passes if name == "direction" else ""})
        if name == "direction":
            rows.append({"label": label, **size, "part": "direction_per_pass", "ms": round(ms / n_passes, 3),
                         "per_iteration": "", "share": round(ms / n_passes / per_iteration, 3), "iterations": "",
                         "passes": ""})
    print(f"Nine {variant} {size['mesh']} at U = {float(state.time - 1.0) * config.U_draw:.1f} mm, {m} candidate "
          f"pairs ({evaluated} evaluated per iteration), {len(iters)} steps of {dt * config.U_draw:g} mm, "
          f"{np.mean(iters):.2f} Newton iterations and "
          f"{np.sum(passes) / np.sum(iters):.2f} active-set passes per iteration, {per_iteration:.2f} ms per iteration")
    for r in rows:
        print(f"  {r['part']:>15}: {r['ms']:9.3f} ms  ({r['share']:.2f} of an iteration)")
    return rows


if __name__ == "__main__":
    main()
