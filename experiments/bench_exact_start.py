"""The penalty law and the augmented Lagrangian started from exact contact, against their plain runs and
exact contact itself.

    python experiments/bench_exact_start.py [--case NAME ...] [--runs lcp_ssn,penalty,exact_start,...]

Per case (a scene, variant and config overrides; ``CASES``) runs exact contact (``lcp_ssn``), the penalty law
as it is by default (``penalty``), the penalty law with every step attempt started from the step solved
by exact contact's semismooth Newton with the penalty's compliance (``exact_start``: ``--set
exact_start=true``, :class:`jaxfric.contact.formulations.ExactStartPenalty`), and the augmented Lagrangian
without and with its start from exact contact (``auglag``, ``auglag_exact_start``), one after the other in
this process, with compilation timed apart. Per run: steps, cut steps, Newton iterations (the exact start's
both solves), solve and compile time, the steady drawing force over the scene's steady window (or the
drawing force at the end where the stroke stops short of it), the largest penetration and the clamping
force at the end. Writes
``experiments/results/bench_exact_start.csv`` (rows of the cases run replace that case's earlier rows).

Timings are ratios within one process: run it alone (one XLA thread per run, as ``jaxfric run``'s
single-device setting: ``XLA_FLAGS=--xla_force_host_platform_device_count=1``).

``--trace CASE --at U``: where the exact start's iterations go. Runs ``exact_start`` on CASE to the first step
end at or beyond U mm of draw, solves the next nominal increment from there with the compliant semismooth
Newton (:func:`jaxfric.contact.formulations.exact_start_point`, from the load loop's secant guess) and then the
penalty law's Newton by hand from its start, with the solver's line search
(``stiff_penalty_newton.searched_step``). Per iteration: step length, residual before and after (max norm,
N/mm), the step's size against the increment test, and the pairs whose status changed (open 0, stick 1,
slip 2) by kind with the largest gap and normal force among them. Writes
``experiments/results/bench_exact_start_trace.csv``.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import os

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from benchutil import read_rows, write_rows  # noqa: E402
from blankholder_penalty_newton import status_changes  # noqa: E402
from jaxfric.contact.formulations import exact_start_point  # noqa: E402
from jaxfric.contact.system import linearize  # noqa: E402
from jaxfric.io.instants import steady_drawing_force  # noqa: E402
from jaxfric.loadpath.model import tool_positions  # noqa: E402
from jaxfric.loadpath.run import run  # noqa: E402
from jaxfric.loadpath.step import StepContext, step_args, unknowns  # noqa: E402
from jaxfric.scenes import make  # noqa: E402
from stiff_penalty_newton import searched_step  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "results", "bench_exact_start.csv")
TRACE_OUT = os.path.join(HERE, "results", "bench_exact_start_trace.csv")

# name: (scene, variant, overrides)
CASES = {
    "nine_mu017": ("nine", "mu017", {}),
    "nine_mu017_U10": ("nine", "mu017", {"U_draw": 10.0}),
    "nine_mu000": ("nine", "mu000", {}),
    "blankholder_shape1_U3": ("blankholder", "shape1", {"U_pull": 3.0}),
    "blankholder_shape1": ("blankholder", "shape1", {}),
    "bead_th045_mu017": ("bead", "th045_mu017", {}),
    "bead_th090_mu017": ("bead", "th090_mu017", {}),
    "bead_th135_mu017": ("bead", "th135_mu017", {}),
    "flat_die_const_force": ("flat_die", "const_force", {}),
}
RUNS = {"lcp_ssn": ("lcp_ssn", {}), "penalty": ("penalty", {}),
        "exact_start": ("penalty", {"exact_start": True}), "auglag": ("auglag", {}),
        "auglag_exact_start": ("auglag", {"exact_start": True})}


def one(case: str, label: str) -> dict:
    """The row of one run of ``case`` with the algorithm and overrides of ``RUNS[label]``."""
    scene_name, variant, overrides = CASES[case]
    algorithm, extra = RUNS[label]
    scene = make(scene_name, variant, algorithm, {**overrides, **extra})
    res = run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe, progress=False,
              raise_on_failure=False)
    h = res.history
    window = getattr(scene, "steady_window", None)
    steady = steady_drawing_force(h, window) if window is not None else None
    gap = np.asarray(h["max_penetration"]) if "max_penetration" in h else np.zeros(1)
    return {"case": case, "run": label, "scene": scene_name, "variant": variant, "algorithm": algorithm,
            "law": type(scene.model.contact).__name__, "converged": res.converged,
            "steps": len(h["time"]) - 1, "cut_steps": int(np.sum(np.asarray(h["cutbacks"]) > 0)),
            "newton_iterations": int(np.sum(np.asarray(h["newton_iters"]))),
            "solve_s": round(float(res.wall_s), 2), "compile_s": round(float(res.compile_s), 2),
            "steady_drawing_force": steady, "drawing_force_end": float(h["drawing_force"][-1]),
            "clamping_force_end": float(h["clamping_force"][-1]) if "clamping_force" in h else None,
            "max_penetration": float(np.max(gap))}


def trace(case: str, at: float, iterations: int = 30) -> list[dict]:
    """The exact start of the nominal increment after the first step end at or beyond ``at`` mm of draw of
    ``case``, its penalty solve by hand (module doc)."""
    scene_name, variant, overrides = CASES[case]
    scene = make(scene_name, variant, "penalty", {**overrides, "exact_start": True})
    full = run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe, progress=False,
               raise_on_failure=False)
    h = full.history
    row = int(np.flatnonzero((np.asarray(h["phase_name"]) == "draw")
                             & (np.asarray(h["drawing_displacement"]) >= at))[0])
    previous, state = (run(scene.model, newton=scene.newton, observe=scene.observe, progress=False,
                           raise_on_failure=False,   # the same program, stopped at that row
                           control=dataclasses.replace(scene.control, max_steps=n)).simulation.final
                       for n in (row - 1, row))
    model = scene.model
    stroke = float(getattr(scene.config, importlib.import_module(f"jaxfric.scenes.{scene_name}").STROKE_FIELD))
    t = float(h["time"][row]) + float(scene.config.dU) / stroke     # the nominal increment (Nine, blankholder)
    args, _, _ = step_args(model, state, int(state.phase), t, StepContext.build(model))
    x_ref = unknowns(model, state.u, tool_positions(state))
    # The load loop's secant guess: the last accepted increment, scaled to this one.
    x_prev = unknowns(model, previous.u, tool_positions(previous))
    x0 = x_ref + (t - float(state.time)) / (float(state.time) - float(previous.time)) * (x_ref - x_prev)
    start, penalty, exact = jax.jit(lambda a, x, xr: exact_start_point(model.contact, a, x, xr, scene.newton))(
        args, x0, x_ref)
    lin_at = jax.jit(lambda x: linearize(x, penalty))
    x, lin = start, lin_at(start)
    opts = scene.newton
    tol = opts.atol + opts.rtol * max(float(lin.scale), 1e-6)
    out = []
    for k in range(iterations):
        dx, alpha, new = searched_step(lin_at, x, lin)
        step = alpha * float(jnp.max(jnp.abs(dx)))
        out.append({"case": case, "u_draw": float(h["drawing_displacement"][row]),
                    "exact_iterations": int(exact.iterations), "iteration": k, "step_length": alpha,
                    "residual_before": float(jnp.max(jnp.abs(lin.residual))),
                    "residual_after": float(jnp.max(jnp.abs(new.residual))), "tolerance": tol,
                    "step": step,
                    "step_tolerance": opts.du_atol + opts.du_rtol * float(jnp.max(jnp.abs(x + alpha * dx - x_ref))),
                    **status_changes(lin, new)})
        x, lin = x + alpha * dx, new
        r = out[-1]
        print(f"{k}: length {alpha:g}, residual {r['residual_before']:.3e} -> {r['residual_after']:.3e} "
              f"(tolerance {tol:.1e}), step {step:.2e} ({r['step_tolerance']:.1e}), "
              f"{r['status_changes']} status changes", flush=True)
        if r["residual_after"] <= tol and not r["status_changes"] and step <= r["step_tolerance"]:
            break
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", nargs="*", choices=sorted(CASES), default=["nine_mu017_U10", "blankholder_shape1_U3"])
    ap.add_argument("--trace", choices=sorted(c for c in CASES if CASES[c][0] in ("nine", "blankholder")),
                    help="trace one exact-started step of this case instead")
    ap.add_argument("--at", type=float, default=6.0, help="--trace: draw (mm) after which the step is traced")
    ap.add_argument("--runs", default="lcp_ssn,penalty,exact_start", help="comma-separated, of " + ", ".join(RUNS))
    a = ap.parse_args(argv)
    if a.trace:
        write_rows(TRACE_OUT, trace(a.trace, a.at))
        return
    labels = a.runs.split(",")
    for label in labels:
        if label not in RUNS:
            raise SystemExit(f"--runs: unknown run {label!r}; choose from {', '.join(RUNS)}")
    rows = []
    for case in a.case:
        for label in labels:
            row = one(case, label)
            rows.append(row)
            print(f"{case:>22} {label:>11}: {row['steps']} steps ({row['cut_steps']} cut), "
                  f"{row['newton_iterations']} iterations, solve {row['solve_s']} s + compile {row['compile_s']} s, "
                  f"steady {row['steady_drawing_force']}, end {row['drawing_force_end']:.4f} N/mm", flush=True)
    done = {(r["case"], r["run"]) for r in rows}
    kept = [r for r in read_rows(OUT) if (r["case"], r["run"]) not in done]
    write_rows(OUT, kept + rows)


if __name__ == "__main__":
    main()
