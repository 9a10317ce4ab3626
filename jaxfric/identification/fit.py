"""Identification of scene parameters from a measured drawing-force curve.

    >>> from jaxfric.identification.fit import fit, write_fit
    >>> res = fit("nine", "measured.csv", ["mu"], overrides={"mesh": "40x2", "U_draw": 10})
    >>> res.params, res.stderr            # {"mu": 0.1700...}, {"mu": 1.2e-3}
    >>> write_fit(res, "fits/nine")       # fit.json, fit.png, fit_history.csv

**The measurement.** A CSV (or a mapping of arrays) with at least the columns ``drawing_displacement``
(mm) and ``drawing_force`` (N/mm). Rows at displacement <= 0 are dropped (before drawing the force is
not a drawing force, and a ``history.csv`` written by ``jaxfric run`` carries its clamping rows there);
the remaining displacements must increase strictly and lie inside the simulated stroke.

**The model of the measurement.** The simulated drawing force, linearly interpolated at the measured
displacements, along a *frozen step sequence*: the accepted steps of an adaptive run at the current
parameters become the nominal steps of the runs that follow (:func:`jaxfric.fem.loading.with_steps`). A
frozen sequence makes the simulated curve a smooth function of the parameters, where an adaptive run
would change its steps, and with them its force by the discretisation noise, whenever the parameters
move. A frozen step that fails at other parameters is still cut by the step controller (only there),
since Newton at the edge of its convergence region, where the controller leaves the accepted steps,
does not survive a change of 1e-3 in mu on the Nine test. Every such cut is a small jump of the curve
in the parameters, so the replays allow more Newton iterations per step than the planning run
(``REPLAY_ITERATIONS``, against the scene's 25): on the Nine test at 100 x 2 (mu, R1) moved from (0.12,
5.2) to (0.134, 5.243) cut 15 frozen steps with 25 iterations and 5 with 60; at (0.17, 5.5), 24 and
11. When the fit has converged on one sequence, the adaptive run is
repeated at the optimum and the fit continues on the new sequence until the sequence no longer changes,
so the answer is the parameters at which the ordinary adaptive run (``jaxfric run``) reproduces the
data best.

**The optimiser.** Levenberg-Marquardt (Gauss-Newton with Marquardt's scaled damping) on the residuals
r = F_sim(x_k; p) - F_k, with the Jacobian from forward-mode differentiation through the whole loading
path (one ``jax.jacfwd``: the primal plus n tangents per simulation). For a handful of parameters and a
few hundred smooth residuals this converges quadratically near the optimum in a few simulations, where
L-BFGS (gradient-only) would need many more, each costing a full simulation; and J^T J gives the
Gauss-Newton covariance for free. Bounds are kept by projecting every trial point on the box
(``optax.projections.projection_box``); updates are applied with ``optax.apply_updates``.

**Uncertainty.** With independent measurement errors of equal variance, cov(p) = s^2 (J^T J)^-1 with
s^2 = |r|^2 / (m - n) at the optimum; ``stderr`` is the square root of its diagonal and the 95 %
interval is p +/- t_{0.975, m-n} stderr (linearised, so it assumes the model is nearly linear in p over
the interval, which holds for the small intervals of a well-posed fit).

The measurement and the fitted observations are :mod:`jaxfric.identification.fit_data`, the compiled curve along a
frozen sequence :mod:`jaxfric.identification.fit_curve`, the global stage's grid and interpolated misfit
:mod:`jaxfric.identification.fit_global`, the result and its files :mod:`jaxfric.identification.fit_result`, and what
fits keep between calls :data:`CURVES` and :data:`GRID_RUNS`; this module is the driver.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ..contact.formulations import ALGORITHMS, DIFFERENTIABLE_ALGORITHMS
from ..numerics._checks import check_int, check_positive
from ..numerics.lru import LRU
from ..numerics.newton import NewtonOptions
from ..numerics.results import Result, describe
from .fit_curve import Curve, refined_plan
from .fit_data import Measurement, bin_means, curve_columns, observations, read_measurement, window_edges
from .fit_global import grid_axes, surrogate_minima
from .fit_result import FitResult, write_fit
from .params import Parameterization, adaptive_run, parameterize

__all__ = ["Measurement", "FitResult", "FitError", "read_measurement", "bin_means", "fit", "write_fit"]

# Kept between fits: repeated fits of one model (the noise draws of experiments/identify_nine.py: the
# same scene, parameters, grid and measured displacements, other forces) reuse them.
# Compiled curves (:class:`jaxfric.identification.fit_curve.Curve`: a jitted forward-mode Jacobian of a whole replay,
# one compilation each) by model, step sequence, measured displacements, windows and substeps.
CURVES: LRU = LRU(8)
# The global stage's adaptive runs by model and grid: per grid point, the displacement and force
# columns of its history (None: the run failed). They do not depend on the measured forces, so fits of
# other measurements on the same grid cost no simulation; a grid holds up to 10,000 runs.
GRID_RUNS: LRU = LRU(4)



class FitError(RuntimeError):
    """The simulation at the start values fails: the fit cannot begin (not an input error)."""


def fit(scene: str, data, params, *, variant: str | None = None, algorithm: str = "penalty",
        overrides: dict | None = None, bounds: dict | None = None, window: float | None = None,
        newton: NewtonOptions | None = None, max_iter: int = 30, xtol: float = 1e-7,
        max_replans: int = 4, substeps: int = 1, grid: dict | None = None, starts: int = 1,
        progress: bool = True, ready: Callable[[], None] | None = None) -> FitResult:
    """Fit the config fields ``params`` of ``scene`` to the measured drawing-force curve ``data``.

    Args:
        scene, variant, algorithm, overrides: the scene, as for :func:`jaxfric.scenes.make`; the
            start values of the parameters are the config's (variant, then overrides).
        data: CSV path, mapping or :class:`Measurement` (see :func:`read_measurement`).
        params: names of config fields to fit (see :func:`jaxfric.identification.params.parameterize`).
        bounds: {name: (low, high)}; default [0, inf) for every parameter.
        window: None: fit the force at every measured point. A length (mm): fit the mean force over
            consecutive windows of about that length, measured and simulated alike. On a coarse mesh
            the simulated force ripples as nodes pass over a curved tool (node spacing = period); a
            window of a few node spacings fits the trend, not the ripple.
        max_iter: Levenberg-Marquardt trials (accepted or not) per step sequence; when they run out,
            the fit re-plans at the best point so far (while ``max_replans`` allows).
        xtol: converged when an accepted step changes every p_i by at most xtol (|p_i| + xtol).
        max_replans: adaptive runs at the optimum, to settle the step sequence. 0: fit on the
            sequence planned at the start values (cheaper; the answer then carries the difference
            between that sequence and the one an adaptive run at the optimum would take).
        substeps: replay every planned step as this many equal steps (1: as planned). Smaller
            replayed steps converge at parameter values further from the plan's without being cut,
            and every cut is a small jump of the fitted curve; the replays cost that many times more,
            and the fitted model is then the run with the finer steps.
        grid: {name: increasing values}: a global stage before Levenberg-Marquardt. The adaptive run
            at every point of the grid (the product of the axes; a fitted parameter the grid does not
            name stays at its start value), the observations interpolated multilinearly between the
            points, and Levenberg-Marquardt started from the minimum of the interpolated misfit
            instead of the start values. For misfits with several local minima, as where two
            parameters compensate each other and the model's discretisation ripples along the valley
            they leave (mu and R1 on the Nine test). The runs are kept for later fits of the same
            scene and grid (other measurements, e.g. noise draws, cost no simulation;
            :data:`GRID_RUNS`).
        starts: with a grid, Levenberg-Marquardt from up to this many local minima of the
            interpolated misfit (lowest first, distinct basins:
            :func:`jaxfric.identification.fit_global.surrogate_minima`); the fit with the lowest misfit is the result
            (its ``start``), the others are kept in ``local_fits``. Where the interpolation error of the grid is larger
            than the misfit differences between basins, the lowest interpolated minimum need not be in the lowest basin.
        ready: called once the input is validated, before the first simulation (the command line
            makes its output directory there, so that refused input leaves none).

    Raises ValueError (one line, naming the field) on bad input, before any simulation, and
    :class:`FitError` when the simulation at the start values fails.
    """
    t_start = time.perf_counter()
    names = _check_arguments(params, algorithm, overrides, bounds, grid, newton, xtol, max_iter, max_replans,
                             substeps, starts)
    problem, axes = _prepare(scene, data, names, variant=variant, algorithm=algorithm, overrides=overrides,
                             bounds=bounds, window=window, newton=newton, max_iter=max_iter, xtol=xtol,
                             max_replans=max_replans, substeps=substeps, grid=grid, starts=starts,
                             progress=progress)
    if ready is not None:
        ready()
    starts_at, grid_rows = ([problem.par.p0.copy()], []) if axes is None else _global_stage(problem, axes, starts)
    best, outcomes = _local_stage(problem, starts_at)
    return _result(problem, best, outcomes, grid_rows, t_start)


@dataclasses.dataclass
class _Problem:
    """One call of :func:`fit`: the parameterised scene, the measurement and its observations, the
    options of the local stage, and the counts of simulations and re-plans so far (the only fields
    that change).

    Attributes:
        scene, algorithm, overrides: as given to :func:`fit`; names: the fitted parameters.
        par: the parameterisation; meas: the measurement; edges: window edges (mm) or None;
            observed: the measured observations (force at every point, or window means).
        lo, hi: (n,) bounds; project: the projection of a point on them.
        newton, max_iter, xtol, max_replans, substeps: as given to :func:`fit`.
        model_key: what the simulations depend on besides the parameters (the key of the caches).
        say: prints a progress line (or nothing).
    """

    scene: str
    algorithm: str
    overrides: dict
    names: tuple
    par: Parameterization
    meas: Measurement
    edges: np.ndarray | None
    observed: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    project: Callable
    newton: NewtonOptions | None
    max_iter: int
    xtol: float
    max_replans: int
    substeps: int
    model_key: tuple
    say: Callable[[str], None]
    simulations: int = 0
    replans: int = 0


def _check_arguments(params, algorithm, overrides, bounds, grid, newton, xtol, max_iter, max_replans, substeps,
                     starts) -> tuple:
    """Check the arguments of :func:`fit` that need neither the scene nor the measurement; returns
    the fitted names as a tuple (ValueError naming the field)."""
    if isinstance(params, str):
        params = (params,)
    if not (isinstance(params, (tuple, list)) and all(isinstance(n, str) for n in params)):
        raise ValueError(f"field 'params' must be a name or a sequence of names of config fields, got {params!r}")
    if algorithm in ALGORITHMS and algorithm not in DIFFERENTIABLE_ALGORITHMS:
        raise ValueError(f"field 'algorithm' = {algorithm!r} cannot be fitted: its formulation has no derivatives; "
                         f"choose one of {', '.join(DIFFERENTIABLE_ALGORITHMS)}")
    for name, mapping in (("overrides", overrides), ("bounds", bounds), ("grid", grid)):
        if mapping is not None and not isinstance(mapping, Mapping):
            raise ValueError(f"field {name!r} must be a dict keyed by config field, got {mapping!r}")
    if newton is not None and not isinstance(newton, NewtonOptions):
        raise ValueError(f"field 'newton' must be a NewtonOptions or None, got {newton!r}")
    check_positive("xtol", xtol)
    for name, value, least in (("max_iter", max_iter, 1), ("max_replans", max_replans, 0), ("substeps", substeps, 1),
                               ("starts", starts, 1)):
        check_int(name, value, least)
    return tuple(params)


def _prepare(scene: str, data, names: tuple, *, variant, algorithm, overrides, bounds, window, newton, max_iter,
             xtol, max_replans, substeps, grid, starts, progress) -> tuple[_Problem, list | None]:
    """Read and check the measurement, build the parameterised scene and check the bounds and the
    grid against it: the :class:`_Problem` and the grid's axes (None without a grid). ValueError
    naming the field; nothing is simulated."""
    meas = read_measurement(data)
    if meas.displacement.size < len(names):
        raise ValueError(f"measurement {meas.source!r} has {meas.displacement.size} point(s) at displacement > 0, "
                         f"fewer than the {len(names)} parameter(s)")
    if starts > 1 and not grid:
        raise ValueError(f"field 'starts' = {starts} needs a grid (the starts are minima of the global stage)")
    edges = window_edges(meas.displacement, window, len(names))
    observed = meas.force if edges is None else bin_means(meas.displacement, meas.force, edges)
    par = parameterize(scene, names, variant=variant, algorithm=algorithm, overrides=overrides)
    lo, hi = _bounds(names, par.p0, bounds)
    axes = grid_axes(grid, names, lo, hi) if grid else None
    project = jax.jit(lambda p: optax.projections.projection_box(p, jnp.asarray(lo), jnp.asarray(hi)))
    say = (lambda text: print(text, file=sys.stderr, flush=True)) if progress else (lambda text: None)
    model_key = (scene, names, par.scene.variant, algorithm, repr(sorted((overrides or {}).items())), newton)
    problem = _Problem(scene=scene, algorithm=algorithm, overrides=dict(overrides or {}), names=names, par=par,
                       meas=meas, edges=edges, observed=observed, lo=lo, hi=hi, project=project, newton=newton,
                       max_iter=max_iter, xtol=xtol, max_replans=max_replans, substeps=substeps,
                       model_key=model_key, say=say)
    return problem, axes


def _bounds(names, p0, bounds) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) per fitted parameter: ``bounds`` where given, else [0, inf); each must hold its
    start value ``p0`` (ValueError naming the field ``bounds``)."""
    lo, hi = np.zeros(len(names)), np.full(len(names), np.inf)
    bounds = dict(bounds or {})
    unknown = [k for k in bounds if k not in names]
    if unknown:
        raise ValueError(f"field 'bounds' names {unknown[0]!r}, which is not a fitted parameter "
                         f"({', '.join(names)})")
    for i, name in enumerate(names):
        if name in bounds:
            try:
                a, b = (float(v) for v in bounds[name])
            except (TypeError, ValueError):
                raise ValueError(f"field 'bounds' of {name!r} must be a pair (low, high) of numbers, got "
                                 f"{bounds[name]!r}") from None
            if math.isnan(a) or math.isnan(b) or not a < b:
                raise ValueError(f"field 'bounds' of {name!r} must satisfy low < high, got {bounds[name]!r}")
            lo[i], hi[i] = a, b
        if not lo[i] <= p0[i] <= hi[i]:
            raise ValueError(f"field 'bounds' of {name!r} = [{lo[i]:g}, {hi[i]:g}] excludes the start value "
                             f"{p0[i]:g}; set the start with --set {name}=VALUE")
    return lo, hi


# ---- the global stage ------------------------------------------------------------------------------

def _global_stage(problem: _Problem, axes: list, starts: int) -> tuple[list, list]:
    """Adaptive runs on the grid (a parameter the grid does not name at its start value), then the
    starts of the local stage at up to ``starts`` minima of the interpolated misfit: (starts, the
    grid's rows). Raises :class:`FitError` when no run of the grid completes."""
    names, say = problem.names, problem.say
    axes = [np.array([problem.par.p0[i]]) if a is None else a for i, a in enumerate(axes)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(names))
    obs, grid_rows = _grid_runs(problem, axes, points)
    if not any(row["converged"] for row in grid_rows):
        raise FitError("no run of the global stage completes: no start for the fit")
    starts_at = []
    for best, best_cost in surrogate_minima(axes, obs, problem.observed, starts):
        it = iter(best)
        starts_at.append(np.array([next(it) if a.size > 1 else a[0] for a in axes]))
        if not math.isfinite(best_cost):  # every cell has a failed corner: the best point run
            j = int(np.argmin([row["cost"] for row in grid_rows]))
            starts_at[-1] = points[j].copy()
        say(f"  global stage: interpolated misfit {best_cost:.6g} at "
            + ", ".join(f"{n} = {v:.6g}" for n, v in zip(names, starts_at[-1])))
    return starts_at, grid_rows


def _grid_runs(problem: _Problem, axes: list, points: np.ndarray) -> tuple[np.ndarray, list]:
    """The adaptive run at every grid point (kept in :data:`GRID_RUNS`): their
    observations (NaN where a run failed) and a row per point (parameters, misfit, converged)."""
    names, observed = problem.names, problem.observed
    runs = GRID_RUNS.get((*problem.model_key, tuple(a.tobytes() for a in axes)), dict)
    problem.say(f"fit {problem.scene}: global stage, adaptive runs at {len(points)} grid points")
    obs = np.full((len(points), observed.size), np.nan)
    rows = []
    for j, p in enumerate(points):
        if j not in runs:
            res = adaptive_run(problem.par, p, problem.newton)
            problem.simulations += 1
            runs[j] = curve_columns(res.history) if res.converged else None
        grid_run = runs[j]
        if grid_run is not None:
            obs[j] = observations(grid_run, problem.meas.displacement, problem.edges)
        r = obs[j] - observed
        rows.append({**dict(zip(names, p.tolist())), "cost": 0.5 * float(r @ r) if grid_run is not None else math.inf,
                     "converged": grid_run is not None})
        problem.say(f"  grid point {j + 1}/{len(points)}: misfit {rows[-1]['cost']:.6g} at "
                    + ", ".join(f"{n} = {v:.6g}" for n, v in zip(names, p)))
    return obs, rows


# ---- the local stage: Levenberg-Marquardt on frozen step sequences ------------------------------------

def _local_stage(problem: _Problem, starts_at: list) -> tuple[dict, list]:
    """Levenberg-Marquardt from every start (:func:`_local_fit`): the outcome of the lowest misfit
    and all outcomes, in the order of the starts. A start other than the first that cannot be
    simulated is left out; the first one's :class:`FitError` is the fit's."""
    outcomes = []
    for number, p_start in enumerate(starts_at):
        try:
            outcomes.append(_local_fit(problem, p_start, number, len(starts_at)))
        except FitError as failure:  # a later start may still fit; the first one's failure is the fit's
            if number == 0:
                raise
            problem.say(f"  start {number + 1} abandoned: {failure}")
    best = min(outcomes, key=lambda o: o["cur"]["cost"])
    if len(starts_at) > 1:
        problem.say(f"  best of {len(outcomes)} starts: start {best['number'] + 1}, misfit {best['cur']['cost']:.6g}")
    return best, outcomes


def _local_fit(problem: _Problem, p_start: np.ndarray, number: int, count: int) -> dict:
    """Levenberg-Marquardt from ``p_start`` (start ``number`` of ``count``) on the step sequence
    planned there, re-planning at the optimum until the sequence settles (module docstring).

    Returns {cur (the last accepted point, :func:`_evaluate`), converged, message, p_start,
    start_force, iterations (a row per trial), number}. Raises :class:`FitError` when the start
    values do not simulate.
    """
    names = problem.names
    problem.say(f"fit {problem.scene}: planning the step sequence at "
                + ", ".join(f"{n} = {v:g}" for n, v in zip(names, p_start)))
    curve, failure = _planned(problem, p_start)
    if curve is None:
        raise FitError(f"the simulation at the start values does not complete: {failure}")
    cur = _evaluate(problem, curve, p_start.copy())
    if not math.isfinite(cur["cost"]):
        raise FitError(f"the replayed step sequence fails at the start values ({describe(cur['code'])})")
    start_force = cur["pointwise"]
    iterations = [{"iteration": 0, "accepted": True, "cost": cur["cost"], "damping": 1e-3,
                   **dict(zip(names, cur["p"].tolist()))}]
    replans = 0
    while True:
        cur, settled, message = _trials(problem, curve, cur, iterations)
        again, converged, message = _replan(problem, curve, cur, settled, message, replans)
        if again is None:
            break
        replans += 1
        problem.replans += 1
        problem.say(f"  re-planned the step sequence at the optimum ({len(again.times)} steps, was {len(curve.times)})")
        curve = again
        cur = _evaluate(problem, curve, cur["p"])
        if not math.isfinite(cur["cost"]):
            message = f"the re-planned step sequence fails at the fitted values ({describe(cur['code'])})"
            break
    if count > 1:
        for row in iterations:
            row["start"] = number + 1
    return {"cur": cur, "converged": converged, "message": message, "p_start": p_start,
            "start_force": start_force, "iterations": iterations, "number": number}


def _trials(problem: _Problem, curve: Curve, cur: dict, iterations: list) -> tuple[dict, bool, str]:
    """Up to ``max_iter`` Levenberg-Marquardt trials on one step sequence from ``cur`` (damping from
    1e-3; a row per trial appended to ``iterations``, numbered on from its last). Returns the last
    accepted point, whether the trials settled (a step below ``xtol``, a zero misfit, or the damping
    beyond 1e12, which also gives a message) and that message ("" otherwise)."""
    names, damping = problem.names, 1e-3
    for _ in range(problem.max_iter):
        k = len(iterations)
        dp = _lm_step(cur["jac"], cur["r"], damping)
        trial = np.asarray(problem.project(optax.apply_updates(jnp.asarray(cur["p"]), jnp.asarray(dp))))
        new = _evaluate(problem, curve, trial)
        accepted = new["cost"] <= cur["cost"]
        iterations.append({"iteration": k, "accepted": bool(accepted), "cost": new["cost"], "damping": damping,
                           **dict(zip(names, trial.tolist()))})
        problem.say(f"  trial {k}: misfit {new['cost']:.6g} ({'accepted' if accepted else 'rejected'}, "
                    f"{new['cuts']} cutbacks) at " + ", ".join(f"{n} = {v:.10g}" for n, v in zip(names, trial)))
        if accepted:
            moved = np.abs(trial - cur["p"])
            cur, damping = new, max(damping / 3.0, 1e-9)
            if np.all(moved <= problem.xtol * (np.abs(trial) + problem.xtol)) or cur["cost"] == 0.0:
                return cur, True, ""
        else:
            damping *= 10.0
            if damping > 1e12:
                return cur, True, "no decrease of the misfit even with very small steps (damping > 1e12)"
    return cur, False, ""


def _replan(problem: _Problem, curve: Curve, cur: dict, settled: bool, message: str,
            replans: int) -> tuple[Curve | None, bool, str]:
    """After the trials on ``curve`` (``replans`` re-plans so far): the curve of the adaptive run at
    the optimum when the fit goes on there, else None, whether it converged and why it stopped."""
    # Trials that stall on one sequence (a replay that cuts a step at some trial points moves the
    # curve by a small jump, which Levenberg-Marquardt cannot step over) still moved the point:
    # re-plan there while re-plans are left.
    stalled = not settled
    if stalled and replans >= problem.max_replans:
        return None, False, f"no convergence in {problem.max_iter} trials on this step sequence"
    if message:
        return None, False, message
    if problem.max_replans == 0:
        return None, True, ""
    # Re-plan at the optimum: the answer must hold for the adaptive run at these values.
    again, failure = _planned(problem, cur["p"])
    if again is None:
        return None, False, f"the adaptive run at the fitted values does not complete: {failure}"
    if again.same_plan(curve):
        return None, not stalled, (f"no convergence in {problem.max_iter} trials on the step sequence of the "
                                   "adaptive run at the fitted values" if stalled else "")
    if replans >= problem.max_replans:
        return None, False, f"the step sequence still changed after {problem.max_replans} re-plans"
    return again, False, ""


def _planned(problem: _Problem, p: np.ndarray) -> tuple[Curve | None, str]:
    """A curve on the step sequence of the adaptive run at ``p`` (compiled once per sequence: kept in
    :data:`CURVES`); None and the reason if the run fails. Raises ValueError when
    the measurement reaches beyond the simulated stroke."""
    res = adaptive_run(problem.par, p, problem.newton)
    problem.simulations += 1
    if not res.converged:
        return None, res.message
    history, meas, edges = res.history, problem.meas, problem.edges
    top = float(np.max(history["drawing_displacement"]))
    if meas.displacement[-1] > top * (1 + 1e-12):
        raise ValueError(f"measurement {meas.source!r} reaches drawing_displacement {meas.displacement[-1]:g} "
                         f"mm, beyond the simulated stroke {top:g} mm (raise the scene's stroke field)")
    key = (*problem.model_key, history["time"].tobytes(), meas.displacement.tobytes(),
           None if edges is None else edges.tobytes(), problem.substeps)
    curve = CURVES.get(key, lambda: Curve(problem.par, refined_plan(history, problem.substeps), meas.displacement,
                                          edges, problem.newton))
    return curve, ""


def _evaluate(problem: _Problem, curve: Curve, p: np.ndarray) -> dict:
    """The curve at ``p``: {p, r (residuals), jac, pointwise (force at the measured points), cost
    (|r|^2 / 2; inf where the replay fails or r is not finite), code, cuts (cutbacks)}."""
    obs, jac, pointwise, code, cuts = curve(p)
    problem.simulations += 1
    r = obs - problem.observed
    cost = 0.5 * float(r @ r) if code == Result.SUCCESS and np.all(np.isfinite(r)) else math.inf
    return {"p": p, "r": r, "jac": jac, "pointwise": pointwise, "cost": cost, "code": code, "cuts": cuts}


def _lm_step(jac, r, damping):
    """Levenberg-Marquardt step: (J^T J + damping diag(J^T J)) dp = -J^T r."""
    a = jac.T @ jac
    d = np.diag(a).copy()
    d[d <= 0] = 1.0
    return np.linalg.solve(a + damping * np.diag(d), -jac.T @ r)


# ---- the result --------------------------------------------------------------------------------------

def _result(problem: _Problem, best: dict, outcomes: list, grid_rows: list, t_start: float) -> FitResult:
    """The :class:`FitResult` of the best local fit with its Gauss-Newton uncertainty (module
    docstring), every local fit (``outcomes``) and the global stage's rows; ``t_start``: when
    :func:`fit` was called (``time.perf_counter``)."""
    from scipy.stats import t as student_t

    names, cur = problem.names, best["cur"]
    p, r, jac = cur["p"], cur["r"], cur["jac"]
    m, n = len(r), len(names)
    s2 = 2.0 * cur["cost"] / max(m - n, 1)
    try:
        cov = s2 * np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        cov = np.full((n, n), np.inf)
    err = np.sqrt(np.maximum(np.diag(cov), 0.0))
    q = float(student_t.ppf(0.975, max(m - n, 1)))
    return FitResult(
        scene=problem.scene, variant=problem.par.scene.variant, algorithm=problem.algorithm,
        overrides=problem.overrides, names=names, params=dict(zip(names, p.tolist())),
        stderr=dict(zip(names, err.tolist())),
        ci95={nm: (float(v - q * e), float(v + q * e)) for nm, v, e in zip(names, p, err)},
        start=dict(zip(names, best["p_start"].tolist())),
        bounds={nm: (float(a), float(b)) for nm, a, b in zip(names, problem.lo, problem.hi)},
        window=None if problem.edges is None else float(problem.edges[1] - problem.edges[0]),
        covariance=cov, residual_rms=float(np.sqrt(np.mean(r**2))), cost=cur["cost"], n_points=m,
        n_simulations=problem.simulations, n_replans=problem.replans, wall_s=time.perf_counter() - t_start,
        converged=best["converged"], message=best["message"] or "converged",
        iterations=[row for o in outcomes for row in o["iterations"]], measurement=problem.meas,
        fitted_force=cur["pointwise"], start_force=best["start_force"], grid=grid_rows,
        local_fits=[{"number": o["number"] + 1, "start": dict(zip(names, o["p_start"].tolist())),
                     "end": dict(zip(names, o["cur"]["p"].tolist())), "cost": o["cur"]["cost"],
                     "converged": o["converged"], "message": o["message"] or "converged"} for o in outcomes])
