"""Newton iterations of steady drawing steps on the Nine test against the order of the step predictor.

    python experiments/nine_predictor.py [--u0 20] [--steps 15] [--algorithm lcp_ssn]

Runs Nine mu017 (300 x 3) to U = u0 mm with the load loop of ``jaxfric.loadpath.simulate``, takes three more
nominal steps (0.1 mm) with the secant predictor, and then, from that same state, ``--steps`` nominal
steps three times: with the initial guess extrapolated linearly (the secant predictor of the load
loop), quadratically and cubically from the last converged states. Each step is solved by
``solve_step`` with the default Newton options. Writes ``results/nine_predictor.csv`` (one row per step
and order: iterations, ||R||_inf of each evaluated point; with exact contact the first one is the
initial guess's without contact forces) and prints the totals.
"""

from __future__ import annotations

import argparse
import csv
import os

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxfric.loadpath.simulate import simulate  # noqa: E402
from jaxfric.loadpath.step import StepContext, solve_step  # noqa: E402
from jaxfric.numerics.newton import NewtonOptions  # noqa: E402
from jaxfric.scenes import nine  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
# Extrapolation weights on the last 2, 3, 4 states (newest last) for equal steps.
WEIGHTS = {1: (-1.0, 2.0), 2: (1.0, -3.0, 3.0), 3: (-1.0, 4.0, -6.0, 4.0)}


def _guess(states, order):
    w = WEIGHTS[order]
    last = states[-len(w):]
    return (sum(c * s.u for c, s in zip(w, last)), sum(c * s.contact.q for c, s in zip(w, last)))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--u0", type=float, default=20.0, help="drawing displacement to start from (mm)")
    ap.add_argument("--steps", type=int, default=15, help="steps per predictor order")
    ap.add_argument("--algorithm", default="lcp_ssn")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "nine_predictor.csv"))
    a = ap.parse_args(argv)

    short = nine.build(nine.NineConfig(U_draw=a.u0), a.algorithm, "mu017")
    sim = eqx.filter_jit(lambda m: simulate(m, control=short.control))(short.model)
    if int(sim.code) != 0:
        raise SystemExit(f"the run to U = {a.u0} mm did not converge (code {int(sim.code)})")
    config = nine.NineConfig()
    model = nine.build(config, a.algorithm, "mu017").model
    ctx = StepContext.build(model)
    step = eqx.filter_jit(lambda st, t, g: solve_step(model, st, 1, t, NewtonOptions(), ctx, guess=g))
    dt = config.dU / config.U_draw
    # The short run ends at pseudo-time 2 = its U_draw; in the full run that state sits at u0 / U_draw.
    states = [eqx.tree_at(lambda s: s.time, sim.final, jnp.asarray(1.0 + a.u0 / config.U_draw))]
    for _ in range(3):
        g = _guess(states, 1) if len(states) > 1 else (states[-1].u, states[-1].contact.q)
        sol, new = step(states[-1], float(states[-1].time) + dt, g)
        if int(sol.code) != 0:
            raise SystemExit(f"a warm-up step failed (code {int(sol.code)})")
        states.append(new)

    rows = []
    for order in WEIGHTS:
        hist = list(states)
        for i in range(a.steps):
            sol, new = step(hist[-1], float(hist[-1].time) + dt, _guess(hist, order))
            r = np.asarray(sol.residual_history)
            rows.append({"order": order, "step": i, "code": int(sol.code), "iterations": int(sol.iterations),
                         "residuals": " ".join(f"{v:.3g}" for v in r[~np.isnan(r)])})
            if int(sol.code) != 0:
                break
            hist.append(new)
        done = [r for r in rows if r["order"] == order]
        print(f"order {order}: {len(done)} steps, {sum(r['iterations'] for r in done)} Newton iterations"
              + ("" if done[-1]["code"] == 0 else f" (stopped: code {done[-1]['code']})"), flush=True)
    os.makedirs(os.path.dirname(a.out), exist_ok=True)
    with open(a.out, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    print("wrote", a.out)


if __name__ == "__main__":
    main()
