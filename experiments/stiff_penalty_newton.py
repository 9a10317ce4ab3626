"""Newton iterates of the attempt where a stiff-penalty Nine run stops (issue 5, extreme cases).

    python experiments/stiff_penalty_newton.py [--eps-n 1e9] [--variant mu017] [--iterations 14]
    python experiments/stiff_penalty_newton.py --spec --mesh 300x3 --eps-n 1e6 --set max_steps=30000

Runs the Nine test of ``tests/test_extreme.py`` (30 x 2, B pushed 3 mm in 6 steps, drawn 1 mm in 4), or
with ``--spec`` the spec's load path (the penalty study's case with the second command), with the
penalty law at ``--eps-n`` until it stops, then repeats the failed attempt by hand from the last
converged state: Newton steps on ``jaxfric.contact.system.linearize`` with the solver's line search (the full
step, a quarter, a sixteenth, which is kept). Prints, per iteration, the step length taken, the residual
before and after (max norm, N/mm), the linear solve's own residual |J dx + R|, every pair whose status
(open 0 / stick 1 / slip 2) changed, with its gap and forces before and after, and the residual tolerance
of the convergence test.
"""

from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxfric.contact.rigid import pair_nodes  # noqa: E402
from jaxfric.contact.system import linearize  # noqa: E402
from jaxfric.loadpath.model import tool_positions  # noqa: E402
from jaxfric.loadpath.run import run  # noqa: E402
from jaxfric.loadpath.step import StepContext, step_args, unknowns  # noqa: E402
from jaxfric.numerics.linalg import linear_solve  # noqa: E402
from jaxfric.scenes import make  # noqa: E402

NINE = {"mesh": "30x2", "stroke": 3.0, "dq_clamp": 0.5, "U_draw": 1.0, "dU": 0.25}


def by_hand(model, state, t: float):
    """The step to pseudo-time ``t`` from the converged ``state``, for Newton by hand: the jitted
    linearisation (:func:`jaxfric.contact.system.linearize`), the start point and its linearisation."""
    args, _, _ = step_args(model, state, int(state.phase), t, StepContext.build(model))
    lin_at = jax.jit(lambda x: linearize(x, args))
    x = unknowns(model, state.u, tool_positions(state))
    return lin_at, x, lin_at(x)


_solve = jax.jit(linear_solve)


def searched_step(lin_at, x, lin):
    """One Newton step from ``x`` (linearised as ``lin``) with the solver's line search: the full step, a
    quarter, a sixteenth, the first that does not raise the residual's norm (the last otherwise). Returns
    (the full correction, the step length taken, the linearisation there)."""
    dx = _solve(lin.jacobian, -lin.residual)
    for alpha in (1.0, 0.25, 1.0 / 16.0):
        new = lin_at(x + alpha * dx)
        if jnp.sum(new.residual**2) <= jnp.sum(lin.residual**2):
            break
    return dx, alpha, new


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--eps-n", type=float, default=1e9)
    ap.add_argument("--variant", default="mu017")
    ap.add_argument("--iterations", type=int, default=14)
    ap.add_argument("--spec", action="store_true", help="the spec's load path instead of the short one")
    ap.add_argument("--mesh", default=None, help="NXxNY (default: 30x2, or the spec mesh with --spec)")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="another config field")
    a = ap.parse_args(argv)

    config = {} if a.spec else dict(NINE)
    config["eps_n"] = a.eps_n
    if a.mesh:
        config["mesh"] = a.mesh
    config.update(item.split("=", 1) for item in a.set)  # text values: make() converts them by field type
    scene = make("nine", a.variant, "penalty", config)
    res = run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe, progress=False,
              raise_on_failure=False)
    print(res.message)
    if res.converged:
        return
    state, t = res.simulation.final, float(res.simulation.failed_time)
    model = scene.model
    lin_at, x, lin = by_hand(model, state, t)
    opts = scene.newton
    print(f"step t {t:.9g}; residual tolerance at the start point "
          f"{opts.atol + opts.rtol * max(float(lin.scale), 1e-6):.3e} N/mm "
          f"(scale |f_int| {float(lin.scale):.4g} N/mm)")
    for k in range(a.iterations):
        dx, alpha, new = searched_step(lin_at, x, lin)
        lin_res = float(jnp.max(jnp.abs(lin.jacobian.matvec(dx) + lin.residual)))  # linear solve's own residual
        before, after = lin.aux[2], new.aux[2]
        changed = np.nonzero(np.asarray(before["status"] != after["status"]))[0]
        pairs = [f"pair {i}: {int(before['status'][i])}->{int(after['status'][i])}, gap {float(before['gap'][i]):.2e}"
                 f"->{float(after['gap'][i]):.2e} mm, R_N {float(before['rn'][i]):.3g}->{float(after['rn'][i]):.3g}"
                 for i in changed]
        worst = int(jnp.argmax(jnp.abs(new.residual)))
        print(f"{k:2d} step {alpha:.4g}: |R| {float(jnp.max(jnp.abs(lin.residual))):.3e} -> "
              f"{float(jnp.max(jnp.abs(new.residual))):.3e} N/mm (row {worst}), |dx| "
              f"{float(jnp.max(jnp.abs(alpha * dx))):.2e} mm, |J dx + R| {lin_res:.1e}, {len(changed)} status changes"
              + ("; " + "; ".join(pairs[:6]) if pairs else ""))
        x, lin = x + alpha * dx, new
    n_dofs = model.mesh.n_dofs
    if worst < n_dofs:  # where the last residual sits: a sheet node (i along, j through) or a tool row
        node = worst // 2
        i, j = divmod(node, model.mesh.ny + 1)
        X = np.asarray(model.mesh.nodes)[node]
        u = np.asarray(x[:n_dofs]).reshape(-1, 2)[node]
        candidate = node in pair_nodes(model.tools)
        print(f"last largest residual: node {node} (i = {i} of {model.mesh.nx}, j = {j} of {model.mesh.ny}), "
              f"{'xy'[worst % 2]} row, X = ({X[0]:.4f}, {X[1]:.4f}) mm, u = ({u[0]:.4f}, {u[1]:.4f}) mm, "
              f"{'a' if candidate else 'not a'} contact candidate")
    else:
        print(f"last largest residual: tool row {worst - n_dofs}")


if __name__ == "__main__":
    main()
