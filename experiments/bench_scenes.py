"""What each scene pays for: ``python experiments/bench_scenes.py [--repeat 20]``.

At the spec mesh of every scene (first variant, and Nine ``mu000`` against ``mu017``), times one Newton
iteration's algebra at the start of the first step: residual + Jacobian (``linearize_step``), and
the linear solve. Reports the number of unknowns, of force-driven tools (bordered unknowns), of
candidate pairs (node-tool pairs evaluated per iteration) against the sheet's boundary nodes, and
whether friction terms are traced. The flat die is also timed with its die displacement-driven in every
phase (no bordered unknown), to show the cost of the border. Writes
``experiments/results/bench_scenes.csv``.
"""

from __future__ import annotations

import argparse
import os

import jax
import jax.numpy as jnp
import numpy as np

import jaxfric as jf
from benchutil import median_time, write_rows
from jaxfric import scenes
from jaxfric.contact.rigid import Move, pair_nodes

CASES = [("flat_die", "const_force"), ("bead", None), ("nine", "mu000"), ("nine", "mu017"), ("blankholder", None)]


def _without_force_driven(model: jf.StripModel) -> jf.StripModel:
    """The same model with every tool displacement-driven (held in place) in every phase."""
    import equinox as eqx

    tools = tuple(eqx.tree_at(lambda t: t.controls, t, tuple(Move(0.0, 0.0) for _ in t.controls))
                  for t in model.tools)
    return eqx.tree_at(lambda m: m.tools, model, tools)


def measure(label, model, repeat):
    state = jf.initial_state(model)
    t = jnp.asarray(0.5 / max(1, len(model.phases[0].increments) if hasattr(model.phases[0], "increments") else 1))
    lin_fn = jax.jit(lambda m, s: jf.linearize_step(m, s, 0, t)[:2])
    solve_fn = jax.jit(lambda J, r: jf.linear_solve(J, -r))
    R, J = lin_fn(model, state)
    ms_lin = 1e3 * median_time(lin_fn, model, state, repeat=repeat)
    ms_solve = 1e3 * median_time(solve_fn, J, R, repeat=repeat)
    mesh = model.mesh
    boundary = len(set(np.concatenate([np.asarray(mesh.top), np.asarray(mesh.bottom)]).tolist()))
    row = dict(case=label, mesh=f"{mesh.nx}x{mesh.ny}", unknowns=int(R.shape[0]),
               bordered_unknowns=len(model.force_tools), tools=len(model.tools),
               frictional_tools=sum(t.frictional for t in model.tools),
               candidate_pairs=int(pair_nodes(model.tools).size), boundary_nodes=boundary,
               ms_linearize=round(ms_lin, 3), ms_solve=round(ms_solve, 3),
               ms_iteration=round(ms_lin + ms_solve, 3))
    print(", ".join(f"{k}={v}" for k, v in row.items()), flush=True)
    return row


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeat", type=int, default=20)
    a = p.parse_args(argv)
    rows = []
    for name, variant in CASES:
        scene = scenes.make(name, variant, "penalty")
        rows.append(measure(f"{name}/{scene.variant}", scene.model, a.repeat))
        if name == "flat_die":
            rows.append(measure(f"{name}/{scene.variant} die held (no border)", _without_force_driven(scene.model),
                                a.repeat))
    write_rows(os.path.join(os.path.dirname(__file__), "results", "bench_scenes.csv"), rows)


if __name__ == "__main__":
    main()
