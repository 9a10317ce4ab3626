"""mu of the Nine test fitted to curves the fitting model did not make, against the fit mesh:
``python experiments/fit_bias_mesh.py [--meshes 50x2,100x2,200x2,300x3] [--cases ...]``.

The data (each a run of ``nine --variant mu017``, mu = 0.17, U_draw = 10 mm; what the fitting model
is not):
- ``reference``: exact contact (``lcp_ssn``) on 1200 x 3 at half the nominal increments (dq_clamp = dU
  = 0.05 mm), the accuracy tests' reference discretisation of the Nine (docs/results.md, accuracy);
- ``noise1pct-sN``: the reference curve with independent Gaussian noise of 1 % of its mean drawing force
  added to every row (seed N);
- ``penalty600x3``: another algorithm at another mesh: penalty contact (the spec's eps_n = 1e5) on 600 x 3
  at the nominal increments;
- ``sigma_y+3pct``: the reference discretisation with a yield stress 3 % above the fitting model's
  (a sheet whose material differs from its data sheet: the bias this carries into mu);
- ``quadratic600x3``: elements quadratic along the strip (``anst``, 4 points through each element) on
  600 x 3 at half the nominal increments, converged along the strip within 0.2 % (docs/results.md,
  elements quadratic along the strip): the data of a fit by that element on a coarser mesh.

Every fit is the command a user runs, ``jaxfric fit nine --data CSV --param mu --mesh M --set U_draw=10
--set mu=0.12 --window 1`` (exact contact, re-planned to the adaptive run at the optimum), through
:func:`jaxfric.identification.fit.fit`. The ``reference`` curve is fitted at every mesh of ``--meshes``
(the bias against the fit mesh), the other data at ``--at`` (the recommended fit mesh); ``--set
NAME=VALUE`` changes the fitting model (e.g. ``element=anst``, ``thickness_points=4``), recorded in the
``fit_settings`` column; ``--stroke S`` draws the data and the fits S mm (data files of their own) and
``--steady U0`` fits only the data from U0 on (a steady window); ``--model-error step,mesh,layers`` adds
the fitting model's own estimate of its discretisation error in mu (``jaxfric fit --model-error``) and the
interval widened by it.

Writes ``experiments/results/fit_bias_mesh.csv`` (a row per fit, after every fit) and ``.png``; the
data curves are kept in ``experiments/results/fit_bias_mesh/DATA.csv`` (drawing displacement and
force), so a rerun fits them without simulating them again.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

import jaxfric
from benchutil import read_rows, write_rows
from jaxfric import scenes
from jaxfric.identification.fit import fit

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
DATA_DIR = os.path.join(RESULTS, "fit_bias_mesh")
TRUE_MU = 0.17
STROKE = 10.0
REFERENCE = {"mesh": "1200x3", "dq_clamp": 0.05, "dU": 0.05}
DATA = {
    "reference": ("lcp_ssn", REFERENCE),
    "penalty600x3": ("penalty", {"mesh": "600x3"}),
    "sigma_y+3pct": ("lcp_ssn", {**REFERENCE, "sigma_y": 171.0 * 1.03}),
    "quadratic600x3": ("lcp_ssn", {"mesh": "600x3", "dq_clamp": 0.05, "dU": 0.05, "element": "anst",
                                   "thickness_points": 4, "element_order": 2}),
}
NOISE = 0.01


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", default="50x2,100x2,200x2,300x3", help="fit meshes of the reference curve")
    ap.add_argument("--at", default="100x2", help="fit mesh of the other data")
    ap.add_argument("--seeds", default="0,1,2", help="noise draws on the reference curve")
    ap.add_argument("--cases", default="", help="only these DATA@MESH cases (comma-separated)")
    ap.add_argument("--set", dest="settings", action="append", default=[], metavar="NAME=VALUE",
                    help="a config value of the fitting model (e.g. element=anst), as jaxfric fit's --set")
    ap.add_argument("--stroke", type=float, default=STROKE,
                    help="drawing stroke of the data and of the fits (mm); other than 10: its own data files")
    ap.add_argument("--steady", type=float, default=None, metavar="U0",
                    help="fit only the data from U0 mm to the stroke (a steady window; default: all of it)")
    ap.add_argument("--model-error", default="", metavar="C[,C...]",
                    help="also carry the fitting model's discretisation error into the interval (step, mesh, "
                         "layers; jaxfric fit --model-error)")
    a = ap.parse_args(argv)
    components = tuple(filter(None, a.model_error.split(",")))
    settings = dict(s.split("=", 1) for s in a.settings)
    label = " ".join(a.settings + ([f"U_draw={a.stroke:g}"] if a.stroke != STROKE else [])
                     + ([f"from={a.steady:g}"] if a.steady is not None else [])) or "defaults"
    cases = [("reference", m) for m in a.meshes.split(",")]
    cases += [(f"noise1pct-s{s}", a.at) for s in a.seeds.split(",") if s]
    cases += [(d, a.at) for d in DATA if d != "reference"]
    if a.cases:
        wanted = set(a.cases.split(","))
        cases = [c for c in cases if f"{c[0]}@{c[1]}" in wanted]
    path = os.path.join(RESULTS, "fit_bias_mesh.csv")
    mine: list[dict] = []
    for data, mesh in cases:
        measured = _data(data, a.stroke)
        if a.steady is not None:
            keep = measured["drawing_displacement"] >= a.steady - 1e-9
            measured = {k: v[keep] for k, v in measured.items()}
        overrides = {"mesh": mesh, "U_draw": a.stroke, "mu": 0.12, **settings}
        res = fit("nine", measured, ["mu"], variant="mu017", overrides=overrides, window=1.0, progress=True,
                  model_error=components)
        lo, hi = res.ci95["mu"]
        row = {"data": data, "fit_mesh": mesh, "fit_settings": label, "mu": res.params["mu"],
               "error": res.params["mu"] - TRUE_MU,
               "rel_error_pct": 100 * (res.params["mu"] / TRUE_MU - 1), "stderr": res.stderr["mu"], "ci_low": lo,
               "ci_high": hi, "inside": bool(lo <= TRUE_MU <= hi), "residual_rms": res.residual_rms,
               "converged": res.converged, "n_simulations": res.n_simulations, "wall_s": round(res.wall_s, 1),
               **_model_error_columns(res)}
        mine.append(row)
        print(" ".join(f"{k}={v:.6g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()), flush=True)
        # Merged with the file as it is now (other invocations may have written rows meanwhile).
        done = {_key(r) for r in mine}
        rows = [r for r in read_rows(path) if _key(r) not in done] + mine
        columns = list(dict.fromkeys(k for r in rows for k in r))
        write_rows(path, [{k: r.get(k, "") for k in columns} for r in rows])
    _plot(read_rows(path), os.path.join(RESULTS, "fit_bias_mesh.png"))


def _key(row: dict) -> tuple:
    return row["data"], row["fit_mesh"], row.get("fit_settings", "defaults")


def _model_error_columns(res) -> dict:
    """The model-error estimate's columns (empty without one): the bias per component and in all, and
    the interval widened by it."""
    if res.model_error is None:
        return {}
    lo, hi = res.ci95_model["mu"]
    return {"model_error": "+".join(res.model_error["components"]), "model_bias": res.model_error["bias"]["mu"],
            "model_bound": res.model_error["bound"]["mu"],
            **{f"bias_{c}": v["mu"] for c, v in res.model_error["components"].items()},
            "ci_model_low": lo, "ci_model_high": hi, "inside_model": bool(lo <= TRUE_MU <= hi),
            "model_error_s": round(res.model_error["wall_s"], 1)}


def _data(name: str, stroke: float = STROKE) -> dict:
    """The data curve ``name`` drawn ``stroke`` mm (simulated once, then read from DATA_DIR: ``NAME.csv``
    for the 10 mm stroke, ``NAME-U<stroke>.csv`` for another)."""
    base = "reference" if name.startswith("noise") else name
    path = os.path.join(DATA_DIR, f"{base}.csv" if stroke == STROKE else f"{base}-U{stroke:g}.csv")
    if not os.path.exists(path):
        algorithm, overrides = DATA[base]
        sc = scenes.make("nine", "mu017", algorithm, {**overrides, "U_draw": stroke})
        t0 = time.perf_counter()
        res = jaxfric.run(sc.model, control=sc.control, observe=sc.observe, progress=False)
        if not res.converged:
            raise RuntimeError(f"data run {base} failed: {res.message}")
        print(f"data {base}: {len(res.history['time'])} rows, {time.perf_counter() - t0:.1f} s", flush=True)
        os.makedirs(DATA_DIR, exist_ok=True)
        write_rows(path, [{"drawing_displacement": u, "drawing_force": f} for u, f in
                          zip(res.history["drawing_displacement"].tolist(), res.history["drawing_force"].tolist())])
    rows = read_rows(path)
    u = np.array([float(r["drawing_displacement"]) for r in rows])
    f = np.array([float(r["drawing_force"]) for r in rows])
    if name.startswith("noise"):
        seed = int(name.rpartition("-s")[2])
        draw = u > 0
        f = f + NOISE * float(np.mean(f[draw])) * np.random.default_rng(seed).standard_normal(f.size)
    return {"drawing_displacement": u, "drawing_force": f}


def _plot(rows: list[dict], path: str) -> None:
    """mu against the fit mesh: one line per data, fitting model and number of layers, with the 95 %
    interval (and, where estimated, the interval widened by the model's error, light)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(13, 5.2))
    groups = dict.fromkeys((r["data"], r["fit_settings"], str(r["fit_mesh"]).split("x")[1]) for r in rows)
    for k, (data, label, layers) in enumerate(groups):
        sel = sorted((r for r in rows if (r["data"], r["fit_settings"], str(r["fit_mesh"]).split("x")[1])
                      == (data, label, layers)), key=lambda r: int(str(r["fit_mesh"]).split("x")[0]))
        x = np.array([int(str(r["fit_mesh"]).split("x")[0]) for r in sel]) * (1 + 0.012 * k)  # offsets
        mu = np.array([float(r["mu"]) for r in sel])
        half = np.array([float(r["ci_high"]) - float(r["mu"]) for r in sel])
        name = f"{data}, {layers} layers" + ("" if label == "defaults" else f", {label}")
        line = ax.errorbar(x, mu, yerr=half, fmt="o-" if len(sel) > 1 else "s", capsize=3, label=name,
                           color=plt.cm.tab20(k % 20))  # more groups than the default cycle has colours
        model = [(xi, m, float(r["ci_model_low"]), float(r["ci_model_high"])) for xi, m, r in zip(x, mu, sel)
                 if r.get("ci_model_low")]
        for xi, m, lo, hi in model:
            ax.plot([xi, xi], [lo, hi], color=line[0].get_color(), alpha=0.35, lw=6, solid_capstyle="butt")
    ax.plot([], [], color="0.5", alpha=0.35, lw=6, label="95 % with the model's error (--model-error)")
    ax.axhline(TRUE_MU, color="k", lw=1, label="truth 0.17")
    ax.axhspan(TRUE_MU - 0.005, TRUE_MU + 0.005, color="0.88", label="goal: within 0.005")
    ax.set_xscale("log")
    ax.set_ylim(0.09, 0.23)
    ax.set_xticks([50, 100, 150, 200, 300])
    ax.set_xticklabels(["50", "100", "150", "200", "300"])
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("elements along the strip of the fit mesh")
    ax.set_ylabel("fitted mu (95 % interval)")
    ax.set_title("Nine mu017: mu fitted to curves the fitting model did not make\n(the interval with the model's "
                 "error at 100 x 2 runs from 0.02 to 0.32)", fontsize=9)
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    ax.grid(alpha=0.3)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


if __name__ == "__main__":
    main()
