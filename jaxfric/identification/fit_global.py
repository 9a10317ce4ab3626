"""The global stage of an identification (:func:`jaxfric.identification.fit.fit` with a ``grid``): the grid of
parameter values at which adaptive runs are made, and the minima of the misfit of the observations
interpolated multilinearly between them, from which the least-squares fit starts.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["grid_axes", "surrogate_minima", "MAX_GRID_POINTS"]

MAX_GRID_POINTS = 10_000  # adaptive runs of the global stage (``grid``), every axis combined


def grid_axes(grid, names, lo, hi) -> list:
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


def surrogate_minima(axes: list, obs: np.ndarray, observed: np.ndarray, count: int, refine: int = 10) -> list:
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
    field = cost.reshape(shape)
    # The lowest lattice minima are polished, more of them than asked for: in a valley narrower than
    # the lattice spacing the lowest lattice point need not lie in the lowest basin.
    chosen = _lattice_minima(field)[:max(8, 4 * count)]

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


def _lattice_minima(field: np.ndarray) -> np.ndarray:
    """Indices (k, ndim) of the lattice points of ``field`` with no lower neighbour along any axis (a
    plateau keeps all its points; inf is no minimum), lowest first."""
    shape = field.shape
    padded = np.pad(field, 1, constant_values=np.inf)
    centre = tuple(slice(1, -1) for _ in shape)
    lowest = np.isfinite(field)
    for ax in range(len(shape)):
        for shift in (-1, 1):
            neighbour = tuple(slice(1 + shift, n + 1 + shift) if i == ax else centre[i] for i, n in enumerate(shape))
            lowest &= field <= padded[neighbour]
    index = np.stack(np.unravel_index(np.flatnonzero(lowest.reshape(-1)), shape), axis=-1)
    return index[np.argsort(field[tuple(index.T)], kind="stable")]
