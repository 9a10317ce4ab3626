"""The size-dependent parts of a Nine Newton iteration against the mesh, timed in alternation.

    python experiments/bench_scaling.py [--mesh 300x3 600x3 1200x3 1200x6 2400x6] [--u0 0.5] [--rounds 5]
                                        [--out CSV]

``bench_iteration.py`` times each mesh in a process of its own, one mesh after the other; on a machine
whose speed drifts by a fifth or more within an hour that makes the meshes' ratios uncertain. Here every
mesh is run in one process to U = u0 mm (Nine mu017, ``lcp_ssn``, the scene's defaults, every pair
evaluated), and the parts whose cost grows with the mesh are then timed at each mesh's state in rounds, the
meshes alternated within each round: the element forces and consistent tangents, assembled
(``elements``), the pairs' projections and their derivatives (``pairs``) and one block-Thomas solve of the
assembled tangent (``solve``). Each round takes the median of ``--calls`` calls per part and mesh (process
CPU time); the CSV holds the median over the rounds and the rounds' spread (largest over smallest).
Pin it to one core with one XLA thread (``XLA_FLAGS=--xla_cpu_multi_thread_eigen=false
intra_op_parallelism_threads=1 taskset -c 0 ...``). Writes ``results/bench_scaling.csv``.
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

from bench_iteration import size_parts  # noqa: E402
from benchutil import median_time, write_rows  # noqa: E402
from jaxfric import scenes  # noqa: E402
from jaxfric.loadpath.model import tool_positions  # noqa: E402
from jaxfric.loadpath.simulate import simulate  # noqa: E402
from jaxfric.loadpath.step import StepContext, step_args  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))


def parts_of(mesh: str, u0: float) -> tuple[dict, dict]:
    """The mesh's size and its parts ``{name: (compiled function, args)}`` at its state at U = u0."""
    sc = scenes.make("nine", "mu017", "lcp_ssn", {"mesh": mesh, "U_draw": u0, "preselect": False})
    model = sc.model
    sim = eqx.filter_jit(lambda m: simulate(m, control=sc.control))(model)
    if int(sim.code) != 0:
        raise RuntimeError(f"{mesh}: the run to U = {u0} mm did not converge (code {int(sim.code)})")
    state = sim.final
    args, _, _ = step_args(model, state, 1, state.time, StepContext.build(model))
    parts, K = size_parts(args, state.u, tool_positions(state))
    size = {"mesh": mesh, "elements": int(model.mesh.n_elements), "dofs": int(model.mesh.n_dofs),
            "blocks": int(K.diag.shape[0]), "block_size": int(K.diag.shape[1]),
            "pairs": int(sum(len(t.candidates) for t in model.tools)),
            "plastic_points": int(jnp.sum(state.material.eqps > 0))}
    return size, parts


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", nargs="+", default=["300x3", "600x3", "1200x3", "1200x6", "2400x6"])
    ap.add_argument("--u0", type=float, default=0.5, help="drawing displacement of the timed state (mm)")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--calls", type=int, default=7, help="calls per part, mesh and round (their median)")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "bench_scaling.csv"))
    a = ap.parse_args(argv)

    meshes = {}
    for mesh in a.mesh:
        meshes[mesh] = parts_of(mesh, a.u0)
        print(f"{mesh}: state at U = {a.u0} mm, {meshes[mesh][0]}", flush=True)
    times: dict = {(m, p): [] for m in meshes for p in meshes[m][1]}
    for r in range(a.rounds):
        for mesh, (_, parts) in meshes.items():
            for name, (fn, *args) in parts.items():
                times[mesh, name].append(1e3 * median_time(fn, *args, repeat=a.calls, clock=time.process_time))
        print(f"round {r + 1} of {a.rounds}", flush=True)

    rows = []
    for mesh, (size, parts) in meshes.items():
        for name in parts:
            t = np.asarray(times[mesh, name])
            per = {"elements": size["elements"], "pairs": size["pairs"], "solve": size["blocks"]}[name]
            rows.append({**size, "part": name, "ms": round(float(np.median(t)), 3),
                         "per_1000": round(1e3 * float(np.median(t)) / per, 4),
                         "per": {"elements": "element", "pairs": "pair", "solve": "block"}[name],
                         "spread": round(float(t.max() / t.min()), 3), "rounds": a.rounds})
            print(f"{mesh:>7s} {name:>9s} {rows[-1]['ms']:9.3f} ms  {rows[-1]['per_1000']:8.4f} ms per 1000 "
                  f"{rows[-1]['per']}s  (rounds' spread {rows[-1]['spread']})")
    write_rows(a.out, rows)


if __name__ == "__main__":
    main()
