"""The outcome of an identification (:func:`jaxfric.identification.fit.fit`) and its files: ``fit.json``,
``fit_history.csv``, ``fit.png`` and, after a global stage, ``fit_grid.csv``.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os

import numpy as np

from .fit_data import Measurement

__all__ = ["FitResult", "write_fit"]


@dataclasses.dataclass
class FitResult:
    """Outcome of :func:`jaxfric.identification.fit.fit`.

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
        iterations: per simulation of the local stage, a dict (iteration, run: "replay" of the frozen
            sequence or "adaptive" run at the optimum, accepted, cost, params).
        measurement: the :class:`Measurement`; fitted_force, start_force: simulated force at the
            measured displacements (pointwise, whatever ``window``), at the optimum and at the start.
        grid: the global stage (``grid`` argument): per grid point, a dict of its parameters, its
            misfit (inf where the run failed) and ``converged``; empty without one. ``start`` is
            then the point the global stage chose.
        local_fits: per start of the local stage (``starts``), a dict of its number (the
            ``start`` column of ``iterations`` when there are several), its start and end
            (parameters), misfit, converged and message; the result is the lowest misfit's.
        model_error: None, or the model's discretisation error carried into the parameters
            (:func:`jaxfric.identification.fit_model_error.model_error`: its ``bias`` per parameter, per
            component, and ``bound``, the sum of the components' magnitudes); ci95_model: {name: (low,
            high)}, the 95 % interval widened by that bound.
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
    model_error: dict | None = None
    ci95_model: dict = dataclasses.field(default_factory=dict)


def _json_number(v):
    """``v``, or None (JSON null) where it is not finite."""
    return v if math.isfinite(v) else None


def _override_text(field: str, value) -> str:
    """An override as ``fit.json`` records it: the mesh (nx, ny) as "NXxNY", anything else as str()."""
    if field == "mesh" and isinstance(value, (tuple, list)) and len(value) == 2:
        return "x".join(str(v) for v in value)
    return str(value)


def write_fit(result: FitResult, out: str) -> dict:
    """Write ``fit.json``, ``fit_history.csv`` and ``fit.png`` into ``out`` (and ``fit_grid.csv``, the
    global stage's runs, when there was one); returns the JSON dict."""
    os.makedirs(out, exist_ok=True)
    summary = {
        "scene": result.scene, "variant": result.variant, "algorithm": result.algorithm,
        "overrides": {k: _override_text(k, v) for k, v in result.overrides.items()},
        "params": result.params, "stderr": {k: _json_number(v) for k, v in result.stderr.items()},
        "ci95": {k: [_json_number(a), _json_number(b)] for k, (a, b) in result.ci95.items()},
        "start": result.start, "bounds": {k: [_json_number(a), _json_number(b)] for k, (a, b) in result.bounds.items()},
        "covariance": [[_json_number(float(v)) for v in row] for row in result.covariance],
        "window": result.window, "residual_rms": result.residual_rms, "n_points": result.n_points,
        "n_simulations": result.n_simulations, "n_replans": result.n_replans,
        "wall_s": result.wall_s, "converged": result.converged, "message": result.message,
        "measurement": result.measurement.source,
    }
    if result.model_error is not None:
        summary["model_error"] = {
            "bias": result.model_error["bias"], "bound": result.model_error["bound"],
            "components": result.model_error["components"],
            "ci95": {k: [a, b] for k, (a, b) in result.ci95_model.items()},
            "max_observation_error": float(np.max(np.abs(result.model_error["observation_error"]))),
            "wall_s": result.model_error["wall_s"]}
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
    """``fit.png``: measured, start and fitted force; the misfit and parameters per accepted trial; the
    global stage's misfit where it varies one or two parameters."""
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
    bx.set_xlabel("simulation of the fit (frozen-sequence replays, then adaptive runs)")
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
    least-squares iterates from the chosen start."""
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
                label="least-squares iterates")
        ax.plot(result.start[a], result.start[b], "s", mfc="none", color="tab:blue",
                label="start (interpolated minimum)")
        ax.figure.colorbar(sc, ax=ax, label="misfit (N/mm)^2")
        ax.set_xlabel(a)
        ax.set_ylabel(b)
    ax.set_title(f"global stage: {len(rows)} adaptive runs", fontsize=10)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
