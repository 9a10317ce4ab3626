"""The measured drawing-force curve of an identification (:mod:`jaxfric.identification.fit`) and the observations
fitted to it: the force at every measured displacement, or its means over windows.

A measurement is a CSV (or a mapping of arrays) with at least the columns ``drawing_displacement``
(mm) and ``drawing_force`` (N/mm). Rows at displacement <= 0 are dropped (before drawing the force is
not a drawing force, and a ``history.csv`` written by ``jaxfric run`` carries its clamping rows there);
the remaining displacements must increase strictly.
"""

from __future__ import annotations

import csv
import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np

from ..numerics._checks import check_positive

__all__ = ["Measurement", "read_measurement", "bin_means", "window_edges", "observations", "curve_columns",
           "MAX_MAGNITUDE", "MAX_WINDOWS"]

_COLUMNS = ("drawing_displacement", "drawing_force")
# Beyond these a measured value is not a sheet-drawing measurement (and its squares overflow the misfit).
MAX_MAGNITUDE = {"drawing_displacement": 1e6, "drawing_force": 1e12}  # mm, N/mm
MAX_WINDOWS = 100_000  # fitted windows (``window``)


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
        columns = _read_csv(source)
    else:
        source = "data"
        columns = _read_mapping(data)
    return _measurement(columns, source)


def _read_csv(source: str) -> dict[str, np.ndarray]:
    """The two columns of the CSV file ``source`` as float arrays (ValueError naming the file, and the
    column and row of a bad value)."""
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
    return columns


def _read_mapping(data) -> dict[str, np.ndarray]:
    """The two columns of the mapping ``data`` as flat float arrays of equal length (ValueError
    naming the field ``data``)."""
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
    return columns


def _measurement(columns: dict[str, np.ndarray], source: str) -> Measurement:
    """The measurement of the columns read from ``source``: values finite and within
    :data:`MAX_MAGNITUDE`, the rows at displacement > 0, the displacement strictly increasing."""
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


def window_edges(x: np.ndarray, window, n_params: int):
    """Window edges over [x_0, x_last] of width about ``window`` (mm), or None (pointwise). Raises
    ValueError naming the field ``window`` when it leaves more than :data:`MAX_WINDOWS` windows, or
    fewer than ``n_params``."""
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


def curve_columns(history: dict) -> dict[str, np.ndarray]:
    """The columns of a run's history that :func:`observations` reads (displacement and force)."""
    return {c: np.asarray(history[c]) for c in _COLUMNS}


def observations(history: dict, x: np.ndarray, edges):
    """The fitted observations of a completed run: its drawing force interpolated linearly at the
    measured displacements ``x`` (mm), or its means over the windows ``edges`` (None: pointwise), as
    :class:`jaxfric.identification.fit_curve.Curve` computes them along a replay."""
    xr, fr = np.asarray(history["drawing_displacement"]), np.asarray(history["drawing_force"])
    return np.interp(x, xr, fr) if edges is None else bin_means(xr, fr, edges)
