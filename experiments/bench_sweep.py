"""Cost of a vmapped friction sweep against single runs (issue: batched sweeps).

    python experiments/bench_sweep.py [--scene flat_die] [--variant const_force] [--members 16]
                                      [--mesh NXxNY] [--set NAME=VALUE ...] [--chunk N]
                                      [--singles K] [--csv PATH] [--solver thomas|cyclic]
                                      [--devices N]

Runs ``members`` friction coefficients evenly spaced in [0.05, 0.3] as one compiled vmapped simulation
(:func:`jaxfric.loadpath.sweep.sweep`) and as single runs (:func:`jaxfric.loadpath.run.run`, compiled once), checks that
the histories agree to 1e-10 of each column's scale, and writes
``experiments/results/bench_sweep_<scene>.csv`` (or ``--csv PATH``) with compile and solve times, their
ratios and the device. ``--chunk N``: the sweep's element chunk per member (default: the sweep's, sized
for a CPU cache). ``--singles K``: time only K evenly spaced members as single runs (the mean and the
agreement check over those; for a device where single runs are slow). ``--solver``: the
block-tridiagonal solve every program here traces (:func:`jaxfric.numerics.linalg.block_solver`; default
``auto``: ``cyclic`` on a GPU, ``thomas`` on a CPU). ``--devices N``: spread the sweep's members over the
first N devices (:func:`jaxfric.loadpath.sweep.sweep`'s ``devices``; default all). On a CPU, JAX sees
N devices with ``XLA_FLAGS=--xla_force_host_platform_device_count=N`` in the environment.

``--iteration``: instead, time one Newton iteration (linearisation and solve) of all members at once
(vmapped) against one member's, at the converged final state of member 0: what batching costs per
member without the load loop's lockstep. Two batched figures: every member at its own copy of the
state (what a sweep does: the element arithmetic is batched too), and one state shared by all
members (only what depends on the swept value is batched: friction and the solve).
"""

from __future__ import annotations

import argparse
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxfric as jf
from benchutil import median_time, write_rows
from jaxfric import scenes
from jaxfric.fem.assembly import element_chunk
from jaxfric.loadpath.sweep import default_chunk, stack_models, sweep
from jaxfric.numerics.linalg import BLOCK_SOLVERS, block_solver, linear_solve, resolved_block_solver


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="flat_die")
    p.add_argument("--variant", default=None)
    p.add_argument("--members", type=int, default=16)
    p.add_argument("--mesh", default=None)
    p.add_argument("--set", dest="overrides", action="append", default=[])
    p.add_argument("--iteration", action="store_true", help="time one batched Newton iteration only")
    p.add_argument("--chunk", type=int, default=None, help="the sweep's element chunk per member")
    p.add_argument("--singles", type=int, default=None, help="number of members also run singly")
    p.add_argument("--csv", default=None, help="where to write the row")
    p.add_argument("--solver", choices=BLOCK_SOLVERS, default="auto", help="block-tridiagonal solve")
    p.add_argument("--devices", type=int, default=None, help="devices the sweep spreads its members over")
    a = p.parse_args(argv)
    if a.members < 1 or (a.singles is not None and not 1 <= a.singles <= a.members):
        p.error("--members must be >= 1 and --singles in 1..members")
    if a.devices is not None and not 1 <= a.devices <= len(jax.devices()):
        p.error(f"--devices must lie in 1..{len(jax.devices())} (the devices JAX sees)")
    extra = dict(s.split("=", 1) for s in a.overrides)
    if a.mesh:
        extra["mesh"] = a.mesh
    mus = np.linspace(0.05, 0.3, a.members)
    built = [scenes.make(a.scene, a.variant, "penalty", {**extra, "mu": float(m)}) for m in mus]
    with block_solver(a.solver):
        bench(a, built)


def bench(a, built) -> None:
    if a.iteration:
        return iteration_cost(built, a.chunk)
    devices = None if a.devices is None else jax.devices()[:a.devices]
    out = sweep([s.model for s in built], control=built[0].control, observe=built[0].observe, chunk=a.chunk,
                devices=devices)
    print(f"sweep of {a.members} over {out.n_devices} device(s): compile {out.compile_s:.2f} s, "
          f"solve {out.wall_s:.2f} s", flush=True)
    k = a.members if a.singles is None else a.singles
    chosen = sorted(set(np.linspace(0, a.members - 1, k).round().astype(int).tolist()))
    singles, compile_single, worst, iters = [], None, 0.0, []
    for i in chosen:
        s = built[i]
        r = jf.run(s.model, control=s.control, observe=s.observe, progress=False)
        compile_single = r.compile_s if compile_single is None else compile_single
        singles.append(r.wall_s)
        iters.append(int(np.sum(r.history["newton_iters"])))
        h = out.history(i)
        for name in ("drawing_force", "clamping_force", "time"):
            scale = max(float(np.max(np.abs(r.history[name]))), 1e-300)
            worst = max(worst, float(np.max(np.abs(h[name] - r.history[name]))) / scale)
    mean_single = float(np.mean(singles))
    row = {"scene": a.scene, "variant": built[0].variant, "mesh": f"{built[0].model.mesh.nx}x{built[0].model.mesh.ny}",
           "members": a.members, "devices": out.n_devices, "sweep_compile_s": round(out.compile_s, 3),
           "sweep_wall_s": round(out.wall_s, 3),
           "single_compile_s": round(compile_single, 3), "single_wall_s_mean": round(mean_single, 3),
           "single_wall_s_max": round(max(singles), 3), "singles_run": len(chosen),
           # The loop of all members' single runs, measured or (with --singles) estimated from the mean.
           "looped_wall_s": round(mean_single * a.members, 3),
           "sweep_over_single": round(out.wall_s / mean_single, 2),
           "sweep_over_looped": round(out.wall_s / (mean_single * a.members), 2), "max_rel_diff": f"{worst:.1e}",
           # The flat loop's cost law: about the largest member's total of Newton iterations (and its
           # attempts) in batched passes, against the mean member's in single runs.
           "member_iters_mean": round(float(np.mean(iters)), 1), "member_iters_max": max(iters),
           "chunk": a.chunk if a.chunk is not None else "default", "solver": resolved_block_solver(),
           "device": jax.devices()[0].device_kind, "jax": jax.__version__}
    for key, v in row.items():
        print(f"{key:>20}: {v}")
    write_rows(a.csv or os.path.join(os.path.dirname(__file__), "results", f"bench_sweep_{a.scene}.csv"), [row])


def iteration_cost(built, chunk=None) -> None:
    values, axes, (treedef, static) = stack_models([s.model for s in built])
    r = jf.run(built[0].model, control=built[0].control, observe=built[0].observe, progress=False)
    state = jax.tree_util.tree_map(jnp.asarray, r.final)

    def iteration(v, s):
        model = eqx.combine(jax.tree_util.tree_unflatten(treedef, v), static)
        lin = jf.linearize_step(model, s, s.phase, s.time)
        return linear_solve(lin.jacobian, -lin.residual)

    n = len(built)
    v0 = [v if ax is None else v[0] for v, ax in zip(values, axes)]
    states = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (n,) + a.shape) + 0, state)
    one = median_time(jax.jit(iteration), v0, state, repeat=20)
    chunk = default_chunk(n) if chunk is None else chunk   # as jaxfric.loadpath.sweep.sweep traces its members
    with element_chunk(chunk):
        own = median_time(jax.jit(jax.vmap(iteration, in_axes=(axes, 0))), values, states, repeat=10)
    shared = median_time(jax.jit(jax.vmap(iteration, in_axes=(axes, None))), values, state, repeat=10)
    print(f"one Newton iteration: single {1e3 * one:.2f} ms; {n} members vmapped, each at its own state "
          f"{1e3 * own:.2f} ms = {own / one:.1f}x single ({1e3 * own / n:.2f} ms per member); one state "
          f"shared by all members {1e3 * shared:.2f} ms = {shared / one:.1f}x")

    # Its two halves apart: the linearisation (element arithmetic, contact, assembly) and the
    # block-tridiagonal solve of the assembled system.
    def linearise(v, s):
        model = eqx.combine(jax.tree_util.tree_unflatten(treedef, v), static)
        return jf.linearize_step(model, s, s.phase, s.time)

    lin1 = jax.jit(linearise)(v0, state)
    with element_chunk(chunk):
        lin_one = median_time(jax.jit(linearise), v0, state, repeat=20)
        lin_own = median_time(jax.jit(jax.vmap(linearise, in_axes=(axes, 0))), values, states, repeat=10)
        lins = jax.jit(jax.vmap(linearise, in_axes=(axes, 0)))(values, states)
    solve = jax.jit(lambda lin: linear_solve(lin.jacobian, -lin.residual))
    solve_one = median_time(solve, lin1, repeat=20)
    solve_own = median_time(jax.jit(jax.vmap(lambda lin: linear_solve(lin.jacobian, -lin.residual))),
                            lins, repeat=10)
    print(f"  linearisation: single {1e3 * lin_one:.2f} ms, {n} vmapped {1e3 * lin_own:.2f} ms; "
          f"solve: single {1e3 * solve_one:.2f} ms, {n} vmapped {1e3 * solve_own:.2f} ms")


if __name__ == "__main__":
    main()
