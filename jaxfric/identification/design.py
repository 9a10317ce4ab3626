"""Tool dimensions for a target drawing force: the inverse problem a bead designer solves.

    >>> from jaxfric.identification.design import design, write_design
    >>> res = design("blankholder", 165.0, ["R", "H"], variant="shape3", bounds={"R": (3.0, 9.0), "H": (6.0, 9.7)})
    >>> res.params, res.force          # {"R": 4.17..., "H": 9.42...}, 165.01...
    >>> write_design(res, "designs/blankholder")   # design.json, design_history.csv, design.png

**The target.** A restraining force F* (N/mm): the mean drawing force over a window of the draw (the
scene's ``steady_window`` unless ``window`` = (a, b) mm is given), the quantity of the benchmarks'
steady drawing force. Or a target curve (a CSV or mapping as :func:`jaxfric.identification.fit.fit`
reads a measurement): the force at its displacements, or its means over windows of ``window`` mm.

**The method** is the identification's (:mod:`jaxfric.identification.fit`), with targets in place of
measurements: the force along a frozen step sequence with its forward-mode Jacobian in the design
parameters, bounded least squares (``scipy.optimize.least_squares``, trust-region reflective) on r =
F(p) - F*, then adaptive runs at the design with Gauss-Newton steps until the ordinary run
(``jaxfric run`` at the design) meets the target. It stops when every target is met within ``rtol``
(relative; the default 1e-3 is well inside the benchmarks' discretisation error), or when a step moves
no parameter by more than ``xtol`` relative. With more parameters than targets (R and H for one force)
the designs meeting the target form a curve; the solver's steps, scaled by the Jacobian's columns,
end at one of them near the start (the start is the designer's preference: set it with ``--set``).

**Out of reach.** A design that stops with the target not met is answered with the forces of the
adaptive runs at the corners of the bounds' box (``DesignResult.reachable``): the reachable range where
the force is monotone in each parameter, and the message says when the target lies outside it. A
target inside that range but not met (a force too rough in the parameters at a coarse mesh, or a local
minimum of the misfit) is reported as not met, with the closest design found.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import numbers
import time
from collections.abc import Callable

import numpy as np

from .. import scenes
from ..numerics.newton import NewtonOptions
from .fit import Problem, adaptive_history, check_arguments, check_bounds, local_stage, met, new_problem
from .fit_data import Measurement, observations, read_measurement, window_edges
from .params import parameterize

__all__ = ["DesignResult", "design", "write_design", "TARGET_POINTS"]

TARGET_POINTS = 401  # displacements at which a restraining-force design records the force along the draw


@dataclasses.dataclass
class DesignResult:
    """Outcome of :func:`design`.

    Attributes:
        scene, variant, algorithm, overrides, names: what was designed.
        params, start: {name: value} at the design and at the start; bounds: {name: (low, high)}.
        target: the restraining force F* (N/mm), or None for a target curve; steady_window: (a, b)
            (mm) of the restraining force (None for a curve); window: the windows' length (mm) of a
            target curve (None: every point, or a restraining force).
        targets: the fitted targets (the restraining force, or the target curve's points or window
            means); force: the design's restraining force (the mean over ``window``), or its
            observations of the target curve; start_value: the same at the start.
        sensitivity: {name: dF/dp} at the design (N/mm per unit of p; for a target curve, of its first
            observation), from the forward-mode Jacobian of the last replay.
        rtol: the relative tolerance on the target; converged: every target met within it (by the
            adaptive run at the design where the design re-planned); message: "target met", or why not.
        reachable: None, or {"low", "high" (N/mm), "corners": [{name: value, "force": N/mm or None}]}
            when the design stopped unmet: the forces at the corners of the bounds' box.
        displacement, target_force, design_force, start_force: the target and the drawing force at the
            design and at the start, at the target's displacements (for the figure).
        n_simulations, wall_s, iterations: as :class:`jaxfric.identification.fit.FitResult`'s.
    """

    scene: str
    variant: str
    algorithm: str
    overrides: dict
    names: tuple
    params: dict
    start: dict
    bounds: dict
    target: float | None
    steady_window: tuple[float, float] | None
    window: float | None
    targets: np.ndarray
    force: float | np.ndarray
    start_value: float | np.ndarray
    sensitivity: dict
    rtol: float
    converged: bool
    message: str
    reachable: dict | None
    displacement: np.ndarray
    target_force: np.ndarray
    design_force: np.ndarray
    start_force: np.ndarray
    n_simulations: int
    wall_s: float
    iterations: list


def design(scene: str, target, params, *, variant: str | None = None, algorithm: str = "lcp_ssn",
           overrides: dict | None = None, bounds: dict | None = None, window=None, rtol: float = 1e-3,
           newton: NewtonOptions | None = None, max_iter: int = 20, xtol: float = 1e-4, max_replans: int = 4,
           progress: bool = True, ready: Callable[[], None] | None = None) -> DesignResult:
    """The config fields ``params`` of ``scene`` (tool dimensions, the Nine's stroke, the clamping
    force, friction) for which the drawing force meets ``target`` (module docstring).

    Args:
        target: a restraining force (N/mm, a number), or a target curve (CSV path, mapping or
            :class:`~jaxfric.identification.fit_data.Measurement`).
        params: config field names; their start values are the variant's, then the overrides'.
        bounds: {name: (low, high)}, finite, for every parameter (a design outside the tool's
            admissible dimensions is not a design).
        window: for a restraining force, (a, b) (mm; default the scene's ``steady_window``); for a
            target curve, the windows' length (mm; None: every point), as ``fit``'s.
        rtol: the target is met when every observation is within rtol of it (relative to the
            largest target, for a curve).
        max_iter, xtol, max_replans, newton: as :func:`jaxfric.identification.fit.fit`'s.
        ready: called once the input is validated, before the first simulation.

    Raises ValueError (one line, naming the field) on bad input, before any simulation, and
    :class:`~jaxfric.identification.fit.FitError` when the simulation at the start fails.
    """
    t_start = time.perf_counter()
    names = check_arguments(params, algorithm, overrides, bounds, None, newton, xtol, max_iter, max_replans, 1, 1)
    if not (isinstance(rtol, numbers.Real) and 0 < rtol < 1):
        raise ValueError(f"field 'rtol' must be a number in (0, 1), got {rtol!r}")
    par = parameterize(scene, names, variant=variant, algorithm=algorithm, overrides=overrides)
    lo, hi = check_bounds(names, par.p0, bounds)
    unbounded = [n for n, a, b in zip(names, lo, hi) if not (math.isfinite(a) and math.isfinite(b))]
    if not bounds or unbounded:
        raise ValueError(f"field 'bounds' must give finite (low, high) for every designed parameter; missing for "
                         f"{(unbounded or list(names))[0]!r}")
    meas, edges, scalar = _targets(par.scene, target, window)
    problem = new_problem(par, meas, edges, lo, hi, algorithm=algorithm, overrides=overrides, newton=newton,
                          max_iter=max_iter, xtol=xtol, max_replans=max_replans, substeps=1, progress=progress,
                          rtol=float(rtol), task="design")
    observed = problem.observed
    if ready is not None:
        ready()
    best, _ = local_stage(problem, [par.p0.copy()])
    cur = best["cur"]
    done = met(cur["r"], observed, rtol)
    reachable, message = None, "target met"
    if not done:
        worst = int(np.argmax(np.abs(cur["r"])))
        message = (f"target not met within rtol = {rtol:g}: {observed[worst] + cur['r'][worst]:.6g} N/mm for "
                   f"{observed[worst]:.6g}" + (f" ({best['message']})" if best["message"] else
                                               " (steps below xtol: the closest design the model resolves)"))
    if scalar and not done:
        reachable = _corners(problem, edges)
        if reachable["low"] is not None and not reachable["low"] <= float(observed[0]) <= reachable["high"]:
            message = (f"target {float(observed[0]):.6g} N/mm is outside the range reachable within the bounds, "
                       f"[{reachable['low']:.6g}, {reachable['high']:.6g}] N/mm (adaptive runs at the corners of "
                       f"the bounds); {message}")
    jac = np.asarray(cur["jac"])
    return DesignResult(
        scene=scene, variant=par.scene.variant, algorithm=algorithm, overrides=dict(overrides or {}), names=names,
        params=dict(zip(names, np.asarray(cur["p"]).tolist())), start=dict(zip(names, par.p0.tolist())),
        bounds={n: (float(a), float(b)) for n, a, b in zip(names, lo, hi)},
        target=float(observed[0]) if scalar else None,
        steady_window=(float(edges[0]), float(edges[-1])) if scalar else None,
        window=None if scalar or edges is None else float(edges[1] - edges[0]),
        targets=observed, force=float(observed[0] + cur["r"][0]) if scalar else observed + cur["r"],
        start_value=float(best["start_obs"][0]) if scalar else best["start_obs"],
        target_force=meas.force,
        sensitivity=dict(zip(names, jac[0].tolist())), rtol=float(rtol), converged=done, message=message,
        reachable=reachable, displacement=meas.displacement, design_force=cur["pointwise"],
        start_force=best["start_force"], n_simulations=problem.simulations, wall_s=time.perf_counter() - t_start,
        iterations=best["iterations"])


def _targets(scene: scenes.Scene, target, window) -> tuple[Measurement, np.ndarray | None, bool]:
    """The targets as a measurement: (measurement, window edges or None, whether it is one restraining
    force). A restraining force becomes a constant curve at :data:`TARGET_POINTS` displacements over
    the whole draw with one window, ``window`` (default the scene's steady window)."""
    if isinstance(target, numbers.Real) and not isinstance(target, bool):
        target = float(target)
        if not (math.isfinite(target) and target > 0):
            raise ValueError(f"field 'target' must be a positive restraining force (N/mm), got {target!r}")
        stroke = float(getattr(scene.config, scenes.SCENES[scene.name].STROKE_FIELD))
        a, b = scene.steady_window if window is None else _window(window)
        if not 0 <= a < b <= stroke:
            raise ValueError(f"field 'window' = [{a:g}, {b:g}] mm must lie in the draw [0, {stroke:g}] mm, with a < b")
        x = np.linspace(stroke / TARGET_POINTS, stroke, TARGET_POINTS)
        meas = Measurement(displacement=x, force=np.full_like(x, float(target)), source=f"target {target:g} N/mm")
        return meas, np.array([a, b]), True
    meas = read_measurement(target)
    return meas, window_edges(meas.displacement, window, 1), False


def _window(window) -> tuple[float, float]:
    """(a, b) from a pair of numbers (ValueError naming the field ``window``)."""
    try:
        a, b = (float(v) for v in window)
    except (TypeError, ValueError):
        raise ValueError(f"field 'window' of a restraining-force target must be a pair (a, b) in mm, got "
                         f"{window!r}") from None
    return a, b


def _corners(problem: Problem, edges: np.ndarray) -> dict:
    """The restraining force of the adaptive runs at the corners of the bounds' box (None where a run
    fails): {"low", "high" (None when every run fails), "corners"}."""
    problem.say(f"design {problem.scene}: target not met; the forces at the {2 ** len(problem.names)} corners "
                "of the bounds")
    corners = []
    for p in itertools.product(*zip(problem.lo, problem.hi)):
        history, _ = adaptive_history(problem, np.array(p))
        force = None if history is None else float(observations(history, problem.meas.displacement, edges)[0])
        corners.append({**dict(zip(problem.names, p)), "force": force})
    forces = [c["force"] for c in corners if c["force"] is not None]
    return {"low": min(forces) if forces else None, "high": max(forces) if forces else None, "corners": corners}


def write_design(result: DesignResult, out: str) -> dict:
    """Write ``design.json``, ``design_history.csv`` and ``design.png`` into ``out``; returns the JSON dict."""
    import csv
    import json
    import os

    from .fit_result import _json_number, _override_text

    os.makedirs(out, exist_ok=True)
    scalar = result.target is not None
    summary = {
        "scene": result.scene, "variant": result.variant, "algorithm": result.algorithm,
        "overrides": {k: _override_text(k, v) for k, v in result.overrides.items()},
        "params": result.params, "start": result.start,
        "bounds": {k: [a, b] for k, (a, b) in result.bounds.items()},
        "target": result.target, "steady_window": result.steady_window, "window": result.window,
        "force": result.force if scalar else None, "start_force": result.start_value if scalar else None,
        "rel_error": (result.force / result.target - 1) if result.target is not None else None,
        "sensitivity": {k: _json_number(v) for k, v in result.sensitivity.items()},
        "rtol": result.rtol, "converged": result.converged, "message": result.message,
        "reachable": result.reachable, "n_simulations": result.n_simulations, "wall_s": result.wall_s,
    }
    with open(os.path.join(out, "design.json"), "w") as f:
        json.dump(summary, f, indent=2)
    with open(os.path.join(out, "design_history.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(result.iterations[0]))
        w.writeheader()
        w.writerows(result.iterations)
    _plot(result, os.path.join(out, "design.png"))
    return summary


def _plot(result: DesignResult, path: str) -> None:
    """``design.png``: the drawing force at the start and at the design with the target; the
    parameters per accepted simulation."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
    x = result.displacement
    ax.plot(x, result.start_force, "--", color="tab:blue", lw=1,
            label="start: " + ", ".join(f"{k} = {v:.4g}" for k, v in result.start.items()))
    ax.plot(x, result.design_force, "-", color="tab:red", lw=1.5,
            label="design: " + ", ".join(f"{k} = {v:.5g}" for k, v in result.params.items()))
    if result.target is not None and result.steady_window is not None:
        a, b = result.steady_window
        ax.axvspan(a, b, color="0.9", zorder=0, label=f"window [{a:g}, {b:g}] mm")
        ax.hlines(result.target, a, b, color="k", lw=1.2, label=f"target {result.target:.4g} N/mm")
        ax.hlines(result.force, a, b, color="tab:red", ls=":", lw=1.2, label=f"design's mean {result.force:.4g} N/mm")
    else:
        ax.plot(x, result.target_force, ".", ms=3, color="0.4", label="target curve")
    ax.set_xlabel("drawing displacement (mm)")
    ax.set_ylabel("drawing force (N/mm)")
    ax.set_title(f"{result.scene} {result.variant}: drawing force at the start and at the design", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    its = [row for row in result.iterations if row["accepted"]]
    for name in result.names:
        bx.plot([row["iteration"] for row in its], [row[name] for row in its], "o-", ms=4, label=name)
    bx.set_xlabel("simulation of the design (frozen-sequence replays, then adaptive runs)")
    bx.set_ylabel("parameter value")
    bx.set_title(f"{result.n_simulations} simulations, {result.wall_s:.1f} s"
                 + ("" if result.converged else f" (not met: {result.message[:60]})"), fontsize=10)
    bx.legend(fontsize=8)
    bx.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
