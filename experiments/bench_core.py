"""Core performance benchmark: ``python experiments/bench_core.py [--meshes 300x3,1200x6] [--repeat 20]``.

For the stretch-bend strip (plastic stretching then bending, ``experiments/strips.py``)
at each mesh, prints and writes to ``experiments/results/bench_core.csv``:

- compile time of the whole jitted simulation;
- Newton iterations per accepted step and wall time per Newton iteration of the full run;
- the split of one Newton iteration at the final (plastic) state into residual + tangent assembly,
  the block-tridiagonal solve, and the dense reference solve.
"""

from __future__ import annotations

import argparse
import os

import jax
import jax.numpy as jnp

import jaxfric as jf
from benchutil import median_time, write_rows
from jaxfric.fem.assembly import internal_force_and_tangent, mesh_geometry
from strips import stretch_bend_strip


def bench(nx: int, ny: int, repeat: int = 20) -> dict:
    model = stretch_bend_strip(nx=nx, ny=ny)
    result = jf.run(model, progress=False)
    h = result.history
    n_steps = len(h["time"]) - 1
    iters = int(h["newton_iters"].sum())

    mesh, mat = model.mesh, model.material
    geo = mesh_geometry(mesh)
    # The previous-step history is what a Newton iteration sees; use the final converged state.
    u = jnp.asarray(result.final.u)
    states = jax.tree_util.tree_map(jnp.asarray, result.final.material)
    assemble = jax.jit(lambda u, s: internal_force_and_tangent(mesh, mat, "fbar", geo, u, s)[:2])
    f_int, K = assemble(u, states)
    rhs = -f_int.reshape(-1)
    solve = jax.jit(jf.block_tridiag_solve)
    dense = jax.jit(lambda K, b: jnp.linalg.solve(K.to_dense(), b))
    t_asm = median_time(assemble, u, states, repeat=repeat)
    t_solve = median_time(solve, K, rhs, repeat=repeat)
    t_dense = median_time(dense, K, rhs, repeat=max(3, repeat // 5)) if nx * ny <= 1000 else float("nan")
    return dict(mesh=f"{nx}x{ny}", n_elements=nx * ny, n_dofs=mesh.n_dofs, converged=result.converged,
                n_steps=n_steps, newton_iters=iters, iters_per_step=iters / max(n_steps, 1),
                compile_s=result.compile_s, wall_s=result.wall_s,
                ms_per_iteration_run=1e3 * result.wall_s / max(iters, 1),
                ms_assembly=1e3 * t_asm, ms_solve=1e3 * t_solve, ms_dense_solve=1e3 * t_dense)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", default="300x3,1200x6")
    parser.add_argument("--repeat", type=int, default=20)
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "bench_core.csv"))
    args = parser.parse_args()
    rows = []
    for spec in args.meshes.split(","):
        nx, ny = (int(v) for v in spec.lower().split("x"))
        row = bench(nx, ny, args.repeat)
        rows.append(row)
        print(f"{row['mesh']:>8}: {row['n_elements']} elements, compile {row['compile_s']:.1f} s, "
              f"{row['n_steps']} steps, {row['iters_per_step']:.2f} Newton it/step, run "
              f"{row['wall_s']:.2f} s = {row['ms_per_iteration_run']:.2f} ms/iteration; one iteration: "
              f"assembly {row['ms_assembly']:.2f} ms + block solve {row['ms_solve']:.2f} ms "
              f"(dense solve {row['ms_dense_solve']:.1f} ms)", flush=True)
    write_rows(args.out, rows)


if __name__ == "__main__":
    main()
