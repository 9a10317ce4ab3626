"""Cost of a forward-mode derivative along a whole load path: ``python experiments/bench_jvp.py
[--scene nine] [--variant mu017] [--algorithm penalty] [--mesh 40x2] [--adaptive] [--h 1e-5] [--no-fd] [--tag T]
[--set NAME=VALUE ...]``.

Differentiates the final drawing force of the scene with respect to the friction coefficient of its
frictional tools (``jax.jvp`` through the load loop: each converged step by the implicit function
theorem, the plastic history threaded through) and compares its wall time with the primal run of the
same compiled structure. Also checks the derivative against central differences of the primal.

By default the nominal steps run in a fixed-length scan (``simulate_fixed``): central differences are
then differences along one step sequence. With ``--adaptive`` the step sequence itself changes with mu
(cutbacks), and differences of the primal jump by the force noise of a changed sequence: at 60 x 2
they gave 3122, 1134 and -21492 N/mm for h = 1e-3, 1e-4, 1e-5 against a jvp of 3503. ``--no-fd``
skips the differences (two more primal runs). Writes ``experiments/results/bench_jvp_<scene><tag>.csv``.
"""

from __future__ import annotations

import argparse
import os
import time

import equinox as eqx
import jax
import jax.numpy as jnp

from benchutil import write_rows
from jaxfric import scenes
from jaxfric.loadpath.simulate import simulate, simulate_fixed


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", default="nine")
    p.add_argument("--variant", default="mu017")
    p.add_argument("--algorithm", default="penalty", help="penalty, auglag, lcp_ssn or lcp_lemke")
    p.add_argument("--mesh", default="40x2")
    p.add_argument("--adaptive", action="store_true", help="adaptive steps instead of the nominal ones")
    p.add_argument("--h", type=float, default=1e-5, help="central-difference step in mu")
    p.add_argument("--no-fd", action="store_true", help="skip the central differences")
    p.add_argument("--tag", default="", help="suffix of the CSV name")
    p.add_argument("--set", dest="overrides", action="append", default=[])
    a = p.parse_args(argv)
    extra = dict(s.split("=", 1) for s in a.overrides)
    scene = scenes.make(a.scene, a.variant, a.algorithm, {"mesh": a.mesh, **extra})
    model = scene.model
    frictional = [k for k, t in enumerate(model.tools) if t.frictional]
    mu0 = float(model.tools[frictional[0]].mu[-1])

    def final_force(mu):
        m = eqx.tree_at(lambda m: [m.tools[k].mu for k in frictional], model,
                        [jnp.where(model.tools[k].mu > 0, mu, 0.0) for k in frictional])
        if a.adaptive:
            sim = simulate(m, control=scene.control, observe=scene.observe)
        else:
            sim = simulate_fixed(m, observe=scene.observe)
        return sim.history.observed["drawing_force"][sim.history.n_rows - 1], sim.code

    primal = jax.jit(final_force)
    tangent = jax.jit(lambda mu: jax.jvp(lambda v: final_force(v)[0], (mu,), (jnp.ones_like(mu),)))
    mu = jnp.asarray(mu0)
    rows = {}
    for name, fn in (("primal", primal), ("jvp", tangent)):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(mu))
        compile_and_run = time.perf_counter() - t0
        t1 = time.perf_counter()
        out = jax.block_until_ready(fn(mu))
        rows[name] = (time.perf_counter() - t1, compile_and_run, out)
    (f, code), _ = rows["primal"][2], None
    _, df = rows["jvp"][2]
    h = a.h
    fd = float("nan") if a.no_fd else (primal(mu + h)[0] - primal(mu - h)[0]) / (2 * h)
    row = {"scene": a.scene, "variant": scene.variant, "algorithm": a.algorithm, "mesh": a.mesh,
           "steps": "adaptive" if a.adaptive else "fixed",
           "mu": mu0, "h": h, "code": int(code),
           "drawing_force": float(f), "dF_dmu_jvp": float(df), "dF_dmu_central_diff": float(fd),
           "rel_diff": abs(float(df) - float(fd)) / max(abs(float(fd)), 1e-300),
           "primal_s": round(rows["primal"][0], 3), "jvp_s": round(rows["jvp"][0], 3),
           "jvp_over_primal": round(rows["jvp"][0] / rows["primal"][0], 2),
           "primal_first_call_s": round(rows["primal"][1], 2), "jvp_first_call_s": round(rows["jvp"][1], 2)}
    for k, v in row.items():
        print(f"{k:>22}: {v}")
    write_rows(os.path.join(os.path.dirname(__file__), "results", f"bench_jvp_{a.scene}{a.tag}.csv"), [row])


if __name__ == "__main__":
    main()
