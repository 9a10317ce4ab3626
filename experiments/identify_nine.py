"""Identification of mu (and R1) from synthetic drawing-force curves of the Nine test:
``python experiments/identify_nine.py [--mesh 100x2] [--stroke 10] [--window 1] [--draws 10]``.

1. The measurement: ``jaxfric run nine --variant mu017 --algorithm penalty`` at the given mesh and stroke
   (mu = 0.17, R1 = 5.5 mm), its ``drawing_displacement`` and ``drawing_force`` columns. The fits run on
   the penalty path too: the same model, so this study measures the optimiser, the noise and the
   intervals, not the model's error (``docs/results.md``, identification, for a curve from a finer model).
2. Noise-free: fit mu from 0.12, and mu and R1 together from (0.12, 5.2 mm); the error of the
   recovered values.
3. With noise: ten draws of independent Gaussian noise of standard deviation 1 % of the mean measured
   force added to every point (seeds 0..9); for each, the fitted values, their standard errors and
   whether the true values lie inside the reported 95 % intervals. These fits keep the step sequence
   planned at the start values (``max_replans=0``): all draws then share one compiled simulation
   (about 1 min a fit instead of 5). What that costs in accuracy is measured by the noise-free fit on
   the same terms (row ``none, start plan``): its distance to the truth is the bias the draws carry.

**Global stage for mu + R1** (``--grid``, default ``mu=0.101:0.251:7,R1=5.07:5.97:9``, chosen so that the
truth lies on no grid line): the two parameters compensate each other, and the windowed misfit has local
minima along the valley they leave (``scan_joint_misfit.py``), so the joint fits start from the minimum
of the misfit interpolated between adaptive runs on a grid (``jaxfric.identification.fit.fit(..., grid=...)``; the truth
is not a grid point). The grid's runs do not depend on the data: the noise draws reuse them.
``--params mu,R1`` runs one parameter set and keeps the CSV rows of the others.

**The draws seen by the linearised model** (``_Linear``): for every draw, the estimate and interval
of the model linearised at the truth (columns ``*_linear_*``), and the coverage of those intervals
over 4000 draws (``identify_nine_linear.csv``): which misses belong to the draw, which to the fit.

Writes ``experiments/results/identify_nine.csv`` and ``identify_nine.png``. At 100 x 2 the mean force
over 1 mm windows is a smooth, monotone function of mu (0.10 ... 0.20); at 40 x 2 it is not (the
force ripples by +/- 20 % as the 2.5 mm elements pass over the cylinders, and the misfit has local
minima), so the mesh matters more than the optimiser here.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

import jaxfric
from benchutil import write_rows
from jaxfric import scenes
from jaxfric.cli import parse_grid
from jaxfric.identification.fit import bin_means, fit
from jaxfric.identification.fit_curve import Curve
from jaxfric.identification.fit_data import window_edges
from jaxfric.identification.params import parameterize

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
TRUE = {"mu": 0.17, "R1": 5.5}
START = {"mu": 0.12, "R1": 5.2}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default="100x2")
    ap.add_argument("--stroke", type=float, default=10.0, help="U_draw (mm)")
    ap.add_argument("--window", type=float, default=1.0, help="fitted window length (mm)")
    ap.add_argument("--draws", type=int, default=10)
    ap.add_argument("--seeds", help="comma-separated noise seeds instead of 0 .. draws-1 (parallel runs)")
    ap.add_argument("--noise", type=float, default=0.01, help="noise std / mean force")
    ap.add_argument("--params", default="mu;mu,R1", help="parameter sets to fit, ';'-separated")
    ap.add_argument("--grid", default="mu=0.101:0.251:7,R1=5.07:5.97:9",
                    help="global stage of the fits of more than one parameter (NAME=LOW:HIGH:N,...); '' for none")
    ap.add_argument("--tag", default="", help="suffix of the CSV and figure names (parallel runs)")
    ap.add_argument("--no-clean", action="store_true", help="only the noise draws")
    ap.add_argument("--clean", choices=("both", "start-plan"), default="both",
                    help="noise-free cases: both (re-planned and start plan) or only the start-plan one")
    ap.add_argument("--merge", metavar="TAG[,TAG]", help="only merge the rows of identify_nine<TAG>.csv (runs made "
                    "with --tag) into identify_nine.csv, replacing rows of the same case, and redraw the figure")
    ap.add_argument("--verbose", action="store_true", help="the fits' progress lines (grid points, trials)")
    ap.add_argument("--draw-replans", type=int, default=0, help="re-plans allowed in the noise fits")
    ap.add_argument("--starts", type=int, default=1, help="local fits from the lowest minima of the global stage")
    a = ap.parse_args(argv)
    if a.merge:
        rows = _read(os.path.join(RESULTS, "identify_nine.csv"))
        for tag in a.merge.split(","):
            more = _read(os.path.join(RESULTS, f"identify_nine{tag}.csv"))
            done = {(r["params"], r["noise"]) for r in more}
            rows = [r for r in rows if (r["params"], r["noise"]) not in done] + more
        clean, sigma, history = _measurement(a)
        oracle = _Linear(a, history, clean, sigma)
        for r in rows:
            if str(r["noise"]).startswith("seed"):
                r["residual_rms_truth"] = _truth_rms(clean, sigma, int(r["noise"][4:]), r["window_mm"])
                r.update(oracle.row(r["params"].split("+"), int(r["noise"][4:])))
        _write_coverage(oracle, sorted({r["params"] for r in rows}))
        seed = lambda r: int(r["noise"][4:]) if str(r["noise"]).startswith("seed") else -1  # noqa: E731
        save(sorted(rows, key=lambda r: (r["params"] != "mu", seed(r))))
        return
    seeds = [int(v) for v in a.seeds.split(",")] if a.seeds else list(range(a.draws))
    specs = list(filter(None, a.grid.split(",")))
    grid = parse_grid(specs, [spec.partition("=")[0].strip() for spec in specs])
    path = os.path.join(RESULTS, f"identify_nine{a.tag}.csv")
    ran = {"+".join(group.split(",")) for group in a.params.split(";")}
    kept = [r for r in _read(path) if r["params"] not in ran]
    base = {"mesh": a.mesh, "U_draw": a.stroke}
    clean, sigma, history = _measurement(a)
    oracle = _Linear(a, history, clean, sigma) if seeds else None
    rows = []
    for names in (tuple(group.split(",")) for group in a.params.split(";")):
        start = {**base, **{n: START[n] for n in names}}
        clean_cases = [("none", None, 4)] * (a.clean == "both") + [("none, start plan", None, 0)]
        cases = ([] if a.no_clean else clean_cases) + [(f"seed{s}", s, a.draw_replans) for s in seeds]
        stage = {n: v for n, v in grid.items() if n in names} if len(names) > 1 else None
        for label, seed, replans in cases:
            data = _noisy(clean, sigma, seed)
            res = fit("nine", data, names, variant="mu017", algorithm="penalty", overrides=start, window=a.window,
                      max_replans=replans, grid=stage or None, starts=a.starts if stage else 1, progress=a.verbose)
            row = {"params": "+".join(names), "noise": label, "mesh": a.mesh, "window_mm": a.window,
                   "converged": res.converged, "n_simulations": res.n_simulations, "n_replans": res.n_replans,
                   "wall_s": round(res.wall_s, 1), "residual_rms": res.residual_rms,
                   "residual_rms_truth": "" if seed is None else _truth_rms(clean, sigma, seed, a.window),
                   "grid_points": len(res.grid), "start": " ".join(f"{n}={res.start[n]:.6g}" for n in names),
                   "local_fits": len(res.local_fits)}
            for n in names:
                lo, hi = res.ci95[n]
                row.update({f"{n}": res.params[n], f"{n}_err": res.params[n] - TRUE[n], f"{n}_stderr": res.stderr[n],
                            f"{n}_ci_low": lo, f"{n}_ci_high": hi, f"{n}_inside": bool(lo <= TRUE[n] <= hi)})
            if seed is not None:
                row.update(oracle.row(names, seed))
            rows.append(row)
            print(" ".join(f"{k}={v:.6g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()), flush=True)
            save(kept + rows, a.tag)  # after every fit: a run stopped halfway keeps what it computed
    if oracle is not None and not a.tag:
        _write_coverage(oracle, sorted({r["params"] for r in kept + rows}))


def _measurement(a):
    """The synthetic measurement (the run at the truth) and the noise's standard deviation."""
    sc = scenes.make("nine", "mu017", "penalty", {"mesh": a.mesh, "U_draw": a.stroke})
    t0 = time.perf_counter()
    h = jaxfric.run(sc.model, control=sc.control, observe=sc.observe, progress=False).history
    print(f"measurement: {len(h['time'])} rows, {time.perf_counter() - t0:.1f} s", flush=True)
    clean = {"drawing_displacement": h["drawing_displacement"], "drawing_force": h["drawing_force"]}
    return clean, a.noise * float(np.mean(h["drawing_force"][h["drawing_displacement"] > 0])), h


class _Linear:
    """The noise draws seen by the model linearised at the truth, on the measurement's own step
    sequence: the Jacobian J of the fitted observations at the true values (forward mode; the same
    curve the fit uses), and for a draw with observation noise e the estimate p_true + (J^T J)^-1 J^T e
    with its Gauss-Newton interval. This is what the fit would report if the model were linear and
    free of discretisation error: a draw whose linearised interval misses the truth is one no
    correct 95 % interval is expected to hold (one in twenty), whatever the optimiser; the gap between
    a fit's error and this one is the model's (nonlinearity, step sequence)."""

    def __init__(self, a, history, clean, sigma):
        from scipy.stats import t as student_t

        t0 = time.perf_counter()
        names = tuple(TRUE)
        par = parameterize("nine", names, variant="mu017", overrides={"mesh": a.mesh, "U_draw": a.stroke})
        x = np.asarray(clean["drawing_displacement"])
        self.keep = x > 0
        self.x = x[self.keep]
        self.edges = None if a.window in (None, "") else window_edges(self.x, float(a.window), len(names))
        obs, jac, _, code, _ = Curve(par, history, self.x, self.edges, None)(np.array([TRUE[n] for n in names]))
        if code != 0:
            raise RuntimeError(f"the replay at the truth fails ({code})")
        self.names, self.jac, self.sigma, self.n_rows = names, jac, sigma, x.size
        self.t_crit = lambda dof: float(student_t.ppf(0.975, dof))
        print(f"linearised model at the truth: {time.perf_counter() - t0:.1f} s, replay-data gap "
              f"{np.max(np.abs(obs - self.observe(np.asarray(clean['drawing_force'])))):.1e} N/mm", flush=True)

    def observe(self, force):
        force = force[self.keep]
        return force if self.edges is None else bin_means(self.x, force, self.edges)

    def estimate(self, names, noise):
        """Linearised error, standard error and inside flag per parameter for one noise vector."""
        J = self.jac[:, [self.names.index(n) for n in names]]
        e = self.observe(noise)
        dp, *_ = np.linalg.lstsq(J, e, rcond=None)
        left = e - J @ dp
        dof = max(J.shape[0] - J.shape[1], 1)
        se = np.sqrt(np.diag(np.linalg.inv(J.T @ J)) * (left @ left) / dof)
        return dp, se, np.abs(dp) <= self.t_crit(dof) * se

    def row(self, names, seed):
        dp, se, inside = self.estimate(names, _noise(self.sigma, seed, self.n_rows))
        out = {}
        for n, d, s, i in zip(names, dp, se, inside):
            out.update({f"{n}_linear_err": float(d), f"{n}_linear_stderr": float(s), f"{n}_linear_inside": bool(i)})
        return out

    def coverage(self, names, draws=4000, seed=12345):
        """Fraction of draws whose linearised intervals hold the truth, per parameter and jointly."""
        rng = np.random.default_rng(seed)
        hits = np.array([self.estimate(names, self.sigma * rng.standard_normal(self.n_rows))[2] for _ in range(draws)])
        return {**{n: float(hits[:, j].mean()) for j, n in enumerate(names)}, "all": float(hits.all(axis=1).mean()),
                "draws": draws}


def _write_coverage(oracle, groups):
    rows = []
    for group in groups:
        cov = oracle.coverage(group.split("+"))
        rows.append({"params": group, "draws": cov.pop("draws"), **{f"coverage_{k}": v for k, v in cov.items()}})
        print(f"linearised coverage of the 95 % intervals, {group}: {rows[-1]}", flush=True)
    write_rows(os.path.join(RESULTS, "identify_nine_linear.csv"), [{k: r.get(k, "") for k in dict.fromkeys(
        k for r in rows for k in r)} for r in rows])


def _noise(sigma, seed, n):
    """The draw of seed ``seed``: n independent Gaussian values of standard deviation sigma."""
    return sigma * np.random.default_rng(seed).standard_normal(n)


def _noisy(clean, sigma, seed):
    data = dict(clean)
    if seed is not None:
        data["drawing_force"] = clean["drawing_force"] + _noise(sigma, seed, len(clean["drawing_force"]))
    return data


def _truth_rms(clean, sigma, seed, window):
    """The residual rms of the model at the true values against a noise draw: the model there is the
    clean measurement itself, so no simulation is needed. A fit that ends above it stopped in a local
    minimum; one below it found a point that fits the draw better than the truth does."""
    x, f = (np.asarray(clean[k]) for k in ("drawing_displacement", "drawing_force"))
    keep = x > 0
    noisy = np.asarray(_noisy(clean, sigma, seed)["drawing_force"])[keep]
    x, f = x[keep], f[keep]
    if window is None or window == "":
        return float(np.sqrt(np.mean((noisy - f) ** 2)))
    edges = window_edges(x, float(window), 1)  # the fit's own windows
    return float(np.sqrt(np.mean((bin_means(x, noisy, edges) - bin_means(x, f, edges)) ** 2)))


def _read(path):
    import csv

    if not os.path.exists(path):
        return []
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    conv = {"True": True, "False": False, "": ""}
    for r in rows:
        for k, v in r.items():
            if v in conv:
                r[k] = conv[v]
                continue
            try:
                r[k] = float(v) if any(c in v for c in ".e") or k.endswith(("_err", "_stderr")) else int(v)
            except ValueError:
                pass
    return rows


def save(rows, tag=""):
    keys = list(dict.fromkeys(k for r in rows for k in r))
    write_rows(os.path.join(RESULTS, f"identify_nine{tag}.csv"), [{k: r.get(k, "") for k in keys} for r in rows])
    _plot(rows, os.path.join(RESULTS, f"identify_nine{tag}.png"))


def _plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = [("mu", "mu"), ("mu+R1", "mu"), ("mu+R1", "R1")]
    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    for ax, (group, name) in zip(axes, groups):
        noisy = [r for r in rows if r["params"] == group and r["noise"].startswith("seed")]
        if not noisy:
            ax.set_axis_off()
            continue
        y = np.arange(len(noisy))
        est = np.array([r[name] for r in noisy])
        lo = np.array([r[f"{name}_ci_low"] for r in noisy])
        hi = np.array([r[f"{name}_ci_high"] for r in noisy])
        ax.errorbar(est, y, xerr=[est - lo, hi - est], fmt="o", capsize=3, color="tab:blue", label="fit, 95 % interval")
        ax.axvline(TRUE[name], color="k", lw=1, label=f"true {name} = {TRUE[name]}")
        clean = [r for r in rows if r["params"] == group and r["noise"] == "none"]
        if clean:
            ax.axvline(clean[0][name], color="tab:red", ls="--", lw=1, label="noise-free fit")
        # A draw whose interval misses the truth even for the model linearised at the truth (_Linear).
        ax.set_yticks(y, [r["noise"] + (" (linearised: out)" if r.get(f"{name}_linear_inside") is False else "")
                          for r in noisy], fontsize=7)
        inside = sum(r[f"{name}_inside"] for r in noisy)
        ax.set_title(f"fit of {group}: {name} ({inside}/{len(noisy)} intervals hold the truth)", fontsize=9)
        ax.set_xlabel(name)
        ax.legend(fontsize=7)
    fig.suptitle("Nine test, identification from synthetic drawing forces with 1 % noise")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
