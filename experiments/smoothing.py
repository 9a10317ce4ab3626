"""Forces and derivatives of the Nine test with the exact and the smoothed contact laws:
``python experiments/smoothing.py [--mesh 40x2] [--stroke 1] [--smoothing 0,0.1,1,10]``.

What derivative does a run return where the exact law has kinks? The pair law (``jaxfric.contact.laws``)
takes its branches with explicit ``where``: closed or open, stick or slip. Differentiating a converged
step by the implicit function theorem then differentiates the branch each pair is on at that step, i.e.
the one-sided derivative in the direction that keeps every pair's status. That is the exact derivative
of the force wherever no pair sits on a switch, but a finite difference with a step h crosses every
switch that lies within h of the parameter, and the force is only piecewise smooth in between.

The smoothed law (``--set smoothing=S``, N/mm: softplus instead of the kinks) makes the force a smooth
function of the parameters, at the price of a force error of order S near the switches. For each S
this script runs the Nine test (variant mu017, short stroke, small steps, tight Newton tolerances),
replays its accepted steps as in ``tests/test_gradients.py``, and compares forward-mode derivatives of
the final drawing and clamping forces with respect to mu and R1 with central differences (h = 1e-4
|p|, ``--rel-h``) along the same replay. Writes ``experiments/results/smoothing_nine<tag>.csv`` and
``.png``.
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchutil import write_rows
from jaxfric.identification.params import parameterize, path_function
from jaxfric.numerics.newton import NewtonOptions

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
NAMES = ("mu", "R1")
OUTPUTS = ("drawing_force", "clamping_force")
# The curved tools leave ~1e-10 N/mm of residual Newton cannot remove: atol 1e-9 (tests/test_gradients.py).
NEWTON = NewtonOptions(rtol=1e-11, atol=1e-9, max_iterations=60)


def one(smoothing: float, base: dict, rel_h: float) -> list[dict]:
    par = parameterize("nine", NAMES, variant="mu017", overrides={**base, "smoothing": smoothing})
    t0 = time.perf_counter()
    path = path_function(par, newton=NEWTON)

    def outputs(p):
        h, code = path(p)
        last = h.n_rows - 1
        return jnp.stack([h.observed[k][last] for k in OUTPUTS]), (code, jnp.sum(h.cutbacks), h.n_rows)

    p0 = jnp.asarray(par.p0)
    primal = jax.jit(outputs)
    value, (code, cuts, rows) = primal(p0)
    if int(code) != 0:
        raise SystemExit(f"smoothing {smoothing}: the replay at the start values fails (code {int(code)})")
    jac = np.asarray(jax.jit(jax.jacfwd(lambda p: outputs(p)[0]))(p0))
    out = []
    for i, name in enumerate(NAMES):
        h = rel_h * abs(float(p0[i]))
        up, (c1, k1, _) = primal(p0.at[i].add(h))
        down, (c2, k2, _) = primal(p0.at[i].add(-h))
        fd = (np.asarray(up) - np.asarray(down)) / (2 * h)
        for j, quantity in enumerate(OUTPUTS):
            out.append({"smoothing": smoothing, "quantity": quantity, "parameter": name,
                        "value": float(value[j]), "jvp": float(jac[j, i]), "central_difference": float(fd[j]),
                        "rel_diff": float(abs(fd[j] - jac[j, i]) / max(np.max(np.abs(jac[j])), 1e-300)),
                        "h": h, "replay_rows": int(rows), "replay_cutbacks": int(cuts),
                        "cutbacks_at_plus_minus_h": f"{int(k1)}/{int(k2)}",
                        "codes_at_plus_minus_h": f"{int(c1)}/{int(c2)}", "wall_s": None})
    wall = time.perf_counter() - t0
    for r in out:
        r["wall_s"] = round(wall, 1)
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default="40x2")
    ap.add_argument("--stroke", type=float, default=1.0, help="U_draw (mm)")
    ap.add_argument("--smoothing", default="0,0.1,1,10", help="force scales S (N/mm), comma-separated")
    ap.add_argument("--rel-h", type=float, default=1e-4, help="difference step relative to |p|")
    ap.add_argument("--tag", default="", help="suffix of the output files")
    a = ap.parse_args(argv)
    # Steps five times smaller than the scene's: with them the friction and material columns of the
    # exact law come close to their differences (docs/results.md, smoothed contact law).
    base = {"mesh": a.mesh, "U_draw": a.stroke, "dU": 0.02, "dq_clamp": 0.05}
    rows = []
    for s in (float(v) for v in a.smoothing.split(",")):
        rows += one(s, base, a.rel_h)
        for r in rows[-4:]:
            print(" ".join(f"{k}={v:.6g}" if isinstance(v, float) else f"{k}={v}" for k, v in r.items()), flush=True)
        stem = os.path.join(RESULTS, f"smoothing_nine{a.tag}")
        write_rows(stem + ".csv", rows)  # after every S: nothing lost
        _plot(rows, stem + ".png")


def _plot(rows, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    svals = sorted({r["smoothing"] for r in rows})
    x = [max(s, 1e-3) for s in svals]   # S = 0 drawn at 1e-3 on the log axis
    for quantity, style in zip(OUTPUTS, ("o-", "s--")):
        f = [next(r["value"] for r in rows if r["smoothing"] == s and r["quantity"] == quantity) for s in svals]
        axes[0].plot(x, f, style, label=quantity)
        for ax, name in zip(axes[1:], NAMES):
            sel = [next(r for r in rows if r["smoothing"] == s and r["quantity"] == quantity and r["parameter"] == name)
                   for s in svals]
            ax.plot(x, [r["jvp"] for r in sel], style, label=f"d {quantity} / d {name}, forward mode")
            ax.plot(x, [r["central_difference"] for r in sel], "x", ms=9, label="central difference")
    axes[0].set_ylabel("force at the end of the stroke (N/mm)")
    for ax, title in zip(axes, ("forces", "derivative w.r.t. mu", "derivative w.r.t. R1 (per mm)")):
        ax.set_xscale("log")
        ax.set_xlabel("smoothing S (N/mm; S = 0 drawn at 1e-3)")
        ax.set_title(title, fontsize=10)
        ax.legend(fontsize=7)
    fig.suptitle("Nine test mu017: exact (S = 0) and smoothed contact laws")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
