"""Where the penalty law's Newton iterations go on the blankholder: its runs against exact contact, and the
iterates of one drawing step.

    python experiments/blankholder_penalty_newton.py [--variant shape1] [--pull 3] [--at 1] [--smoothing 1,10]

Runs the blankholder ``--variant`` at its spec mesh, pulled ``--pull`` mm, with exact contact (``lcp_ssn``),
the penalty law, and the penalty law smoothed at each ``--smoothing`` S (N/mm, the config field: the
softplus law of :mod:`jaxfric.contact.laws`); per run and phase its steps, Newton iterations, cut steps and
their causes, and the solve's wall time, with the drawing and clamping forces at the end. Writes
``experiments/results/blankholder_penalty_newton.csv``.

Then, for the penalty law and for the last ``--smoothing`` S, takes the state converged at the first step end
at or beyond ``--at`` mm of draw and solves the next nominal increment by hand from it (not from the secant
prediction): Newton steps on :func:`jaxfric.contact.system.linearize` with the solver's line search
(``stiff_penalty_newton.searched_step``: the full step, a quarter, a sixteenth, the first that does not raise
the residual's norm). Per iteration: the step length, the residual before and after (max norm, N/mm), and
the pairs whose status changed (open 0, stick 1, slip 2) by kind, with the largest gap (mm) and normal force
(N/mm) among them. Writes ``experiments/results/blankholder_penalty_newton_trace.csv``.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import os

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from benchutil import write_rows  # noqa: E402
from jaxfric.loadpath.run import run  # noqa: E402
from jaxfric.numerics.results import causes  # noqa: E402
from jaxfric.scenes import make  # noqa: E402
from stiff_penalty_newton import by_hand, searched_step  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
RUNS_OUT = os.path.join(HERE, "results", "blankholder_penalty_newton.csv")
TRACE_OUT = os.path.join(HERE, "results", "blankholder_penalty_newton_trace.csv")
ITERATIONS = 40   # Newton iterations traced at most
KINDS = {(0, 1): "open->stick", (0, 2): "open->slip", (1, 0): "stick->open", (2, 0): "slip->open",
         (1, 2): "stick->slip", (2, 1): "slip->stick"}


def _run(scene, max_steps=None):
    control = scene.control if max_steps is None else dataclasses.replace(scene.control, max_steps=max_steps)
    return run(scene.model, newton=scene.newton, control=control, observe=scene.observe, progress=False,
               raise_on_failure=False)


def phase_rows(label: str, result) -> list[dict]:
    """Per phase of ``result``: steps, Newton iterations (failed attempts included), cut steps and causes."""
    h = result.history
    names = np.asarray(h["phase_name"])
    rows = []
    for phase in dict.fromkeys(names[1:]):
        rows_of = np.flatnonzero(names == phase)
        rows_of = rows_of[rows_of > 0]
        codes = collections.Counter(name for c in np.asarray(h["cut_codes"])[rows_of] for name in causes(c))
        rows.append({"run": label, "phase": phase, "steps": len(rows_of),
                     "newton_iterations": int(np.sum(np.asarray(h["newton_iters"])[rows_of])),
                     "cut_steps": int(np.sum(np.asarray(h["cutbacks"])[rows_of] > 0)),
                     "cut_causes": " ".join(f"{k}:{v}" for k, v in sorted(codes.items())),
                     "solve_s": round(float(result.wall_s), 2), "converged": result.converged,
                     "drawing_force_end": float(h["drawing_force"][-1]),
                     "clamping_force_end": float(h["clamping_force"][-1])})
    return rows


def status_changes(lin, new) -> dict:
    """The pairs whose status changed from the linearisation ``lin`` to ``new`` (their contact outputs,
    ``aux[2]``): how many, how many of each kind (``KINDS``), and the largest gap (mm) and normal force
    (N/mm) among them, before or after."""
    before, after = (jax.tree_util.tree_map(np.asarray, v.aux[2]) for v in (lin, new))
    changed = np.flatnonzero(before["status"] != after["status"])
    kinds = collections.Counter(KINDS[(int(before["status"][i]), int(after["status"][i]))] for i in changed)
    rn = np.maximum(np.abs(before["rn"][changed]), np.abs(after["rn"][changed]))
    gap = np.maximum(np.abs(before["gap"][changed]), np.abs(after["gap"][changed]))
    return {"status_changes": len(changed), **{kind: kinds.get(kind, 0) for kind in KINDS.values()},
            "largest_gap": float(gap.max()) if len(changed) else 0.0,
            "largest_rn": float(rn.max()) if len(changed) else 0.0}


def trace(label: str, scene, result, at: float) -> list[dict]:
    """Newton by hand on the nominal increment after the first step end at or beyond ``at`` mm of draw."""
    h = result.history
    draw = np.asarray(h["phase_name"]) == "draw"
    row = int(np.flatnonzero(draw & (np.asarray(h["drawing_displacement"]) >= at))[0])
    state = _run(scene, max_steps=row).simulation.final     # the same program, stopped at that row
    model = scene.model
    pull = float(scene.config.U_pull)
    t = float(h["time"][row]) + float(scene.config.dU) / pull
    lin_at, x, lin = by_hand(model, state, t)
    opts = scene.newton
    tol = opts.atol + opts.rtol * max(float(lin.scale), 1e-6)
    out = []
    for k in range(ITERATIONS):
        dx, alpha, new = searched_step(lin_at, x, lin)
        out.append({"run": label, "u_draw": float(h["drawing_displacement"][row]), "iteration": k,
                    "step_length": alpha, "residual_before": float(jnp.max(jnp.abs(lin.residual))),
                    "residual_after": float(jnp.max(jnp.abs(new.residual))), "tolerance": tol,
                    **status_changes(lin, new)})
        x, lin = x + alpha * dx, new
        if out[-1]["residual_after"] <= tol:
            break
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variant", default="shape1")
    ap.add_argument("--pull", type=float, default=3.0, help="U_pull (mm)")
    ap.add_argument("--at", type=float, default=1.0, help="draw (mm) after which one step is traced")
    ap.add_argument("--smoothing", default="1,10", help="penalty smoothings S (N/mm), comma-separated")
    a = ap.parse_args(argv)
    cases = [("lcp_ssn", "lcp_ssn", {}), ("penalty", "penalty", {})]
    cases += [(f"penalty S={s:g}", "penalty", {"smoothing": s}) for s in map(float, a.smoothing.split(","))]
    runs, traces = [], []
    for label, algorithm, extra in cases:
        scene = make("blankholder", a.variant, algorithm, {"U_pull": a.pull, **extra})
        result = _run(scene)
        rows = phase_rows(label, result)
        for r in rows:
            print(f"{label:>16} {r['phase']:>5}: {r['steps']} steps, {r['newton_iterations']} iterations, "
                  f"{r['cut_steps']} cut ({r['cut_causes'] or '-'}); solve {r['solve_s']} s")
        runs += rows
        if algorithm == "penalty" and label in (cases[1][0], cases[-1][0]):
            traces += trace(label, scene, result, a.at)
            last = traces[-1]
            print(f"{label:>16} traced step after U = {last['u_draw']:.3f} mm: {last['iteration'] + 1} iterations, "
                  f"{sum(r['status_changes'] for r in traces if r['run'] == label)} status changes")
    write_rows(RUNS_OUT, runs)
    write_rows(TRACE_OUT, traces)


if __name__ == "__main__":
    main()
