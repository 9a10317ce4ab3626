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
11. When the fit has converged on one sequence, the adaptive run is repeated at the optimum: where it
takes other steps, its misfit and the last Jacobian (sequences a few steps apart have nearly the same
Jacobian) give a Gauss-Newton step, and adaptive runs follow these steps until one moves no parameter
by more than the stopping tolerance (below). Each adaptive run reuses one compiled program; only when
``max_replans`` such runs do not settle is the fit repeated on the last run's sequence, whose curve
reuses the first one's compiled program where each phase's steps stay within the same power of two
(the sequence is data of the program: :func:`jaxfric.identification.params.plan_steps`). The answer is
then the parameters at which the ordinary adaptive run (``jaxfric run``) reproduces the data best, to the
accuracy the data resolve.

**The optimiser.** ``scipy.optimize.least_squares`` (trust-region reflective, bounded) on the residuals r =
F_sim(x_k; p) - F_k, with the Jacobian from forward-mode differentiation through the whole loading path (the
primal plus n tangents per simulation: :func:`~jaxfric.identification.fit_curve.forward_jacobian`). For a
handful of parameters and a few hundred smooth residuals this converges quadratically near the optimum in a
few simulations, where L-BFGS (gradient-only) would need many more, each costing a full simulation; and J^T
J gives the Gauss-Newton covariance for free. **Stopping**: when the Gauss-Newton step from the current
point moves every parameter by at most ``STOP_FRACTION`` (a tenth) of its standard error there (never less
than ``xtol`` relative), or when the solver's trial steps shrink below that without decreasing the misfit
(the replays' discretisation noise, a few 1e-5 in mu on the Nine at 100 x 2, which no step of the optimiser
can resolve): a further change could not be told apart from the uncertainty the fit reports.

**Uncertainty.** With independent measurement errors of equal variance, cov(p) = s^2 (J^T J)^-1 with
s^2 = |r|^2 / (m - n) at the optimum; ``stderr`` is the square root of its diagonal and the 95 %
interval is p +/- t_{0.975, m-n} stderr (linearised, so it assumes the model is nearly linear in p over
the interval, which holds for the small intervals of a well-posed fit). On data the model did not make,
r also holds the model's misfit of the curve, which s^2 counts as noise, and p carries the model's
bias, which the interval does not: over 200 noisy Nine curves from the reference discretisation, fitted
at 100 x 2, the standard error of mu alone was 13 to 16 times the fits' scatter and its interval held
the truth in every case, the joint intervals of (mu, R1) in 39 and 40 % (``experiments/calibrate_intervals.py``,
docs/results.md, coverage of the intervals).

The measurement and the fitted observations are :mod:`jaxfric.identification.fit_data`, the compiled curve along a
frozen sequence :mod:`jaxfric.identification.fit_curve`, the global stage's grid and interpolated misfit
:mod:`jaxfric.identification.fit_global`, the model's discretisation error carried into the parameters
(``model_error``) :mod:`jaxfric.identification.fit_model_error`, the result and its files
:mod:`jaxfric.identification.fit_result`, and what
fits keep between calls :data:`CURVES` and :data:`GRID_RUNS`; this module is the driver.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Callable, Mapping

import numpy as np

from ..contact.formulations import ALGORITHMS, DIFFERENTIABLE_ALGORITHMS
from ..numerics._checks import check_int, check_positive
from ..numerics.lru import LRU
from ..numerics.newton import NewtonOptions
from ..numerics.results import Result, describe
from ..scenes._common import POLYNOMIAL_TERMS
from . import fit_model_error
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


def fit(scene: str, data, params, *, variant: str | None = None, algorithm: str = "lcp_ssn",
        overrides: dict | None = None, bounds: dict | None = None, window: float | None = None,
        newton: NewtonOptions | None = None, max_iter: int = 30, xtol: float = 1e-7,
        max_replans: int = 4, substeps: int = 1, grid: dict | None = None, starts: int = 1,
        model_error=(), progress: bool = True, ready: Callable[[], None] | None = None) -> FitResult:
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
        max_iter: least-squares trials (simulations, accepted or not) per step sequence; when they run
            out, the fit stops unconverged.
        xtol: the smallest stopping tolerance, relative: a step of p_i by at most xtol (|p_i| + xtol)
            ends the fit even where the standard errors vanish (noise-free data from the model itself;
            module docstring, stopping).
        max_replans: adaptive runs at the optimum, to settle the step sequence (module docstring). 0:
            fit on the sequence planned at the start values (cheaper; the answer then carries the
            difference between that sequence and the one an adaptive run at the optimum would take).
        substeps: replay every planned step as this many equal steps (1: as planned). Smaller
            replayed steps converge at parameter values further from the plan's without being cut,
            and every cut is a small jump of the fitted curve; the replays cost that many times more,
            and the fitted model is then the run with the finer steps.
        grid: {name: increasing values}: a global stage before the least-squares fit. The adaptive run
            at every point of the grid (the product of the axes; a fitted parameter the grid does not
            name stays at its start value), the observations interpolated multilinearly between the
            points, and the least-squares fit started from the minimum of the interpolated misfit
            instead of the start values. For misfits with several local minima, as where two
            parameters compensate each other and the model's discretisation ripples along the valley
            they leave (mu and R1 on the Nine test). The runs are kept for later fits of the same
            scene and grid (other measurements, e.g. noise draws, cost no simulation;
            :data:`GRID_RUNS`).
        starts: with a grid, least squares from up to this many local minima of the
            interpolated misfit (lowest first, distinct basins:
            :func:`jaxfric.identification.fit_global.surrogate_minima`); the fit with the lowest misfit is the result
            (its ``start``), the others are kept in ``local_fits``. Where the interpolation error of the grid is larger
            than the misfit differences between basins, the lowest interpolated minimum need not be in the lowest basin.
        model_error: components of the model's discretisation error to carry into the result
            ("step", "mesh", "layers"; :mod:`jaxfric.identification.fit_model_error`): one adaptive run
            at the fitted values per component, with that discretisation refined; the result's
            ``model_error`` and ``ci95_model`` (the interval widened by the components' bias) follow.
        ready: called once the input is validated, before the first simulation (the command line
            makes its output directory there, so that refused input leaves none).

    Raises ValueError (one line, naming the field) on bad input, before any simulation, and
    :class:`FitError` when the simulation at the start values fails.
    """
    t_start = time.perf_counter()
    names = check_arguments(params, algorithm, overrides, bounds, grid, newton, xtol, max_iter, max_replans,
                            substeps, starts)
    components = _check_components(model_error)
    problem, axes = _prepare(scene, data, names, variant=variant, algorithm=algorithm, overrides=overrides,
                             bounds=bounds, window=window, newton=newton, max_iter=max_iter, xtol=xtol,
                             max_replans=max_replans, substeps=substeps, grid=grid, starts=starts,
                             progress=progress)
    if ready is not None:
        ready()
    starts_at, grid_rows = ([problem.par.p0.copy()], []) if axes is None else _global_stage(problem, axes, starts)
    best, outcomes = local_stage(problem, starts_at)
    error = None
    if components:
        cur = best["cur"]
        error = fit_model_error.model_error(
            scene, problem.par.scene.variant, algorithm, problem.overrides, dict(zip(names, cur["p"].tolist())),
            cur["jac"], problem.observed + cur["r"], problem.meas.displacement, problem.edges, components, problem.say)
        problem.simulations += len(components)
    return _result(problem, best, outcomes, grid_rows, t_start, error)


@dataclasses.dataclass
class Problem:
    """One call of :func:`fit`: the parameterised scene, the measurement and its observations, the
    options of the local stage, and the counts of simulations and re-plans so far (the only fields
    that change).

    Attributes:
        scene, algorithm, overrides: as given to :func:`fit`; names: the fitted parameters.
        par: the parameterisation; meas: the measurement; edges: window edges (mm) or None;
            observed: the measured observations (force at every point, or window means).
        lo, hi: (n,) bounds.
        newton, max_iter, xtol, max_replans, substeps: as given to :func:`fit`.
        model_key: what the simulations depend on besides the parameters (the key of the caches).
        say: prints a progress line (or nothing).
        rtol: None for a fit (stopped by the standard errors). A design
            (:mod:`jaxfric.identification.design`) of targets, not measurements: it stops when every
            observation is within ``rtol`` of its target (:func:`met`), or when the step is below ``xtol``; its
            standard errors, with as many parameters as targets or more, mean nothing.
        task: "fit" or "design", the first word of the progress lines.
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
    newton: NewtonOptions | None
    max_iter: int
    xtol: float
    max_replans: int
    substeps: int
    model_key: tuple
    say: Callable[[str], None]
    rtol: float | None = None
    task: str = "fit"
    simulations: int = 0
    replans: int = 0


def check_arguments(params, algorithm, overrides, bounds, grid, newton, xtol, max_iter, max_replans, substeps,
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


def _check_components(model_error) -> tuple:
    """The model-error components as a tuple of known names, each once (ValueError naming the field)."""
    items = (model_error,) if isinstance(model_error, str) else tuple(model_error or ())
    known = fit_model_error.COMPONENTS
    if any(c not in known for c in items) or len(set(items)) != len(items):
        raise ValueError(f"field 'model_error' must name each of {', '.join(known)} at most once, got {model_error!r}")
    return items


def _prepare(scene: str, data, names: tuple, *, variant, algorithm, overrides, bounds, window, newton, max_iter,
             xtol, max_replans, substeps, grid, starts, progress) -> tuple[Problem, list | None]:
    """Read and check the measurement, build the parameterised scene and check the bounds and the
    grid against it: the :class:`Problem` and the grid's axes (None without a grid). ValueError
    naming the field; nothing is simulated."""
    meas = read_measurement(data)
    if meas.displacement.size < len(names):
        raise ValueError(f"measurement {meas.source!r} has {meas.displacement.size} point(s) at displacement > 0, "
                         f"fewer than the {len(names)} parameter(s)")
    if starts > 1 and not grid:
        raise ValueError(f"field 'starts' = {starts} needs a grid (the starts are minima of the global stage)")
    edges = window_edges(meas.displacement, window, len(names))
    par = parameterize(scene, names, variant=variant, algorithm=algorithm, overrides=overrides)
    lo, hi = check_bounds(names, par.p0, bounds)
    axes = grid_axes(grid, names, lo, hi) if grid else None
    problem = new_problem(par, meas, edges, lo, hi, algorithm=algorithm, overrides=overrides, newton=newton,
                          max_iter=max_iter, xtol=xtol, max_replans=max_replans, substeps=substeps, progress=progress)
    return problem, axes


def new_problem(par: Parameterization, meas: Measurement, edges, lo: np.ndarray, hi: np.ndarray, *, algorithm: str,
                overrides, newton, max_iter: int, xtol: float, max_replans: int, substeps: int, progress: bool,
                rtol: float | None = None, task: str = "fit") -> Problem:
    """The :class:`Problem` of a fit (or, with ``rtol`` and ``task``, a design) of ``par`` to ``meas``:
    its observations (the measured force, or its means over the windows ``edges``), the key of the
    caches and the progress printer."""
    observed = meas.force if edges is None else bin_means(meas.displacement, meas.force, edges)
    say = (lambda text: print(text, file=sys.stderr, flush=True)) if progress else (lambda text: None)
    scene = par.scene.name
    model_key = (scene, par.names, par.scene.variant, algorithm, repr(sorted((overrides or {}).items())), newton)
    return Problem(scene=scene, algorithm=algorithm, overrides=dict(overrides or {}), names=par.names, par=par,
                   meas=meas, edges=edges, observed=observed, lo=lo, hi=hi, newton=newton, max_iter=max_iter,
                   xtol=xtol, max_replans=max_replans, substeps=substeps, model_key=model_key, say=say, rtol=rtol,
                   task=task)


def check_bounds(names, p0, bounds) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) per fitted parameter: ``bounds`` where given, else [0, inf), or (-inf, inf) for a
    friction law's terms, which may be negative; each must hold its start value ``p0`` (ValueError naming
    the field ``bounds``)."""
    lo = np.array([-np.inf if name in POLYNOMIAL_TERMS else 0.0 for name in names])
    hi = np.full(len(names), np.inf)
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

def _global_stage(problem: Problem, axes: list, starts: int) -> tuple[list, list]:
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


def _grid_runs(problem: Problem, axes: list, points: np.ndarray) -> tuple[np.ndarray, list]:
    """The adaptive run at every grid point (kept in :data:`GRID_RUNS`): their
    observations (NaN where a run failed) and a row per point (parameters, misfit, converged)."""
    names, observed = problem.names, problem.observed
    runs = GRID_RUNS.get((*problem.model_key, tuple(a.tobytes() for a in axes)), dict)
    problem.say(f"{problem.task} {problem.scene}: global stage, adaptive runs at {len(points)} grid points")
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


# ---- the local stage: least squares on frozen step sequences ------------------------------------------

def local_stage(problem: Problem, starts_at: list) -> tuple[dict, list]:
    """Least squares from every start (:func:`_local_fit`): the outcome of the lowest misfit
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


def _local_fit(problem: Problem, p_start: np.ndarray, number: int, count: int) -> dict:
    """Least squares from ``p_start`` (start ``number`` of ``count``) on the step sequence planned there,
    then the adaptive runs at the optimum until it stops moving (module docstring).

    Returns {cur (the final point, :func:`_evaluate`'s fields), converged, message, p_start, start_force,
    start_obs (the simulated observations at the start), iterations (a row per simulation), number}.
    Raises :class:`FitError` when the start values do not simulate.
    """
    names = problem.names
    problem.say(f"{problem.task} {problem.scene}: planning the step sequence at "
                + ", ".join(f"{n} = {v:g}" for n, v in zip(names, p_start)))
    history, failure = adaptive_history(problem, p_start)
    if history is None:
        raise FitError(f"the simulation at the start values does not complete: {failure}")
    curve, key = _curve(problem, history)
    cur = _evaluate(problem, curve, p_start.copy())
    if not math.isfinite(cur["cost"]):
        raise FitError(f"the replayed step sequence fails at the start values ({describe(cur['code'])})")
    start_force, start_obs = cur["pointwise"], problem.observed + cur["r"]
    iterations = [_row(problem, 0, "replay", True, cur)]
    compiled = 0
    while True:
        cur, message = _trials(problem, curve, cur, iterations)
        if message or problem.max_replans == 0:
            converged, history = not message, None
            break
        cur, converged, message, history = _settle(problem, key, cur, iterations)
        if converged or history is None or compiled >= problem.max_replans:
            break
        # The optimum still moves with the adaptive run's steps: fit again on its sequence.
        compiled += 1
        curve, key = _curve(problem, history)
        problem.say("  fitting again on the step sequence of the adaptive run at the optimum "
                    f"({len(curve.times)} steps)")
        cur = _evaluate(problem, curve, cur["p"])
        iterations.append(_row(problem, len(iterations), "replay", True, cur))
        if not math.isfinite(cur["cost"]):
            message = f"the re-planned step sequence fails at the fitted values ({describe(cur['code'])})"
            break
    if count > 1:
        for row in iterations:
            row["start"] = number + 1
    return {"cur": cur, "converged": converged, "message": message, "p_start": p_start,
            "start_force": start_force, "start_obs": start_obs, "iterations": iterations, "number": number}


class _Settled(Exception):
    """Raised by the least-squares objective when the solver's next trial moves no parameter by more
    than its stopping tolerance: the trust region has shrunk below what the data resolve."""


def _trials(problem: Problem, curve: Curve, cur: dict, iterations: list) -> tuple[dict, str]:
    """Bounded least squares (``scipy.optimize.least_squares``, trust-region reflective, the Jacobian
    from the replay's forward-mode derivative) on one step sequence from ``cur``, stopped by
    :func:`_converged` or when the solver's trial steps fall below the same tolerance (the misfit no
    longer decreasing along steps the data cannot resolve: the sequence's discretisation noise), or
    after ``max_iter`` trials. A row per trial is appended to ``iterations``. Returns the last
    accepted point and "" or, where the trials ran out, why."""
    from scipy.optimize import least_squares

    names, best, calls = problem.names, {"point": cur}, [0]

    def objective(p):
        point = best["point"]
        calls[0] += 1
        if np.array_equal(p, point["p"]):
            return point["r"]
        if calls[0] > 1 and np.all(np.abs(p - point["p"]) <= _tolerance(problem, point)):
            raise _Settled
        # (the first call is the start, which least_squares moves off a bound it lies on: evaluated)
        new = _evaluate(problem, curve, np.asarray(p, float).copy())
        accepted = new["cost"] < point["cost"] or calls[0] == 1  # least_squares': a decrease of the misfit
        iterations.append(_row(problem, len(iterations), "replay", accepted, new))
        verdict = "accepted" if accepted else "rejected"
        problem.say(f"  trial {len(iterations) - 1}: misfit {new['cost']:.6g} ({verdict}, {new['cuts']} cutbacks) at "
                    + ", ".join(f"{n} = {v:.10g}" for n, v in zip(names, p)))
        if accepted:
            best["point"] = new
        return new["r"] if math.isfinite(new["cost"]) else np.full_like(point["r"], np.nan)

    def jacobian(p):
        return best["point"]["jac"]  # called at accepted points only, the last one evaluated

    def stop(intermediate_result):
        if _converged(problem, best["point"]):
            raise StopIteration

    if _converged(problem, cur):
        return cur, ""
    try:
        out = least_squares(objective, cur["p"], jac=jacobian, bounds=(problem.lo, problem.hi), method="trf",
                            x_scale="jac", xtol=problem.xtol, ftol=None, gtol=None, max_nfev=problem.max_iter + 1,
                            callback=stop)
        ran_out = out.status == 0
    except _Settled:
        ran_out = False
    cur = best["point"]
    return cur, (f"no convergence in {problem.max_iter} trials on one step sequence" if ran_out else "")


def _settle(problem: Problem, key: tuple, cur: dict, iterations: list) -> tuple[dict, bool, str, dict | None]:
    """The adaptive run at the optimum ``cur`` of the sequence whose curve has the key ``key``, and
    Gauss-Newton steps on the adaptive runs with ``cur``'s Jacobian (the sequences differ by a few
    steps, their Jacobians by little) until a step falls within :func:`_tolerance`: then the adaptive
    run reproduces the data best there, to the accuracy the data resolve. At most ``max_replans``
    adaptive runs; each is a row of ``iterations``. Returns (the final point, converged, message, the
    last adaptive run's history when the steps did not settle, to fit on its sequence, else None)."""
    point, p, history = cur, cur["p"], None
    for k in range(problem.max_replans):
        history, failure = adaptive_history(problem, p)
        problem.replans += 1
        if history is None:
            return point, False, f"the adaptive run at the fitted values does not complete: {failure}", None
        if k == 0 and _curve_key(problem, history) == key:
            problem.say("  the adaptive run at the optimum takes the fitted step sequence")
            return point, True, "", None
        r = observations(history, problem.meas.displacement, problem.edges) - problem.observed
        point = {**point, "p": p, "r": r, "cost": 0.5 * float(r @ r),
                 "pointwise": observations(history, problem.meas.displacement, None)}
        iterations.append(_row(problem, len(iterations), "adaptive", True, point))
        step = _gauss_newton_step(problem, point)
        problem.say(f"  adaptive run at the optimum: misfit {point['cost']:.6g}, Gauss-Newton step "
                    + ", ".join(f"{n} {d:+.3g}" for n, d in zip(problem.names, step)))
        if _converged(problem, point):
            return point, True, "", None
        p = point["p"] + step
    return point, False, (f"the optimum still moved with the adaptive run's steps after {problem.max_replans} "
                          "adaptive runs"), history


STOP_FRACTION = 0.1  # a step moving every parameter by at most this fraction of its standard error ends the fit


def _covariance(jac: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Gauss-Newton covariance s^2 (J^T J)^-1, s^2 = |r|^2 / (m - n) (module docstring); inf where
    J^T J is singular."""
    m, n = jac.shape
    try:
        return (r @ r) / max(m - n, 1) * np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        return np.full((n, n), np.inf)


def _standard_errors(cov: np.ndarray) -> np.ndarray:
    """The square roots of the covariance's diagonal (0 where round-off leaves it negative)."""
    return np.sqrt(np.maximum(np.diag(cov), 0.0))


def _tolerance(problem: Problem, point: dict) -> np.ndarray:
    """Per parameter, the step below which the fit stops: ``STOP_FRACTION`` of its standard error at
    ``point``, and never below ``xtol`` (|p_i| + ``xtol``) (noise-free data from the model itself, whose
    standard errors vanish at the optimum); ``xtol`` alone for a design (``rtol`` set)."""
    floor = problem.xtol * (np.abs(point["p"]) + problem.xtol)
    if problem.rtol is not None:
        return floor
    return np.maximum(STOP_FRACTION * _standard_errors(_covariance(point["jac"], point["r"])), floor)


def _gauss_newton_step(problem: Problem, point: dict) -> np.ndarray:
    """The Gauss-Newton step from ``point`` (least-squares solution of J dp = -r), shortened to stay
    inside the bounds."""
    step = np.linalg.lstsq(point["jac"], -point["r"], rcond=None)[0]
    return np.clip(point["p"] + step, problem.lo, problem.hi) - point["p"]


def _converged(problem: Problem, point: dict) -> bool:
    """Whether the Gauss-Newton step from ``point`` moves no parameter by more than :func:`_tolerance`
    (or the misfit is zero, or, for a design, every observation is within ``rtol`` of its target)."""
    if point["cost"] == 0.0:
        return True
    if problem.rtol is not None and met(point["r"], problem.observed, problem.rtol):
        return True
    return bool(np.all(np.abs(_gauss_newton_step(problem, point)) <= _tolerance(problem, point)))


def met(r: np.ndarray, targets: np.ndarray, rtol: float) -> bool:
    """Whether every residual ``r`` is within ``rtol`` of the targets' scale (their largest magnitude:
    a target curve starts near zero force, where a pointwise relative tolerance means nothing)."""
    return bool(np.all(np.abs(r) <= rtol * np.max(np.abs(targets))))


def _row(problem: Problem, k: int, run: str, accepted: bool, point: dict) -> dict:
    """A row of the fit's history: the simulation ``k`` (``run``: "replay" of the frozen sequence or
    "adaptive" run), whether it was accepted, its misfit and parameters."""
    return {"iteration": k, "run": run, "accepted": bool(accepted), "cost": point["cost"],
            **dict(zip(problem.names, np.asarray(point["p"]).tolist()))}


def adaptive_history(problem: Problem, p: np.ndarray) -> tuple[dict | None, str]:
    """The history of the adaptive run at ``p``, or None and why it failed. Raises ValueError when the
    measurement reaches beyond the simulated stroke."""
    res = adaptive_run(problem.par, p, problem.newton)
    problem.simulations += 1
    if not res.converged:
        return None, res.message
    top = float(np.max(res.history["drawing_displacement"]))
    if problem.meas.displacement[-1] > top * (1 + 1e-12):
        raise ValueError(f"measurement {problem.meas.source!r} reaches drawing_displacement "
                         f"{problem.meas.displacement[-1]:g} mm, beyond the simulated stroke {top:g} mm (raise the "
                         "scene's stroke field)")
    return res.history, ""


def _curve_key(problem: Problem, history: dict) -> tuple:
    """What a compiled curve along ``history``'s step sequence depends on (its key in :data:`CURVES`)."""
    edges = problem.edges
    return (*problem.model_key, np.asarray(history["time"]).tobytes(), problem.meas.displacement.tobytes(),
            None if edges is None else edges.tobytes(), problem.substeps)


def _curve(problem: Problem, history: dict) -> tuple[Curve, tuple]:
    """The curve along the step sequence of ``history`` (compiled once per sequence: kept in
    :data:`CURVES`) and its key there."""
    key = _curve_key(problem, history)
    return CURVES.get(key, lambda: Curve(problem.par, refined_plan(history, problem.substeps),
                                         problem.meas.displacement, problem.edges, problem.newton)), key


def _evaluate(problem: Problem, curve: Curve, p: np.ndarray) -> dict:
    """The curve at ``p``: {p, r (residuals), jac, pointwise (force at the measured points), cost
    (|r|^2 / 2; inf where the replay fails or r is not finite), code, cuts (cutbacks)}."""
    obs, jac, pointwise, code, cuts = curve(p)
    problem.simulations += 1
    r = obs - problem.observed
    cost = 0.5 * float(r @ r) if code == Result.SUCCESS and np.all(np.isfinite(r)) else math.inf
    return {"p": p, "r": r, "jac": jac, "pointwise": pointwise, "cost": cost, "code": code, "cuts": cuts}


# ---- the result --------------------------------------------------------------------------------------

def _result(problem: Problem, best: dict, outcomes: list, grid_rows: list, t_start: float,
            error: dict | None) -> FitResult:
    """The :class:`FitResult` of the best local fit with its Gauss-Newton uncertainty (module
    docstring), every local fit (``outcomes``), the global stage's rows and the model's error (or None;
    :func:`jaxfric.identification.fit_model_error.model_error`); ``t_start``: when :func:`fit` was called
    (``time.perf_counter``)."""
    from scipy.stats import t as student_t

    names, cur = problem.names, best["cur"]
    p, r, jac = cur["p"], cur["r"], cur["jac"]
    m, n = len(r), len(names)
    cov = _covariance(jac, r)
    err = _standard_errors(cov)
    q = float(student_t.ppf(0.975, max(m - n, 1)))
    return FitResult(
        scene=problem.scene, variant=problem.par.scene.variant, algorithm=problem.algorithm,
        overrides=problem.overrides, names=names, params=dict(zip(names, p.tolist())),
        stderr=dict(zip(names, err.tolist())),
        ci95={nm: (float(v - q * e), float(v + q * e)) for nm, v, e in zip(names, p, err)},
        model_error=error,
        ci95_model=({} if error is None else
                    {nm: (float(v - q * e - error["bound"][nm]), float(v + q * e + error["bound"][nm]))
                     for nm, v, e in zip(names, p, err)}),
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
