"""Reverse-mode gradient through a whole loading path: cost and memory, with and without per-step
checkpointing: ``python experiments/bench_grad_memory.py [--scene flat_die] [--variant const_force]
[--mesh 24x1] [--params mu,F_clamp,E,sigma_y] [--set NAME=VALUE ...]``.

The gradient of the final drawing force with respect to all ``--params`` (``jax.grad`` through
``simulate_fixed``, every step by the implicit function theorem) against the primal run and against
forward mode (``jax.jacfwd``). Memory is XLA's own account of the compiled function
(``memory_analysis()``: temporary buffers), for the nominal path and for a path of half as many
steps, so the growth with the number of steps reads off directly. Writes
``experiments/results/bench_grad_memory_<scene>.csv``.
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchutil import write_rows
from jaxfric.fem.loading import schedule
from jaxfric.identification.params import parameterize
from jaxfric.loadpath.simulate import simulate_fixed


def _timed(fn, p, repeat=3):
    jax.block_until_ready(fn(p))
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(p))
        best = min(best, time.perf_counter() - t0)
    return best, out


def measure(scene, variant, mesh, names, overrides, stroke_scale):
    over = {"mesh": mesh, **overrides}
    if stroke_scale != 1.0:
        key = {"flat_die": "U_draw", "nine": "U_draw", "bead": "s_draw", "blankholder": "U_pull"}[scene]
        base = parameterize(scene, names, variant=variant, overrides=over).scene.config
        over[key] = getattr(base, key) * stroke_scale
    par = parameterize(scene, names, variant=variant, overrides=over)
    n_steps = schedule(par.scene.model.phases).n_nominal_steps
    observe = par.scene.observe

    def final_force(p, checkpoint=True):
        sim = simulate_fixed(par.model(p), observe=observe, checkpoint=checkpoint)
        return sim.history.observed["drawing_force"][sim.history.n_rows - 1], sim.code

    p0 = jnp.asarray(par.p0)
    out = []
    primal = jax.jit(lambda p: final_force(p))
    t_primal, (f, code) = _timed(primal, p0)
    if int(code) != 0:
        raise SystemExit(f"the nominal steps do not converge (code {int(code)}); use smaller increments")
    fwd = jax.jit(jax.jacfwd(lambda p: final_force(p)[0]))
    t_fwd, g_fwd = _timed(fwd, p0)
    for ckpt in (True, False):
        fn = jax.jit(jax.grad(lambda p: final_force(p, ckpt)[0]))
        mem = fn.lower(p0).compile().memory_analysis()
        t_rev, g_rev = _timed(fn, p0)
        out.append({"scene": scene, "variant": par.scene.variant, "mesh": mesh, "n_steps": n_steps,
                    "n_params": len(names), "checkpoint": ckpt, "drawing_force": float(f),
                    "primal_s": round(t_primal, 3), "jacfwd_s": round(t_fwd, 3), "grad_s": round(t_rev, 3),
                    "grad_over_primal": round(t_rev / t_primal, 2),
                    "temp_MB": round(mem.temp_size_in_bytes / 2**20, 1) if mem else None,
                    # relative to the largest entry (some entries are 0 or round-off: d/d sigma_y
                    # when nothing yields)
                    "rev_vs_fwd": float(np.max(np.abs(np.asarray(g_rev) - np.asarray(g_fwd)))
                                        / np.max(np.abs(np.asarray(g_fwd)))),
                    **{f"d_{n}": float(v) for n, v in zip(names, np.asarray(g_rev))}})
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="flat_die")
    ap.add_argument("--variant", default="const_force")
    ap.add_argument("--mesh", default="24x1")
    ap.add_argument("--params", default="mu,F_clamp,E,sigma_y")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    a = ap.parse_args(argv)
    names = a.params.split(",")
    overrides = dict(s.split("=", 1) for s in a.overrides)
    rows = []
    for scale in (0.5, 1.0):
        for row in measure(a.scene, a.variant, a.mesh, names, overrides, scale):
            print(row, flush=True)
            rows.append(row)
    write_rows(os.path.join(os.path.dirname(os.path.abspath(__file__)), "results",
                            f"bench_grad_memory_{a.scene}.csv"), rows)


if __name__ == "__main__":
    main()
