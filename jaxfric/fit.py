"""Identification of scene parameters from a measured drawing-force curve.

    >>> from jaxfric.fit import fit, write_fit
    >>> res = fit("nine", "measured.csv", ["mu"], overrides={"mesh": "40x2", "U_draw": 10})
    >>> res.params, res.stderr            # {"mu": 0.1700...}, {"mu": 1.2e-3}
    >>> write_fit(res, "fits/nine")       # fit.json, fit.png, fit_history.csv

**The measurement.** A CSV (or a mapping of arrays) with at least the columns ``drawing_displacement``
(mm) and ``drawing_force`` (N/mm). Rows at displacement <= 0 are dropped (before drawing the force is
not a drawing force, and a ``history.csv`` written by ``jaxfric run`` carries its clamping rows there);
the remaining displacements must increase strictly and lie inside the simulated stroke.

**The model of the measurement.** The simulated drawing force, linearly interpolated at the measured
displacements, along a *frozen step sequence*: the accepted steps of an adaptive run at the current
parameters become the nominal steps of the runs that follow (:func:`jaxfric.loading.with_steps`). A
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
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import sys
import time
from collections.abc import Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ._checks import check_int, check_positive
from .formulations import ALGORITHMS, DIFFERENTIABLE_ALGORITHMS
from .newton import NewtonOptions
from .params import Parameterization, adaptive_run, parameterize, path_function
from .results import Result, describe

__all__ = ["Measurement", "FitResult", "FitError", "read_measurement", "bin_means", "fit", "write_fit"]

_COLUMNS = ("drawing_displacement", "drawing_force")
# Beyond these a measured value is not a sheet-drawing measurement (and its squares overflow the misfit).
MAX_MAGNITUDE = {"drawing_displacement": 1e6, "drawing_force": 1e12}  # mm, N/mm
MAX_WINDOWS = 100_000  # fitted windows (``window``)
MAX_GRID_POINTS = 10_000  # adaptive runs of the global stage (``grid``), every axis combined


class FitError(RuntimeError):
    """The simulation at the start values fails: the fit cannot begin (not an input error)."""


@dataclasses.dataclass(frozen=True)
class Measurement:
    """A measured drawing-force curve: displacement (mm, strictly increasing, > 0) and force (N/mm)."""

    displacement: np.ndarray
    force: np.ndarray
    source: str = ""


def read_measurement(data) -> Measurement:
    """A :class:`Measurement` from a CSV path or a mapping with the columns ``drawing_displacement``
    and ``drawing_force``. Raises ValueError (one line, naming the file and column) when a column is
    missing, a value is not a finite number, or the displacement does not increase."""
    if isinstance(data, Measurement):
        return data
    if isinstance(data, (str, os.PathLike)):
        source = os.fspath(data)
        try:
            # utf-8-sig: a spreadsheet's byte-order mark is not part of the first column's name.
            with open(source, newline="", encoding="utf-8-sig") as stream:
                reader = csv.DictReader(stream)
                rows = list(reader)
                header = reader.fieldnames or []
        except OSError as err:
            raise ValueError(f"measurement file {source!r} cannot be read: {err.strerror or err}") from None
        except (csv.Error, UnicodeDecodeError) as err:
            raise ValueError(f"measurement file {source!r} is not a CSV file: {err}") from None
        twice = [c for c in header if header.count(c) > 1]
        if twice:
            raise ValueError(f"measurement file {source!r} has the column {twice[0]!r} twice")
        missing = [c for c in _COLUMNS if c not in header or not rows]
        if missing:
            raise ValueError(f"measurement file {source!r} lacks the column(s) {', '.join(missing)}"
                             + ("" if rows else " (no data rows)"))
        columns = {}
        for c in _COLUMNS:
            values = []
            for k, row in enumerate(rows):
                try:
                    values.append(float(row[c]))
                except (TypeError, ValueError):
                    raise ValueError(f"measurement file {source!r}: column {c!r} row {k + 1} is not a "
                                     f"number: {row[c]!r}") from None
            columns[c] = np.array(values)
    else:
        source = "data"
        try:
            missing = [c for c in _COLUMNS if c not in data]
        except TypeError:
            raise ValueError("field 'data' must be a CSV path or a mapping with the columns "
                             "drawing_displacement and drawing_force") from None
        if missing:
            raise ValueError(f"field 'data' lacks the column(s) {', '.join(missing)}")
        try:
            columns = {c: np.asarray(data[c], dtype=float).ravel() for c in _COLUMNS}
        except (TypeError, ValueError):
            raise ValueError("field 'data': drawing_displacement and drawing_force must be numbers") from None
        if columns[_COLUMNS[0]].shape != columns[_COLUMNS[1]].shape:
            raise ValueError("field 'data': drawing_displacement and drawing_force differ in length")
    x, f = columns["drawing_displacement"], columns["drawing_force"]
    for name, v in (("drawing_displacement", x), ("drawing_force", f)):
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            raise ValueError(f"measurement {source!r}: column {name!r} holds a non-finite value at row "
                             f"{bad[0] + 1} ({v[bad[0]]})")
        bad = np.flatnonzero(np.abs(v) > MAX_MAGNITUDE[name])
        if bad.size:
            raise ValueError(f"measurement {source!r}: column {name!r} holds {v[bad[0]]:g} at row {bad[0] + 1}, "
                             f"beyond {MAX_MAGNITUDE[name]:g} in magnitude")
    keep = x > 0
    x, f = x[keep], f[keep]
    if x.size == 0:
        raise ValueError(f"measurement {source!r}: no row with drawing_displacement > 0")
    step = np.diff(x)
    if np.any(step <= 0):
        k = int(np.flatnonzero(step <= 0)[0])
        raise ValueError(f"measurement {source!r}: drawing_displacement must increase strictly; it goes "
                         f"from {x[k]} to {x[k + 1]}")
    return Measurement(displacement=x, force=f, source=source)


@dataclasses.dataclass
class FitResult:
    """Outcome of :func:`fit`.

    Attributes:
        scene, variant, algorithm, overrides: what was simulated.
        names: fitted parameter names; params, stderr, ci95: {name: value} (ci95: (low, high)).
        start: {name: start value}; bounds: {name: (low, high)}; window: fitted window length (mm)
            or None (pointwise).
        covariance: (n, n) Gauss-Newton covariance at the optimum.
        residual_rms: sqrt(mean r^2) (N/mm) at the optimum; cost: |r|^2 / 2.
        n_points: fitted observations (measured points, or windows); n_simulations: simulations run (adaptive
            planning runs and frozen-sequence runs, each frozen-sequence run with its n forward-mode tangents);
            n_replans: adaptive runs after the first.
        wall_s: total wall time (s), compilation included; converged; message.
        iterations: per accepted or rejected trial, a dict (iteration, accepted, cost, damping, params).
        measurement: the :class:`Measurement`; fitted_force, start_force: simulated force at the
            measured displacements (pointwise, whatever ``window``), at the optimum and at the start.
        grid: the global stage (``grid`` argument): per grid point, a dict of its parameters, its
            misfit (inf where the run failed) and ``converged``; empty without one. ``start`` is
            then the point the global stage chose.
        local_fits: per start of the local stage (``starts``), a dict of its number (the
            ``start`` column of ``iterations`` when there are several), its start and end
            (parameters), misfit, converged and message; the result is the lowest misfit's.
    """

    scene: str
    variant: str
    algorithm: str
    overrides: dict
    names: tuple
    params: dict
    stderr: dict
    ci95: dict
    start: dict
    bounds: dict
    window: float | None
    covariance: np.ndarray
    residual_rms: float
    cost: float
    n_points: int
    n_simulations: int
    n_replans: int
    wall_s: float
    converged: bool
    message: str
    iterations: list
    measurement: Measurement
    fitted_force: np.ndarray
    start_force: np.ndarray
    grid: list = dataclasses.field(default_factory=list)
    local_fits: list = dataclasses.field(default_factory=list)


def bin_means(x, f, edges):
    """Mean of the piecewise-linear curve through (x, f) over each interval [edges[j], edges[j+1]]
    (x increasing; equal neighbours allowed; works on NumPy and JAX arrays alike)."""
    xp = jnp if isinstance(x, jax.Array) else np
    seg = 0.5 * (f[1:] + f[:-1]) * (x[1:] - x[:-1])
    cum = xp.concatenate([xp.zeros(1), xp.cumsum(seg)])
    i = xp.clip(xp.searchsorted(x, edges, side="right"), 1, x.shape[0] - 1)
    x0, x1, f0, f1 = x[i - 1], x[i], f[i - 1], f[i]
    fe = f0 + (f1 - f0) * (edges - x0) / xp.where(x1 > x0, x1 - x0, 1.0)
    area = cum[i - 1] + 0.5 * (f0 + fe) * (edges - x0)
    return (area[1:] - area[:-1]) / (edges[1:] - edges[:-1])


_CURVES: dict[tuple, _Curve] = {}  # compiled curves by scene, parameters and step sequence: repeated fits reuse them
REPLAY_ITERATIONS = 60  # Newton iterations per step allowed in the frozen-sequence replays


class _Curve:
    """The fitted observations (the simulated force at the measured displacements, or its means over
    the windows ``edges``) along one frozen step sequence, with their Jacobian; compiled once per
    sequence."""

    def __init__(self, par: Parameterization, plan_history: dict, x: np.ndarray, edges, newton: NewtonOptions | None):
        self.times = np.asarray(plan_history["time"][1:])
        newton = par.scene.newton if newton is None else newton
        newton = dataclasses.replace(newton, max_iterations=max(newton.max_iterations, REPLAY_ITERATIONS))
        path = path_function(par, newton=newton, plan=plan_history)

        def curve(p):
            h, code = path(p)
            rows = jnp.arange(h.time.shape[0], dtype=h.n_rows.dtype)
            # Unfilled rows get displacements beyond every measured one (interp needs increasing x).
            xr = jnp.where(rows < h.n_rows, h.observed["drawing_displacement"], 1e30 * (1.0 + rows.astype(float)))
            fr = jnp.where(rows < h.n_rows, h.observed["drawing_force"], 0.0)
            pointwise = jnp.interp(jnp.asarray(x), xr, fr)
            obs = pointwise if edges is None else bin_means(xr, fr, jnp.asarray(edges))
            return obs, (obs, pointwise, code, jnp.sum(h.cutbacks))

        self._fn = jax.jit(jax.jacfwd(curve, has_aux=True))

    def same_plan(self, other: _Curve) -> bool:
        return self.times.shape == other.times.shape and np.allclose(self.times, other.times, rtol=0, atol=1e-12)

    def __call__(self, p):
        jac, (obs, pointwise, code, cuts) = self._fn(jnp.asarray(p, jnp.float64))
        return np.asarray(obs), np.asarray(jac), np.asarray(pointwise), int(code), int(cuts)


def _refined(history: dict, substeps: int) -> dict:
    """The step sequence of ``history`` with every accepted step split into ``substeps`` equal steps
    (the time, phase and cutback columns that :func:`jaxfric.params.path_function` replays; a step
    accepted as a retry keeps that mark on its first part)."""
    if substeps == 1:
        return history
    t, phase, cuts = (np.asarray(history[k]) for k in ("time", "phase", "cutbacks"))
    times, phases, retry = [t[0]], [phase[0]], [cuts[0]]
    for k in range(1, len(t)):
        for j in range(1, substeps + 1):
            times.append(t[k] if j == substeps else t[k - 1] + (t[k] - t[k - 1]) * j / substeps)
            phases.append(phase[k])
            retry.append(cuts[k] if j == 1 else 0)
    return {"time": np.array(times), "phase": np.array(phases), "cutbacks": np.array(retry)}


def _bounds(names, p0, bounds) -> tuple[np.ndarray, np.ndarray]:
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


def _lm_step(jac, r, damping):
    """Levenberg-Marquardt step: (J^T J + damping diag(J^T J)) dp = -J^T r."""
    a = jac.T @ jac
    d = np.diag(a).copy()
    d[d <= 0] = 1.0
    return np.linalg.solve(a + damping * np.diag(d), -jac.T @ r)


def _windows(x: np.ndarray, window, n_params: int):
    """Window edges over [x_0, x_last] of width about ``window`` (mm), or None (pointwise)."""
    if window is None:
        return None
    check_positive("window", window)
    w = float(window)
    count = (x[-1] - x[0]) / w  # inf where the quotient overflows
    if count > MAX_WINDOWS:
        raise ValueError(f"field 'window' = {w:g} mm leaves {count:.3g} windows over the measured stroke "
                         f"[{x[0]:g}, {x[-1]:g}] mm, more than {MAX_WINDOWS:,}")
    n = int((x[-1] - x[0]) // w)
    if n < max(n_params, 1):
        raise ValueError(f"field 'window' = {w:g} mm leaves {n} window(s) over the measured stroke "
                         f"[{x[0]:g}, {x[-1]:g}] mm, fewer than the {n_params} parameter(s)")
    return np.linspace(x[0], x[-1], n + 1)


# Adaptive runs (their histories; None: failed) of the global stage by scene, parameters and grid: repeated
# fits reuse them.
_GRIDS: dict[tuple, dict[int, dict | None]] = {}


def _grid_axes(grid, names, lo, hi) -> list:
    """The grid's values per fitted parameter (validated); a parameter the grid does not name keeps
    its start value (an axis of one value)."""
    grid = dict(grid)
    unknown = [k for k in grid if k not in names]
    if unknown:
        raise ValueError(f"field 'grid' names {unknown[0]!r}, which is not a fitted parameter ({', '.join(names)})")
    axes: list[np.ndarray | None] = []
    for i, name in enumerate(names):
        if name not in grid:
            axes.append(None)
            continue
        try:
            v = np.asarray([float(x) for x in grid[name]])
        except (TypeError, ValueError):
            raise ValueError(f"field 'grid' of {name!r} must be a sequence of numbers, got {grid[name]!r}") from None
        if v.size < 2 or not np.all(np.isfinite(v)) or np.any(np.diff(v) <= 0):
            raise ValueError(f"field 'grid' of {name!r} must hold at least two finite, increasing values, "
                             f"got {grid[name]!r}")
        if v[0] < lo[i] or v[-1] > hi[i]:
            raise ValueError(f"field 'grid' of {name!r} = [{v[0]:g}, {v[-1]:g}] leaves the bounds "
                             f"[{lo[i]:g}, {hi[i]:g}]")
        axes.append(v)
    points = math.prod(a.size for a in axes if a is not None)
    if points > MAX_GRID_POINTS:
        raise ValueError(f"field 'grid' gives {points:,} runs (the product of its axes), more than {MAX_GRID_POINTS:,}")
    return axes


def _observations(history: dict, x: np.ndarray, edges):
    """The fitted observations of a completed run (as :class:`_Curve` computes them along a replay)."""
    xr, fr = np.asarray(history["drawing_displacement"]), np.asarray(history["drawing_force"])
    return np.interp(x, xr, fr) if edges is None else bin_means(xr, fr, edges)


def _surrogate_minima(axes: list, obs: np.ndarray, observed: np.ndarray, count: int, refine: int = 10) -> list:
    """Up to ``count`` local minima of the misfit of the observations interpolated multilinearly
    between grid points, lowest first: [(point, misfit), ...].

    Interpolating the observations, not the misfit, follows a narrow valley of the misfit between
    grid points (the observations are smooth in the parameters where the misfit is not quadratic on
    the grid's scale). The misfit is evaluated on a lattice ``refine`` points per cell and axis (fewer
    where that would exceed ~2e5 observations). Its lowest local minima (no lower neighbour along any
    axis; at least 8, since a valley narrower than the lattice spacing can leave the lowest lattice
    point in another basin) are polished by Nelder-Mead (the interpolant is only piecewise smooth), so
    that a start does not depend on where the lattice points fall, and ranked by their polished misfit;
    points within a lattice step of a lower one are the same basin. Cells with a failed run (NaN) are
    left out. Where every cell has one, a single (point, inf). Measured on the Nine's mu + R1 grid
    (7 x 9 runs) for the noise draw of seed 1: the lowest lattice minimum (1.438) polishes to 1.239 at
    (0.1753, 5.531), the second (1.500) to 0.428 at (0.1704, 5.502), within one grid cell of it."""
    from scipy.interpolate import RegularGridInterpolator
    from scipy.optimize import minimize

    live = [a for a in axes if a.size > 1]
    values = obs.reshape([a.size for a in live] + [obs.shape[-1]])
    per_cell = min(refine, max(2, int(round((2e5 / max(obs.shape[-1], 1)) ** (1.0 / len(live))))))
    fine = [np.unique(np.concatenate([np.linspace(a[j], a[j + 1], per_cell + 1)
                                      for j in range(a.size - 1)])) for a in live]
    shape = [f.size for f in fine]
    mesh = np.stack(np.meshgrid(*fine, indexing="ij"), axis=-1).reshape(-1, len(live))
    interp = RegularGridInterpolator(live, values, method="linear")
    cost = 0.5 * np.sum((interp(mesh) - observed) ** 2, axis=1)
    cost[~np.isfinite(cost)] = np.inf
    if not np.isfinite(cost).any():
        return [(mesh[int(np.argmin(cost))], math.inf)]
    # Lattice points with no lower neighbour along any axis (a plateau keeps all its points).
    field = cost.reshape(shape)
    padded = np.pad(field, 1, constant_values=np.inf)
    centre = tuple(slice(1, -1) for _ in shape)
    lowest = np.isfinite(field)
    for ax in range(len(shape)):
        for shift in (-1, 1):
            neighbour = tuple(slice(1 + shift, n + 1 + shift) if i == ax else centre[i] for i, n in enumerate(shape))
            lowest &= field <= padded[neighbour]
    index = np.stack(np.unravel_index(np.flatnonzero(lowest.reshape(-1)), shape), axis=-1)
    # The lowest lattice minima are polished, more of them than asked for: in a valley narrower than
    # the lattice spacing the lowest lattice point need not lie in the lowest basin.
    chosen = index[np.argsort(field[tuple(index.T)], kind="stable")][:max(8, 4 * count)]

    def surrogate(q):
        v = 0.5 * float(np.sum((interp(q[None, :])[0] - observed) ** 2))
        return v if math.isfinite(v) else 1e300

    box = [(a[0], a[-1]) for a in live]
    step = np.array([(a[-1] - a[0]) / (a.size - 1) / per_cell for a in live])
    minima = []
    for k in chosen:
        q0 = np.array([fine[i][j] for i, j in enumerate(k)])
        simplex = np.vstack([q0] + [q0 + np.where(np.arange(len(live)) == i, step[i], 0.0) for i in range(len(live))])
        simplex = np.clip(simplex, [b[0] for b in box], [b[1] for b in box])
        res = minimize(surrogate, q0, method="Nelder-Mead", bounds=box,
                       options={"initial_simplex": simplex, "xatol": 1e-9, "fatol": 1e-12, "maxiter": 2000})
        c0 = float(field[tuple(k)])
        point, value = (np.asarray(res.x), float(res.fun)) if res.fun < c0 else (q0, c0)
        minima.append((point, value))
    # Lattice minima of one basin polish to (nearly) the same point: keep the lowest of each, and
    # basins at least a lattice step apart.
    distinct: list[tuple[np.ndarray, float]] = []
    for point, value in sorted(minima, key=lambda m: m[1]):
        if all(np.max(np.abs(point - other) / step) >= 1.0 for other, _ in distinct):
            distinct.append((point, value))
    return distinct[:count]


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
        params: names of config fields to fit (see :func:`jaxfric.params.parameterize`).
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
            scene and grid (other measurements, e.g. noise draws, cost no simulation).
        starts: with a grid, Levenberg-Marquardt from up to this many local minima of the
            interpolated misfit (lowest first, distinct basins: :func:`_surrogate_minima`); the fit with the lowest
            misfit is the result (its ``start``), the others are kept in ``local_fits``. Where the
            interpolation error of the grid is larger than the misfit differences between basins,
            the lowest interpolated minimum need not be in the lowest basin.
        ready: called once the input is validated, before the first simulation (the command line
            makes its output directory there, so that refused input leaves none).

    Raises ValueError (one line, naming the field) on bad input, before any simulation, and
    :class:`FitError` when the simulation at the start values fails.
    """
    t_start = time.perf_counter()
    if isinstance(params, str):
        params = (params,)
    if not (isinstance(params, (tuple, list)) and all(isinstance(n, str) for n in params)):
        raise ValueError(f"field 'params' must be a name or a sequence of names of config fields, got {params!r}")
    names = tuple(params)
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
    meas = read_measurement(data)
    if meas.displacement.size < len(names):
        raise ValueError(f"measurement {meas.source!r} has {meas.displacement.size} point(s) at displacement > 0, "
                         f"fewer than the {len(names)} parameter(s)")
    if starts > 1 and not grid:
        raise ValueError(f"field 'starts' = {starts} needs a grid (the starts are minima of the global stage)")
    edges = _windows(meas.displacement, window, len(names))
    observed = meas.force if edges is None else bin_means(meas.displacement, meas.force, edges)
    par = parameterize(scene, names, variant=variant, algorithm=algorithm, overrides=overrides)
    lo, hi = _bounds(names, par.p0, bounds)
    axes = _grid_axes(grid, names, lo, hi) if grid else None
    if ready is not None:
        ready()
    project = jax.jit(lambda p: optax.projections.projection_box(p, jnp.asarray(lo), jnp.asarray(hi)))
    say = (lambda text: print(text, file=sys.stderr, flush=True)) if progress else (lambda text: None)
    counts = {"simulations": 0, "replans": 0}
    # What the simulations depend on besides the parameters: the key of the caches of compiled curves
    # and of the global stage's runs.
    model_key = (scene, names, par.scene.variant, algorithm, repr(sorted((overrides or {}).items())), newton)

    def planned(p):
        """A curve on the step sequence of the adaptive run at p; None and the reason if it fails."""
        res = adaptive_run(par, p, newton)
        counts["simulations"] += 1
        if not res.converged:
            return None, res.message
        history = res.history
        top = float(np.max(history["drawing_displacement"]))
        if meas.displacement[-1] > top * (1 + 1e-12):
            raise ValueError(f"measurement {meas.source!r} reaches drawing_displacement {meas.displacement[-1]:g} "
                             f"mm, beyond the simulated stroke {top:g} mm (raise the scene's stroke field)")
        key = (*model_key, history["time"].tobytes(), meas.displacement.tobytes(),
               None if edges is None else edges.tobytes(), substeps)
        if key not in _CURVES:
            while len(_CURVES) >= 8:
                _CURVES.pop(next(iter(_CURVES)))
            _CURVES[key] = _Curve(par, _refined(history, substeps), meas.displacement, edges, newton)
        return _CURVES[key], ""

    def evaluate(curve, p):
        obs, jac, pointwise, code, cuts = curve(p)
        counts["simulations"] += 1
        r = obs - observed
        cost = 0.5 * float(r @ r) if code == Result.SUCCESS and np.all(np.isfinite(r)) else math.inf
        return {"p": p, "r": r, "jac": jac, "pointwise": pointwise, "cost": cost, "code": code, "cuts": cuts}

    def _local(p_start, number, count):
        """Levenberg-Marquardt from p_start, re-planning at the optimum (module docstring)."""
        say(f"fit {scene}: planning the step sequence at " + ", ".join(f"{n} = {v:g}" for n, v in zip(names, p_start)))
        curve, failure = planned(p_start)
        if curve is None:
            raise FitError(f"the simulation at the start values does not complete: {failure}")
        cur = evaluate(curve, p_start.copy())
        if not math.isfinite(cur["cost"]):
            raise FitError(f"the replayed step sequence fails at the start values ({describe(cur['code'])})")
        start_force = cur["pointwise"]
        damping, k, converged, message, replans = 1e-3, 0, False, "", 0
        iterations = [{"iteration": 0, "accepted": True, "cost": cur["cost"], "damping": damping,
                       **dict(zip(names, cur["p"].tolist()))}]
        while True:
            settled = False
            for _ in range(max_iter):
                k += 1
                dp = _lm_step(cur["jac"], cur["r"], damping)
                trial = np.asarray(project(optax.apply_updates(jnp.asarray(cur["p"]), jnp.asarray(dp))))
                new = evaluate(curve, trial)
                accepted = new["cost"] <= cur["cost"]
                iterations.append({"iteration": k, "accepted": bool(accepted), "cost": new["cost"], "damping": damping,
                                   **dict(zip(names, trial.tolist()))})
                say(f"  trial {k}: misfit {new['cost']:.6g} ({'accepted' if accepted else 'rejected'}, "
                    f"{new['cuts']} cutbacks) at " + ", ".join(f"{n} = {v:.10g}" for n, v in zip(names, trial)))
                if accepted:
                    moved = np.abs(trial - cur["p"])
                    cur, damping = new, max(damping / 3.0, 1e-9)
                    if np.all(moved <= xtol * (np.abs(trial) + xtol)) or cur["cost"] == 0.0:
                        settled = True
                        break
                else:
                    damping *= 10.0
                    if damping > 1e12:
                        message = "no decrease of the misfit even with very small steps (damping > 1e12)"
                        settled = True
                        break
            # Trials that stall on one sequence (a replay that cuts a step at some trial points moves the
            # curve by a small jump, which Levenberg-Marquardt cannot step over) still moved the point:
            # re-plan there while re-plans are left.
            stalled = not settled
            if stalled and replans >= max_replans:
                message = f"no convergence in {max_iter} trials on this step sequence"
                break
            if message:
                break
            if max_replans == 0:
                converged = True
                break
            # Re-plan at the optimum: the answer must hold for the adaptive run at these values.
            again, failure = planned(cur["p"])
            if again is None:
                message = f"the adaptive run at the fitted values does not complete: {failure}"
                break
            if again.same_plan(curve):
                if stalled:
                    message = (f"no convergence in {max_iter} trials on the step sequence of the adaptive run at "
                               "the fitted values")
                converged = not stalled
                break
            if replans >= max_replans:
                message = f"the step sequence still changed after {max_replans} re-plans"
                break
            replans += 1
            counts["replans"] += 1
            say(f"  re-planned the step sequence at the optimum ({len(again.times)} steps, was {len(curve.times)})")
            curve, damping = again, 1e-3
            cur = evaluate(curve, cur["p"])
            if not math.isfinite(cur["cost"]):
                message = f"the re-planned step sequence fails at the fitted values ({describe(cur['code'])})"
                break
        if count > 1:
            for row in iterations:
                row["start"] = number + 1
        return {"cur": cur, "converged": converged, "message": message, "p_start": p_start,
                "start_force": start_force, "iterations": iterations, "number": number}

    p_start, grid_rows = par.p0.copy(), []
    if grid:
        assert axes is not None  # set from the grid above
        axes = [np.array([par.p0[i]]) if a is None else a for i, a in enumerate(axes)]
        points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(names))
        runs = _GRIDS.setdefault((*model_key, tuple(a.tobytes() for a in axes)), {})
        say(f"fit {scene}: global stage, adaptive runs at {len(points)} grid points")
        obs = np.full((len(points), observed.size), np.nan)
        for j, p in enumerate(points):
            if j not in runs:
                res = adaptive_run(par, p, newton)
                counts["simulations"] += 1
                runs[j] = res.history if res.converged else None
            grid_run = runs[j]
            if grid_run is not None:
                obs[j] = _observations(grid_run, meas.displacement, edges)
            r = obs[j] - observed
            grid_rows.append({**dict(zip(names, p.tolist())),
                              "cost": 0.5 * float(r @ r) if runs[j] is not None else math.inf,
                              "converged": runs[j] is not None})
            say(f"  grid point {j + 1}/{len(points)}: misfit {grid_rows[-1]['cost']:.6g} at "
                + ", ".join(f"{n} = {v:.6g}" for n, v in zip(names, p)))
        if not any(row["converged"] for row in grid_rows):
            raise FitError("no run of the global stage completes: no start for the fit")
        minima = _surrogate_minima(axes, obs, observed, starts)
        starts_at = []
        for best, best_cost in minima:
            it = iter(best)
            starts_at.append(np.array([next(it) if a.size > 1 else a[0] for a in axes]))
            if not math.isfinite(best_cost):  # every cell has a failed corner: the best point run
                j = int(np.argmin([row["cost"] for row in grid_rows]))
                starts_at[-1] = points[j].copy()
            say(f"  global stage: interpolated misfit {best_cost:.6g} at "
                + ", ".join(f"{n} = {v:.6g}" for n, v in zip(names, starts_at[-1])))
    else:
        starts_at = [p_start]
    outcomes = []
    for number, p_start in enumerate(starts_at):
        try:
            outcomes.append(_local(p_start, number, len(starts_at)))
        except FitError as failure:  # a later start may still fit; the first one's failure is the fit's
            if number == 0:
                raise
            say(f"  start {number + 1} abandoned: {failure}")
    best = min(outcomes, key=lambda o: o["cur"]["cost"])
    cur, converged, message, p_start, start_force = (
        best[k] for k in ("cur", "converged", "message", "p_start", "start_force"))
    iterations = [row for o in outcomes for row in o["iterations"]]
    if len(starts_at) > 1:
        say(f"  best of {len(outcomes)} starts: start {best['number'] + 1}, misfit {cur['cost']:.6g}")

    p, r, jac = cur["p"], cur["r"], cur["jac"]
    m, n = len(r), len(names)
    s2 = 2.0 * cur["cost"] / max(m - n, 1)
    try:
        cov = s2 * np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        cov = np.full((n, n), np.inf)
    err = np.sqrt(np.maximum(np.diag(cov), 0.0))
    from scipy.stats import t as student_t

    q = float(student_t.ppf(0.975, max(m - n, 1)))
    return FitResult(
        scene=scene, variant=par.scene.variant, algorithm=algorithm, overrides=dict(overrides or {}),
        names=names, params=dict(zip(names, p.tolist())), stderr=dict(zip(names, err.tolist())),
        ci95={nm: (float(v - q * e), float(v + q * e)) for nm, v, e in zip(names, p, err)},
        start=dict(zip(names, p_start.tolist())), bounds={nm: (float(a), float(b)) for nm, a, b in zip(names, lo, hi)},
        window=None if edges is None else float(edges[1] - edges[0]),
        covariance=cov, residual_rms=float(np.sqrt(np.mean(r**2))), cost=cur["cost"], n_points=m,
        n_simulations=counts["simulations"], n_replans=counts["replans"], wall_s=time.perf_counter() - t_start,
        converged=converged, message=message or "converged", iterations=iterations, measurement=meas,
        fitted_force=cur["pointwise"], start_force=start_force, grid=grid_rows,
        local_fits=[{"number": o["number"] + 1, "start": dict(zip(names, o["p_start"].tolist())),
                     "end": dict(zip(names, o["cur"]["p"].tolist())),
                     "cost": o["cur"]["cost"], "converged": o["converged"], "message": o["message"] or "converged"}
                    for o in outcomes])


def _json_number(v):
    return v if math.isfinite(v) else None


def write_fit(result: FitResult, out: str) -> dict:
    """Write ``fit.json``, ``fit_history.csv`` and ``fit.png`` into ``out`` (and ``fit_grid.csv``, the
    global stage's runs, when there was one); returns the JSON dict."""
    os.makedirs(out, exist_ok=True)
    summary = {
        "scene": result.scene, "variant": result.variant, "algorithm": result.algorithm,
        "overrides": {k: str(v) for k, v in result.overrides.items()},
        "params": result.params, "stderr": {k: _json_number(v) for k, v in result.stderr.items()},
        "ci95": {k: [_json_number(a), _json_number(b)] for k, (a, b) in result.ci95.items()},
        "start": result.start, "bounds": {k: [a, _json_number(b)] for k, (a, b) in result.bounds.items()},
        "covariance": [[_json_number(float(v)) for v in row] for row in result.covariance],
        "window": result.window, "residual_rms": result.residual_rms, "n_points": result.n_points,
        "n_simulations": result.n_simulations, "n_replans": result.n_replans,
        "wall_s": result.wall_s, "converged": result.converged, "message": result.message,
        "measurement": result.measurement.source,
    }
    if result.grid:
        summary["global_stage"] = {"points": len(result.grid),
                                   "failed": sum(not row["converged"] for row in result.grid),
                                   "file": "fit_grid.csv",
                                   "local_fits": [{**lf, "cost": _json_number(lf["cost"])} for lf in result.local_fits]}
        with open(os.path.join(out, "fit_grid.csv"), "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(result.grid[0]))
            w.writeheader()
            w.writerows(result.grid)
    with open(os.path.join(out, "fit.json"), "w") as f:
        json.dump(summary, f, indent=2)
    keys = list(result.iterations[0])
    with open(os.path.join(out, "fit_history.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(result.iterations)
    _plot(result, os.path.join(out, "fit.png"))
    return summary


def _plot(result: FitResult, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    live = [n for n in result.names if len({row[n] for row in result.grid}) > 1]
    if live and len(live) <= 2:
        fig, (ax, bx, gx) = plt.subplots(1, 3, figsize=(16, 4.2))
        _plot_grid(result, live, gx)
    else:
        fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
    x = result.measurement.displacement
    ax.plot(x, result.measurement.force, ".", ms=3, color="0.4", label="measured")
    ax.plot(x, result.start_force, "--", color="tab:blue", lw=1,
            label="start: " + ", ".join(f"{k} = {v:.4g}" for k, v in result.start.items()))
    ax.plot(x, result.fitted_force, "-", color="tab:red", lw=1.5,
            label="fitted: " + ", ".join(f"{k} = {v:.5g} +/- {result.stderr[k]:.2g}" for k, v in result.params.items()))
    ax.set_xlabel("drawing displacement (mm)")
    ax.set_ylabel("drawing force (N/mm)")
    ax.set_title(f"{result.scene} {result.variant}: measured and fitted drawing force")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    # With several starts, the history of the one kept.
    kept = min(result.local_fits, key=lambda lf: lf["cost"])["number"] if len(result.local_fits) > 1 else None
    its = [row for row in result.iterations if row["accepted"] and row.get("start", kept) == kept]
    bx.semilogy([row["iteration"] for row in its], [max(row["cost"], 1e-300) for row in its], "o-", color="k",
                label="misfit |r|^2/2 (accepted)")
    bx.set_xlabel("Levenberg-Marquardt trial")
    bx.set_ylabel("misfit (N/mm)^2")
    bx.grid(alpha=0.3)
    cx = bx.twinx()
    for name in result.names:
        start = result.start[name] if result.start[name] != 0 else 1.0
        cx.plot([row["iteration"] for row in its], [row[name] / start for row in its], "s--", ms=3,
                label=f"{name} / start")
    cx.set_ylabel("parameter / start value")
    lines = bx.get_legend_handles_labels()
    more = cx.get_legend_handles_labels()
    bx.legend(lines[0] + more[0], lines[1] + more[1], fontsize=8)
    bx.set_title(f"convergence: {result.n_simulations} simulations, {result.wall_s:.1f} s"
                 + ("" if result.converged else " (not converged)"))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _plot_grid(result: FitResult, live: list, ax) -> None:
    """The global stage: misfit of every grid run (log colour; x: failed run) and the path of the
    Levenberg-Marquardt iterates from the chosen start."""
    import matplotlib.colors as mcolors

    rows = result.grid
    ok = [r for r in rows if r["converged"]]
    its = [row for row in result.iterations if row["accepted"]]
    if len(live) == 1:
        (a,) = live
        ax.semilogy([r[a] for r in ok], [max(r["cost"], 1e-300) for r in ok], "o-", color="k", ms=3,
                    label="grid runs")
        ax.axvline(result.start[a], color="tab:blue", ls="--", lw=1, label="start of the fit")
        ax.axvline(result.params[a], color="tab:red", lw=1, label="fitted")
        ax.set_xlabel(a)
        ax.set_ylabel("misfit (N/mm)^2")
    else:
        a, b = live
        costs = np.array([max(r["cost"], 1e-300) for r in ok])
        sc = ax.scatter([r[a] for r in ok], [r[b] for r in ok], c=costs, cmap="viridis", s=28,
                        norm=mcolors.LogNorm(vmin=costs.min(), vmax=costs.max()))
        bad = [r for r in rows if not r["converged"]]
        if bad:
            ax.plot([r[a] for r in bad], [r[b] for r in bad], "x", color="0.5", label="run failed")
        ax.plot([r[a] for r in its], [r[b] for r in its], ".-", color="tab:red", ms=4, lw=1,
                label="Levenberg-Marquardt iterates")
        ax.plot(result.start[a], result.start[b], "s", mfc="none", color="tab:blue",
                label="start (interpolated minimum)")
        ax.figure.colorbar(sc, ax=ax, label="misfit (N/mm)^2")
        ax.set_xlabel(a)
        ax.set_ylabel(b)
    ax.set_title(f"global stage: {len(rows)} adaptive runs", fontsize=10)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
