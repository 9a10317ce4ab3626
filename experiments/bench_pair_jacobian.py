"""The pairs' derivatives: the library's closed form (:meth:`jaxfric.contact.pair_batches.PairTool.jacobian`)
against forward mode through the projection, as the code computed them before, in one process.

    python experiments/bench_pair_jacobian.py [--u0 2] [--rounds 5]

Runs the Nine ``mu017`` (300 x 3, ``lcp_ssn``) to U = u0 mm, then times at that state, every candidate pair
evaluated (``preselect`` off), the variants alternated within each round:

- ``exact_closed`` / ``exact_forward``: exact contact's pair geometry with its derivatives d(n, g_N, slip) /
  d(u, q) (:func:`jaxfric.contact.exact_iterate._geometry`), in closed form / by ``jax.jacfwd`` of the
  projection; ``exact_values``: the same without derivatives;
- ``penalty_closed`` / ``penalty_forward``: the penalty law's pair forces and their Jacobians
  (:func:`jaxfric.contact.rigid.evaluate_pairs`, the scene's penalty), by the chain rule of the closed
  form and the law's derivatives / by ``jax.jacfwd`` through the whole pair.

Each variant is one ``jax.jit`` called on the flat list of its arguments' arrays (``benchutil.on_leaves``),
timed by process CPU time (pin it: ``taskset -c N``, one XLA thread), median of 15 calls per
round; the columns are the median over the rounds, the program's StableHLO operations, and the largest
difference of the derivatives from the forward-mode ones, relative to their largest entry. Writes
``results/bench_pair_jacobian.csv``.
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
from jaxfric.contact import exact_iterate, rigid  # noqa: E402
from jaxfric.loadpath.model import tool_positions  # noqa: E402
from jaxfric.loadpath.simulate import simulate  # noqa: E402
from jaxfric.loadpath.step import StepContext, step_args  # noqa: E402

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "bench_pair_jacobian.csv")


def forward_geometry_jacobian(tool, pr_args):
    """The pair derivatives as ``jax.jacfwd`` of the projection (the code before the closed form)."""
    X, u_a, u_ref, q_k, q_ref = pr_args

    def local(z):
        pr = tool.projection(X, z[:2], u_ref, z[2], q_ref)
        return jnp.concatenate([pr.normal, pr.gap[None], pr.zeta_increment[None]]), pr

    return jax.jacfwd(local, has_aux=True)(jnp.concatenate([u_a, q_k[None]]))


def forward_pair_and_jacobian(tool, law, X, u, q, mu, lam_n, lam_t, u_ref, q_ref, length, speed):
    """The pair force's Jacobian as ``jax.jacfwd`` through the whole pair (the code before the chain rule)."""
    def one(u_a, q_k):
        f, aux = rigid._pair(tool, law, X, u_a, q_k, mu, lam_n, lam_t, u_ref, q_ref, length, speed)
        return f, (f, aux)

    (dfdx, dfdq), out = jax.jacfwd(one, argnums=(0, 1), has_aux=True)(u, q)
    return out, jnp.concatenate([dfdx, dfdq[:, None]], axis=1)


def variants(model, state, u0_time, penalty_model) -> dict:
    """``{name: (compiled, its arguments' arrays)}`` (:func:`benchutil.on_leaves`: the step's data are
    arguments, not constants XLA could fold) at the state ``state``."""
    ctx = StepContext.build(model)
    args, _, _ = step_args(model, state, 1, u0_time, ctx)
    nodes, q, u = model.mesh.nodes, tool_positions(state), state.u
    p_args, _, _ = step_args(penalty_model, state, 1, u0_time, StepContext.build(penalty_model))

    def exact(derivatives):   # (derivatives, gaps): the gaps keep the projection in the values-only program
        def fn(step, nodes, u, q):
            g = exact_iterate._geometry(step, nodes, u, q, derivatives)
            return g[-1], g[0]
        return fn

    def penalty(step, nodes, u, q):
        return [(p.df_dx, p.df_dq) for p in rigid.evaluate_pairs(step, nodes, u, q, jacobian=True)]

    def penalty_forward(step, nodes, u, q):
        """:func:`penalty` traced with the pair force Jacobian by forward mode in place of the chain rule."""
        library = rigid._pair_and_jacobian
        rigid._pair_and_jacobian = forward_pair_and_jacobian
        try:
            return penalty(step, nodes, u, q)
        finally:
            rigid._pair_and_jacobian = library

    exact_args, penalty_args = (args.contact, nodes, u, q), (p_args.contact, nodes, u, q)
    return {"exact_closed": on_leaves(exact(True), *exact_args),
            "exact_forward": on_leaves(_forward_exact, *exact_args),
            "exact_values": on_leaves(exact(False), *exact_args),
            "penalty_closed": on_leaves(penalty, *penalty_args),
            "penalty_forward": on_leaves(penalty_forward, *penalty_args)}


def _forward_exact(step, nodes, u, q):
    """Exact contact's geometry with the derivatives by ``jax.jacfwd`` of the projection."""
    def pair_fn(tool, tool_values, pair_values):
        q_k, q_ref = tool_values
        X, u_a, u_ref = pair_values
        return forward_geometry_jacobian(tool, (X, u_a, u_ref, q_k, q_ref))

    def pair_args(k):
        idx = np.asarray(step.tools[k].candidates)
        return nodes[idx], u[idx], step.u_ref[k]

    out = exact_iterate.map_pairs(step.tools, pair_fn, lambda k: (q[k], step.q_ref[k]), pair_args, friction=False)
    return jnp.concatenate([J for J, _ in out]), jnp.concatenate([pr.gap for _, pr in out])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--u0", type=float, default=2.0, help="drawing displacement of the timed state (mm)")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--out", default=OUT)
    a = ap.parse_args(argv)
    short = scenes.make("nine", "mu017", "lcp_ssn", {"U_draw": a.u0, "preselect": False})
    sim = eqx.filter_jit(lambda m: simulate(m, control=short.control))(short.model)
    scene = scenes.make("nine", "mu017", "lcp_ssn", {"preselect": False})
    penalty = scenes.make("nine", "mu017", "penalty", {"preselect": False})
    u0_time = 1.0 + a.u0 / scene.config.U_draw
    state = eqx.tree_at(lambda s: s.time, sim.final, jnp.asarray(u0_time))
    fns = variants(scene.model, state, u0_time + scene.config.dU / scene.config.U_draw, penalty.model)
    values = {name: jax.block_until_ready(fn(leaves)) for name, (fn, leaves) in fns.items()}
    ops = {name: fn.lower(leaves).as_text().count("stablehlo.") for name, (fn, leaves) in fns.items()}

    def agreement(name):
        ref = {"exact_closed": "exact_forward", "penalty_closed": "penalty_forward"}.get(name)
        if ref is None:
            return ""
        pick = (lambda v: v[0]) if name.startswith("exact") else (lambda v: v)   # the derivatives
        a_, b_ = (np.concatenate([np.ravel(x) for x in jax.tree_util.tree_leaves(pick(values[k]))])
                  for k in (name, ref))
        return f"{np.max(np.abs(a_ - b_)) / np.max(np.abs(b_)):.1e}"

    times: dict = {name: [] for name in fns}
    for _ in range(a.rounds):
        for name, (fn, leaves) in fns.items():
            times[name].append(1e3 * median_time(fn, leaves, repeat=15, clock=time.process_time))
    rows = []
    for name in fns:
        rows.append({"variant": name, "ms": round(float(np.median(times[name])), 3),
                     "rounds_ms": " ".join(f"{t:.3f}" for t in times[name]), "ops": ops[name],
                     "difference": agreement(name)})
        print(f"{name:>16}: {rows[-1]['ms']:7.3f} ms (rounds {rows[-1]['rounds_ms']}), {ops[name]} ops"
              + (f", derivatives equal to {rows[-1]['difference']}" if rows[-1]["difference"] else ""))
    write_rows(a.out, rows)


if __name__ == "__main__":
    main()
