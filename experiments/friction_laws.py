"""Friction laws of pressure and speed identified from drawing curves: ``python experiments/friction_laws.py``.

    python experiments/friction_laws.py [--root DIR] [--noise 0.005] [--seed 1]
        [--card | --speed | --speed-figure | --speed-increments | --period | --pressure-speed]

The flat die (spec section 2, ``const_force``) at four clamping forces, 25, 50, 100 and 200 N/mm, so the
contact pressures span 0 to about 30 MPa. The "measured" curves (drawing force against drawing
displacement) are made with one law, friction falling with pressure, mu(p) = 0.18 - 0.004 p (p in MPa;
``--set friction_law=polynomial --set mu=0.18 --set mu_p=-0.004``), by exact contact
(``lcp_ssn``) at the reference discretisation, twice the elements along and through the thickness (480 x
4), drawn 50 um (the spec's 30 um end before the sheet slides as a whole at 200 N/mm). The fits run on
the penalty path (the spec's eps_N = 1e9) at the spec mesh (240 x 2), so neither the algorithm nor the
mesh of the data is the fitting model's:

- ``law``: (mu, mu_p) jointly, from the four curves at once;
- ``coulomb``: a constant mu from the same curves, what a Coulomb fit gets wrong;
- ``law_noisy``: (mu, mu_p) again with Gaussian noise of ``--noise`` times each curve's largest force
  added to every point (seeded).

Each fit is ``scipy.optimize.least_squares`` (trust region, bounded) on the residuals of all curves, with
the Jacobian by forward mode through each curve's whole loading path (one compiled path function takes
the clamping force as a third, fixed, parameter; ``jaxfric.identification.params``), and the 95 %
intervals of the Gauss-Newton covariance s^2 (J^T J)^-1 with Student's t. Writes
``experiments/results/friction_laws.csv`` (one row per fit), ``friction_laws_curves.csv`` (data and fitted
curves), ``friction_laws.png`` (the curves, the steady force against the clamping force, mu against p)
and, for the law fit, the OpenRadioss ``/FRICTION`` card and the mu(p) table
(``experiments/results/friction_laws/friction.rad``, ``friction.csv``). Reference runs go under
``--root`` (default ``runs/friction_laws``; a second call reads them back).

The speed law (``--speed``): LS-DYNA's decay law mu = mu_d + (mu_0 - mu_d) exp(-decay v), the curves of
the flat die at 50 N/mm drawn 0.1 mm at 0.25, 1 and 4 mm/s made by ``lcp_ssn`` at 480 x 4, fitted by
``lcp_ssn`` at 240 x 2 with five times the reference's increments (the Jacobian through the exact path's
implicit derivatives); the constant mu fitted to the same curves; ``friction_laws_speed.csv``,
``friction_laws_speed_curves.csv``, ``friction_laws_speed.png`` (``--speed-figure`` redraws it from the
two) and the fitted law's cards: LS-DYNA's card 2 (``friction_laws/friction_speed.k``) and OpenRadioss's
``/FRICTION`` with its exponential decay, ``Ifric`` = 4 (``friction_laws/friction_speed.rad``).
``--speed-increments``: the model at the true law against those curves, by mesh and increments
(``friction_laws_speed_increments.csv``). ``--period``: steady sliding against the speed filter's period
(``friction_laws_period.csv``). ``--falling``: which pressure laws the solvers take where the friction bound
mu(p) p falls as the pressure grows (:func:`falling`, ``friction_laws_falling.csv``).

The pressure-and-speed law (``--pressure-speed``): mu(p, v) = 0.18 - 0.004 p + 0.01 v (OpenRadioss's
``Ifric`` = 1 with C1 and C2), the flat die at 25 and 100 N/mm each drawn 50 um at 0.5 and 2 mm/s, the
four curves made as the pressure law's (``lcp_ssn`` at 480 x 4), fitted as the speed law's (``lcp_ssn``
at 240 x 2 with five times the increments): (mu, mu_p, mu_v) jointly from the four curves, with and
without noise, and a constant mu;
``friction_laws_pressure_speed.csv``, ``friction_laws_pressure_speed_curves.csv`` and the fitted law's
``/FRICTION`` block, ``friction_laws/friction_pressure_speed.rad``.

Then what the two fitted laws predict elsewhere (``--card``: only this part, from the table on disk):
shape1's bead card (restraining force against
penetration, :func:`jaxfric.cards.bead_card`) with the fitted mu(p) and with the constant mu, and the
contact pressures of its full-depth run (the bead presses far harder than the flat die, so the law is
used beyond the pressures it was fitted on): ``friction_laws_card.csv`` and ``friction_laws_card.png``, at
the blankholder's default element; ``friction_laws/card_notes.txt`` names the card runs that exact contact
did not complete and the penalty law made instead.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy import optimize, stats  # noqa: E402

from benchutil import write_rows  # noqa: E402
from jaxfric.cards.friction import friction_csv, lsdyna_friction, radioss_friction  # noqa: E402
from jaxfric.contact.friction import Polynomial, VelocityDecay  # noqa: E402
from jaxfric.identification.params import parameterize, path_function  # noqa: E402
from jaxfric.io.batch import run_case  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.join(HERE, "results")
CLAMPS = (25.0, 50.0, 100.0, 200.0)
TRUTH = {"mu": 0.18, "mu_p": -0.004}
LAW = {"friction_law": "polynomial"}

# Drawn 50 um, beyond the spec's 30: at 200 N/mm the sheet slides as a whole only from about 38 um on.
STROKE = {"U_draw": 0.05}
REFERENCE_MESH = "480x4"
# The law fit's curves: one per clamping force, made with the true law (reference_curves).
CLAMP_CASES = {f"F{F:g}": {**LAW, **STROKE, "F_clamp": F} for F in CLAMPS}
START = {"mu": 0.15, "mu_p": 0.0, "mu_v": 0.0}
BOUNDS = {"mu": (0.0, 1.0), "mu_p": (-0.05, 0.05), "mu_v": (-0.05, 0.05)}

# The pressure-and-speed law (--pressure-speed): two clamping forces, each at two drawing speeds.
PS_TRUTH = {"mu": 0.18, "mu_p": -0.004, "mu_v": 0.01}
PS_CASES = {f"F{F:g}_v{v:g}": {**LAW, **STROKE, "F_clamp": F, "draw_speed": v} for F in (25.0, 100.0)
            for v in (0.5, 2.0)}

# The speed law (--speed): LS-DYNA's decay, curves at three drawing speeds, one clamping force, drawn
# 0.1 mm so that each curve has its breakaway (mu_0) and its steady sliding at its speed (mu(v)).
SPEEDS = (0.25, 1.0, 4.0)
SPEED_TRUTH = {"mu": 0.18, "mu_d": 0.10, "decay": 1.0}
SPEED_LAW = {"friction_law": "velocity_decay"}
SPEED_CASE = {"U_draw": 0.1, "F_clamp": 50.0, "steady_window": (0.08, 0.1)}
# The fits take increments five times the reference's (the scene's 0.1 um after the fine start).
FIT_INCREMENTS = {"dU": 5e-4}
SPEED_START = {"mu": 0.15, "mu_d": 0.12, "decay": 0.5}
SPEED_BOUNDS = {"mu": (0.0, 1.0), "mu_d": (0.0, 1.0), "decay": (0.0, 20.0)}


def reference_curves(root: str, cases: dict, truth: dict) -> dict:
    """Per case (label -> config values), the measured curve (displacement, force) of the reference
    discretisation (exact contact at ``REFERENCE_MESH`` and the scene's increments) made with ``truth``."""
    out = {}
    for label, values in cases.items():
        h = _reference(root, label, values, truth)["history"]
        keep = np.asarray(h["drawing_displacement"]) > 0
        out[label] = (np.asarray(h["drawing_displacement"])[keep], np.asarray(h["drawing_force"])[keep])
    return out


def _reference(root: str, label: str, values: dict, truth: dict) -> dict:
    """One reference run (:func:`reference_curves`), read back from ``root`` where it was made before."""
    done = run_case(os.path.join(root, f"reference_{label}"), "flat_die", "const_force", "lcp_ssn",
                    {**truth, **values, "mesh": REFERENCE_MESH}, tag="friction_laws",
                    log=lambda line: print(line, file=sys.stderr, flush=True))
    if not done["summary"]["converged"]:
        raise SystemExit(f"reference run {label} did not converge: {done['summary']['message']}")
    return done


class JointModel:
    """The fitting model's curves of several cases from as few compiled path functions as possible.

    ``cases``: per label, the config values of that curve. Values named in ``extra`` (the clamping
    force) become fixed parameters of a shared path function after ``names``; the others (the drawing
    speed, which sets the phases' static durations) give each distinct set its own path function."""

    def __init__(self, names: tuple, overrides: dict, data: dict, cases: dict, extra: tuple = (),
                 algorithm: str = "penalty", start: dict | None = None):
        start = START if start is None else start
        self.names, self.data, self.extra, self.labels = names, data, extra, tuple(cases)
        self._extra_values = {label: jnp.asarray([cases[label][k] for k in extra], jnp.float64) for label in cases}
        self._groups, functions = {}, {}
        for label, values in cases.items():
            static = tuple(sorted((k, v) for k, v in values.items() if k not in extra))
            if static not in functions:
                first = dict(values)
                par = parameterize("flat_die", [*names, *extra], variant="const_force", algorithm=algorithm,
                                   overrides={**overrides, **first, **{k: start[k] for k in names}})
                functions[static] = self._compile(path_function(par))
            self._groups[label] = functions[static]
        self.evaluations = 0

    @staticmethod
    def _compile(path):
        def curve(theta, extra, u):
            hist, code = path(jnp.concatenate([theta, extra]))
            U, force = hist.observed["drawing_displacement"], hist.observed["drawing_force"]
            rows = jnp.arange(U.shape[0]) < hist.n_rows
            # Rows past the last are padding: push their displacements beyond every measured one.
            U = jnp.where(rows, U, 1e9 + jnp.arange(U.shape[0]))
            return jnp.interp(u, U, force), code

        return jax.jit(curve), jax.jit(jax.jacfwd(lambda th, e, u: curve(th, e, u)[0]))

    def curves(self, theta) -> dict:
        out = {}
        for label in self.labels:
            values, code = self._groups[label][0](jnp.asarray(theta), self._extra_values[label],
                                                  jnp.asarray(self.data[label][0]))
            if int(code) != 0:
                where = dict(zip(self.names, np.asarray(theta).tolist()))
                raise RuntimeError(f"the replay of {label}, {where} stopped (code {int(code)})")
            out[label] = np.asarray(values)
        self.evaluations += 1
        return out

    def residual(self, theta, measured) -> np.ndarray:
        c = self.curves(theta)
        return np.concatenate([c[label] - measured[label] for label in self.labels])

    def jacobian(self, theta) -> np.ndarray:
        return np.concatenate([np.asarray(self._groups[label][1](jnp.asarray(theta), self._extra_values[label],
                                                                 jnp.asarray(self.data[label][0])))
                               for label in self.labels])


def fit(model: JointModel, measured: dict, start: dict | None = None, bounds: dict | None = None) -> dict:
    """Bounded least squares on every curve at once; the estimate, its standard errors and intervals."""
    start, bounds = START if start is None else start, BOUNDS if bounds is None else bounds
    t0 = time.perf_counter()
    x0 = np.array([start[k] for k in model.names])
    lo, hi = np.array([bounds[k][0] for k in model.names]), np.array([bounds[k][1] for k in model.names])
    sol = optimize.least_squares(lambda th: model.residual(th, measured), x0, jac=model.jacobian, bounds=(lo, hi),
                                 x_scale="jac", xtol=1e-10, ftol=1e-12, gtol=1e-12)
    J, r = model.jacobian(sol.x), model.residual(sol.x, measured)
    dof = r.size - sol.x.size
    s2 = float(r @ r) / dof
    cov = s2 * np.linalg.inv(J.T @ J)
    stderr = np.sqrt(np.diag(cov))
    t = float(stats.t.ppf(0.975, dof))
    return {"x": sol.x, "stderr": stderr, "lo": sol.x - t * stderr, "hi": sol.x + t * stderr,
            "rms": float(np.sqrt(np.mean(r**2))), "max_misfit": float(np.max(np.abs(r))), "nfev": int(sol.nfev),
            "seconds": time.perf_counter() - t0, "status": int(sol.status)}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default=os.path.join("runs", "friction_laws"))
    ap.add_argument("--noise", type=float, default=0.005,
                    help="noise of the noisy fit, times each curve's largest force")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--card", action="store_true", help="only the bead cards of the fitted laws (after the fits)")
    ap.add_argument("--speed", action="store_true", help="only the speed law's identification")
    ap.add_argument("--period", action="store_true", help="only the speed filter's period against steady sliding")
    ap.add_argument("--speed-figure", action="store_true", help="only the speed fit's figure, from its CSV files")
    ap.add_argument("--speed-increments", action="store_true",
                    help="only the model at the true speed law against the reference curves, by increments")
    ap.add_argument("--pressure-speed", action="store_true", help="only the pressure-and-speed law's identification")
    ap.add_argument("--falling", action="store_true",
                    help="only the flat die's runs with friction bounds mu(p) p that fall with the pressure")
    a = ap.parse_args(argv)
    if a.falling:
        return falling(a.root)
    if a.pressure_speed:
        return pressure_speed(a.root, a.noise, a.seed)
    if a.speed_increments:
        return speed_increments(a.root)
    if a.speed_figure:
        return speed_figure()
    if a.period:
        return periods()
    if a.card:
        return cards(a.root)
    if a.speed:
        return speed(a.root, a.noise, a.seed)

    rows = []
    clamps = CLAMP_CASES
    data = reference_curves(a.root, clamps, {**LAW, **TRUTH})
    clean = {label: f for label, (_, f) in data.items()}
    noisy = _noisy(clean, a.noise, a.seed)
    law_model = JointModel(("mu", "mu_p"), LAW, data, clamps, extra=("F_clamp",))
    coulomb_model = JointModel(("mu",), {}, data, {k: {kk: vv for kk, vv in v.items() if kk != "friction_law"}
                                                    for k, v in clamps.items()}, extra=("F_clamp",))
    results = _fits({"law": (law_model, clean), "coulomb": (coulomb_model, clean),
                     "law_noisy": (law_model, noisy)}, TRUTH, rows)
    fitted = {"law": law_model.curves(results["law"]["x"]), "coulomb": coulomb_model.curves(results["coulomb"]["x"])}
    _write_curves(os.path.join(RESULTS, "friction_laws_curves.csv"), data, fitted, clamps)

    _write_fit_rows(os.path.join(RESULTS, "friction_laws.csv"), rows)

    out = os.path.join(RESULTS, "friction_laws")
    os.makedirs(out, exist_ok=True)
    mu, mu_p = results["law"]["x"]
    law = Polynomial(c_p=mu_p)
    with open(os.path.join(out, "friction.rad"), "w") as fh:
        fh.write(radioss_friction(law, mu, title="flat die, mu(p) fitted by jaxfric (experiments/friction_laws.py)"))
    with open(os.path.join(out, "friction.csv"), "w") as fh:
        fh.write(friction_csv(law, mu, 30.0))
    _figure(data, fitted, results, os.path.join(RESULTS, "friction_laws.png"))
    cards(a.root)


def _noisy(clean: dict, noise: float, seed: int) -> dict:
    """Each curve with Gaussian noise of ``noise`` times its largest force added to every point (seeded)."""
    rng = np.random.default_rng(seed)
    return {label: f + noise * np.max(np.abs(f)) * rng.standard_normal(f.shape) for label, f in clean.items()}


def _write_fit_rows(path: str, rows: list) -> None:
    """The fits' rows as CSV, every column any row has (blank where a fit has none)."""
    keys: list = []
    for row in rows:
        keys += [k for k in row if k not in keys]
    write_rows(path, [{k: row.get(k, "") for k in keys} for row in rows])


def _fits(fits: dict, truth: dict, rows: list, start: dict | None = None, bounds: dict | None = None) -> dict:
    """Each fit (name -> (model, measured)), its row appended to ``rows``; the results by name."""
    results = {}
    for name, (model, measured) in fits.items():
        res = fit(model, measured, start, bounds)
        results[name] = res
        row = {"fit": name, "parameters": " ".join(model.names)}
        for k, key in enumerate(model.names):
            row.update({key: res["x"][k], f"{key}_stderr": res["stderr"][k], f"{key}_lo95": res["lo"][k],
                        f"{key}_hi95": res["hi"][k], f"{key}_truth": truth.get(key, ""),
                        f"{key}_in_interval": bool(res["lo"][k] <= truth.get(key, np.nan) <= res["hi"][k])})
        row.update({"rms_misfit": res["rms"], "max_misfit": res["max_misfit"], "evaluations": res["nfev"],
                    "seconds": round(res["seconds"], 1)})
        rows.append(row)
        print(name, {k: v for k, v in row.items() if not k.endswith("_truth")}, flush=True)
    return results


def pressure_speed(root: str, noise: float, seed: int) -> None:
    """mu(p, v) = mu + mu_p p + mu_v v from the flat die's curves at two clamping forces and two speeds, fitted
    jointly on the exact path (module docstring), and a constant mu fitted to the same curves."""
    rows: list = []
    data = reference_curves(root, PS_CASES, {**LAW, **PS_TRUTH})
    clean = {label: f for label, (_, f) in data.items()}
    noisy = _noisy(clean, noise, seed)
    # The exact path (its implicit derivatives) with five times the reference's increments, as the speed
    # law's fit: the penalty path's replays of the start values' steps did not converge at trial values
    # of the fit at 2 mm/s and 100 N/mm.
    law_model = JointModel(("mu", "mu_p", "mu_v"), {**LAW, **FIT_INCREMENTS}, data, PS_CASES, extra=("F_clamp",),
                           algorithm="lcp_ssn")
    coulomb_cases = {k: {kk: vv for kk, vv in v.items() if kk != "friction_law"} for k, v in PS_CASES.items()}
    coulomb_model = JointModel(("mu",), FIT_INCREMENTS, data, coulomb_cases, extra=("F_clamp",), algorithm="lcp_ssn")
    results = _fits({"pv_law": (law_model, clean), "pv_coulomb": (coulomb_model, clean),
                     "pv_law_noisy": (law_model, noisy)}, PS_TRUTH, rows)
    fitted = {"law": law_model.curves(results["pv_law"]["x"]),
              "coulomb": coulomb_model.curves(results["pv_coulomb"]["x"])}
    _write_curves(os.path.join(RESULTS, "friction_laws_pressure_speed_curves.csv"), data, fitted, PS_CASES)
    _write_fit_rows(os.path.join(RESULTS, "friction_laws_pressure_speed.csv"), rows)
    mu, mu_p, mu_v = results["pv_law"]["x"]
    out = os.path.join(RESULTS, "friction_laws")
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, "friction_pressure_speed.rad"), "w") as fh:
        fh.write(radioss_friction(Polynomial(c_p=mu_p, c_v=mu_v), mu,
                                  title="flat die, mu(p, v) fitted by jaxfric (experiments/friction_laws.py)"))


def speed(root: str, noise: float, seed: int) -> None:
    """The decay law mu = mu_d + (mu_0 - mu_d) exp(-decay v) from curves at three drawing speeds, fitted on
    the exact path (``lcp_ssn``'s implicit derivatives) at the spec mesh with five times the reference's
    increments; and the constant mu fitted to the same curves."""
    rows: list = []
    cases = {f"v{v:g}": {**SPEED_LAW, **SPEED_CASE, "draw_speed": v} for v in SPEEDS}
    data = reference_curves(root, cases, {**SPEED_LAW, **SPEED_TRUTH})
    clean = {label: f for label, (_, f) in data.items()}
    noisy = _noisy(clean, noise, seed)
    names = ("mu", "mu_d", "decay")
    law_model = JointModel(names, {**SPEED_LAW, **FIT_INCREMENTS}, data, cases, algorithm="lcp_ssn",
                           start=SPEED_START)
    # A constant mu does not read the speed: one path function serves the three curves.
    coulomb_cases = {label: SPEED_CASE for label in cases}
    coulomb_model = JointModel(("mu",), FIT_INCREMENTS, data, coulomb_cases, algorithm="lcp_ssn", start=SPEED_START)
    results = _fits({"speed_law": (law_model, clean), "speed_coulomb": (coulomb_model, clean),
                     "speed_law_noisy": (law_model, noisy)}, SPEED_TRUTH, rows, SPEED_START, SPEED_BOUNDS)
    fitted = {"law": law_model.curves(results["speed_law"]["x"]),
              "coulomb": coulomb_model.curves(results["speed_coulomb"]["x"])}
    _write_curves(os.path.join(RESULTS, "friction_laws_speed_curves.csv"), data, fitted, cases)
    _write_fit_rows(os.path.join(RESULTS, "friction_laws_speed.csv"), rows)
    speed_figure()


def speed_figure() -> None:
    """``friction_laws_speed.png`` from ``friction_laws_speed_curves.csv`` and ``friction_laws_speed.csv``, and the
    fitted law's cards, LS-DYNA's card 2 and OpenRadioss's ``/FRICTION`` (``Ifric`` = 4), in
    ``friction_laws/friction_speed.k`` and ``.rad`` (``--speed-figure``: only this)."""
    data, fitted = {}, {"law": {}, "coulomb": {}}
    with open(os.path.join(RESULTS, "friction_laws_speed_curves.csv")) as fh:
        rows = list(csv.DictReader(fh))
    for label in dict.fromkeys(r["case"] for r in rows):
        mine = [r for r in rows if r["case"] == label]
        data[label] = (_column(mine, "drawing displacement (mm)"), _column(mine, "measured force (N/mm)"))
        fitted["law"][label] = _column(mine, "law fit (N/mm)")
        fitted["coulomb"][label] = _column(mine, "coulomb fit (N/mm)")
    with open(os.path.join(RESULTS, "friction_laws_speed.csv")) as fh:
        fits = {r["fit"]: r for r in csv.DictReader(fh)}
    results = {name: {"x": np.array([float(fits[name][k]) for k in fits[name]["parameters"].split()])}
               for name in fits}
    _speed_figure(data, fitted, results, os.path.join(RESULTS, "friction_laws_speed.png"))
    mu, mu_d, decay = results["speed_law"]["x"]
    out = os.path.join(RESULTS, "friction_laws")
    os.makedirs(out, exist_ok=True)
    law = VelocityDecay(mu_d, decay)
    title = "flat die, mu(v) fitted by jaxfric (experiments/friction_laws.py --speed)"
    for name, text in (("friction_speed.k", lsdyna_friction(law, mu)), ("friction_speed.rad",
                                                                          radioss_friction(law, mu, title=title))):
        with open(os.path.join(out, name), "w") as fh:
            fh.write(text)


def _column(rows: list, name: str) -> np.ndarray:
    return np.array([float(r[name]) for r in rows])


def speed_increments(root: str) -> None:
    """Where the speed fit's misfit comes from: the model at the true law against the reference curves
    (``--speed``'s, read from ``root``), at the fit mesh with the reference's increments and with the
    fit's, and at the reference mesh with the fit's. ``friction_laws_speed_increments.csv``."""
    from jaxfric import scenes
    from jaxfric.loadpath.run import run

    cases = {f"v{v:g}": {**SPEED_LAW, **SPEED_CASE, "draw_speed": v} for v in SPEEDS}
    data = reference_curves(root, cases, {**SPEED_LAW, **SPEED_TRUTH})
    models = {"240x2, reference increments": {"mesh": "240x2"},
              "240x2, fit increments": {"mesh": "240x2", **FIT_INCREMENTS},
              f"{REFERENCE_MESH}, fit increments": {"mesh": REFERENCE_MESH, **FIT_INCREMENTS}}
    rows = []
    for label, values in cases.items():
        U, F = data[label]
        for name, extra in models.items():
            s = scenes.make("flat_die", "const_force", "lcp_ssn", {**values, **SPEED_TRUTH, **extra})
            res = run(s.model, newton=s.newton, control=s.control, observe=s.observe, progress=False)
            miss = np.interp(U, res.history["drawing_displacement"], res.history["drawing_force"]) - F
            rows.append({"case": label, "model at the true law": name,
                         "rms misfit (N/mm)": float(np.sqrt(np.mean(miss**2))),
                         "largest misfit (N/mm)": float(np.max(np.abs(miss))),
                         "where (um)": float(1e3 * U[np.argmax(np.abs(miss))]), "steps": len(res.history["time"]) - 1})
            print(rows[-1], flush=True)
    write_rows(os.path.join(RESULTS, "friction_laws_speed_increments.csv"), rows)


def periods() -> None:
    """Steady sliding through the speed filter (jaxfric.contact.friction): the flat die at 24 x 2 drawn
    0.2 mm at 1 mm/s with mu = 0.12 + 0.01 v, at 50 and 200 N/mm, for filter periods from 0 (the last
    step's raw rate) to 20 ms. Steady sliding at 1 mm/s is mu(1) F_clamp; per case, the last 100 steps'
    mean, range and sign changes of the force's increments. ``friction_laws_period.csv``."""
    from jaxfric import scenes
    from jaxfric.loadpath.run import run

    rows = []
    for F in (50.0, 200.0):
        for period in (0.0, 3e-4, 1e-3, 2e-3, 5e-3, 1e-2, 2e-2):
            s = scenes.make("flat_die", "const_force", "lcp_ssn",
                            {"mesh": "24x2", "friction_law": "polynomial", "mu": 0.12, "mu_v": 0.01, "U_draw": 0.2,
                             "steady_window": (0.1, 0.2), "F_clamp": F, "speed_period": period})
            res = run(s.model, newton=s.newton, control=s.control, observe=s.observe, progress=False)
            tail = np.asarray(res.history["drawing_force"])[-100:]
            rows.append({"F_clamp (N/mm)": F, "period (s)": period, "steady sliding mu(1) F (N/mm)": 0.13 * F,
                         "mean (N/mm)": float(np.mean(tail)), "range (N/mm)": float(np.ptp(tail)),
                         "relative error of the mean": float(np.mean(tail) / (0.13 * F) - 1.0),
                         "sign changes": int(np.sum(np.diff(np.sign(np.diff(tail))) != 0)),
                         "steps": len(res.history["time"])})
            print(rows[-1], flush=True)
    write_rows(os.path.join(RESULTS, "friction_laws_period.csv"), rows)


# Friction bounds that fall with the pressure (--falling): the flat die at 24 x 2 pressed with 200 N/mm,
# 4.2 MPa under the die at the clamp's end, mu_0 = 0.18. The linear laws' bound mu(p) p peaks at
# p = mu_0 / (2 |mu_p|) and reaches 0 where mu is clipped, at mu_0 / |mu_p|; the quadratic law's bound falls
# between 3.2 and 7.4 MPa while mu stays above 0.02 (its least value, at 8 MPa).
FALLING_CASE = {**LAW, "mesh": "24x2", "F_clamp": 200.0, "mu": 0.18}
FALLING_LAWS = {"linear_0.004": {"mu_p": -0.004}, "linear_0.02": {"mu_p": -0.02},
                "linear_0.025": {"mu_p": -0.025}, "linear_0.03": {"mu_p": -0.03}, "linear_0.04": {"mu_p": -0.04},
                "quadratic": {"mu_p": -0.04, "mu_pp": 0.0025}}
FALLING_ALGORITHMS = ("lcp_ssn", "penalty")
# A pair whose coefficient is within this of 0 counts as at the clip (mu = max(polynomial, 0)).
NEAR_CLIP = 0.005


def falling(root: str) -> None:
    """The flat die with each of :data:`FALLING_LAWS` by each of :data:`FALLING_ALGORITHMS`: whether the run
    completes, its cost, and at its last converged step the pairs' pressures, where the bound mu(p) p falls
    (its slope mu_0 + 2 mu_p p + 3 mu_pp p^2 below 0 where mu is not clipped) and how many pairs sit within
    :data:`NEAR_CLIP` of mu = 0. ``friction_laws_falling.csv``."""
    log = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731
    rows = []
    for label, coefficients in FALLING_LAWS.items():
        for algorithm in FALLING_ALGORITHMS:
            done = run_case(os.path.join(root, f"falling_{label}_{algorithm}"), "flat_die", "const_force",
                            algorithm, {**FALLING_CASE, **coefficients}, tag="friction_laws", log=log)
            s, c = done["summary"], done["contact"]
            closed = c["final__rn"] > 0
            p, mu = _pressures(c)[closed], np.asarray(c["final__mu"])[closed]
            c_p, c_pp = coefficients["mu_p"], coefficients.get("mu_pp", 0.0)
            slope = np.where(mu > 0, FALLING_CASE["mu"] + 2 * c_p * p + 3 * c_pp * p**2, 0.0)
            rows.append({"law": label, "mu_p": c_p, "mu_pp": c_pp, "algorithm": algorithm,
                         "completed": bool(s["converged"]), "steps": s.get("n_steps"),
                         "newton_iters": s.get("newton_iters_total"), "cutbacks": s.get("n_cutbacks"),
                         "steady_drawing_force": s.get("steady_drawing_force"), "closed_pairs": int(closed.sum()),
                         "largest_pressure_MPa": float(p.max()), "smallest_mu": float(mu.min()),
                         "pairs_bound_falling": int(np.sum(slope < 0)), "steepest_bound_slope": float(slope.min()),
                         "pairs_near_mu_0": int(np.sum(mu < NEAR_CLIP)),
                         "stopped": "" if s["converged"] else _stop_reason(s["message"])})
            print(rows[-1], flush=True)
    write_rows(os.path.join(RESULTS, "friction_laws_falling.csv"), rows)


def _stop_reason(message: str) -> str:
    """Where a run stopped and the reason's short name, from its summary's message."""
    where = message.split(",")[0]
    if "crawls" in message:
        return f"{where}: stalled (the smallest increment, step after step)"
    if "Newton did not converge" in message:
        return f"{where}: Newton's iteration limit at the smallest increment"
    return message[:120]


def _speed_figure(data, fitted, results, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 4.4))
    colours = plt.cm.viridis(np.linspace(0.0, 0.85, len(SPEEDS)))
    window = SPEED_CASE["steady_window"]
    steady = {}
    for v, col in zip(SPEEDS, colours, strict=True):
        u, f = data[f"v{v:g}"]
        ax[0].plot(1e3 * u, f, "o", ms=2.0, color=col, label=f"measured, v = {v:g} mm/s")
        ax[0].plot(1e3 * u, fitted["law"][f"v{v:g}"], "-", color=col, lw=1.2)
        ax[0].plot(1e3 * u, fitted["coulomb"][f"v{v:g}"], "--", color=col, lw=1.0)
        keep = (u >= window[0]) & (u <= window[1])
        steady[v] = [np.mean(f[keep]), np.mean(fitted["law"][f"v{v:g}"][keep]),
                     np.mean(fitted["coulomb"][f"v{v:g}"][keep])]
    ax[0].set(xlabel="drawing displacement (um)", ylabel="drawing force (N/mm)",
              title="curves: points measured, - decay law fit, -- constant mu fit")
    ax[0].legend(fontsize=7)
    table = np.array([steady[v] for v in SPEEDS])
    ax[1].plot(SPEEDS, table[:, 0], "ko", label="measured (reference, decay law)")
    ax[1].plot(SPEEDS, table[:, 1], "-", color="C0", label="decay law fit")
    ax[1].plot(SPEEDS, table[:, 2], "--", color="C3",
               label=f"constant mu = {results['speed_coulomb']['x'][0]:.4f}")
    ax[1].set(xscale="log", xlabel="drawing speed (mm/s)", ylabel="steady drawing force (N/mm)",
              title=f"steady force, U in [{window[0] * 1e3:g}, {window[1] * 1e3:g}] um")
    ax[1].set_xticks(SPEEDS, [f"{v:g}" for v in SPEEDS])
    ax[1].minorticks_off()
    ax[1].legend(fontsize=8)
    v = np.linspace(0.0, 5.0, 101)
    truth = SPEED_TRUTH
    mu, mu_d, decay = results["speed_law"]["x"]
    _law_panel(ax[2], v, truth["mu_d"] + (truth["mu"] - truth["mu_d"]) * np.exp(-truth["decay"] * v),
               mu_d + (mu - mu_d) * np.exp(-decay * v), f"fit: {mu_d:.4f} + {mu - mu_d:.4f} exp(-{decay:.3f} v)",
               results["speed_coulomb"]["x"][0], "sliding speed v (mm/s)", "mu(v)")
    _save(fig, path)


def _law_panel(ax, x, truth, fitted, label, constant, xlabel, title) -> None:
    """The law of the data, the fitted law and the constant mu fit against ``x``."""
    ax.plot(x, truth, "k-", lw=2.5, alpha=0.4, label="law of the data")
    ax.plot(x, fitted, "-", color="C0", label=label)
    ax.axhline(constant, color="C3", ls="--", label="constant mu fit")
    ax.set(xlabel=xlabel, ylabel="friction coefficient", title=title)
    ax.legend(fontsize=8)


def _save(fig, path: str) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    print("written", path)


def _write_curves(path: str, data: dict, fitted: dict, cases: dict) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["case", "F_clamp (N/mm)", "draw_speed (mm/s)", "drawing displacement (mm)",
                    "measured force (N/mm)", "law fit (N/mm)", "coulomb fit (N/mm)"])
        for label, values in cases.items():
            for u, f, g, c in zip(*data[label], fitted["law"][label], fitted["coulomb"][label], strict=True):
                w.writerow([label, values["F_clamp"], values.get("draw_speed", 1.0), f"{u:.10g}", f"{f:.10g}",
                            f"{g:.10g}", f"{c:.10g}"])


def cards(root: str) -> None:
    """Shape1's bead card with each fitted law (``friction_laws.csv``), and the pressures of the bead."""
    from jaxfric.cards import bead_card

    with open(os.path.join(RESULTS, "friction_laws.csv")) as fh:
        fitted = {row["fit"]: row for row in csv.DictReader(fh)}
    laws = {"mu(p) fit": {**LAW, "mu": float(fitted["law"]["mu"]), "mu_p": float(fitted["law"]["mu_p"])},
            "constant mu fit": {"mu": float(fitted["coulomb"]["mu"])}}
    log = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731
    out = {name: bead_card("shape1", overrides=o, progress=log) for name, o in laws.items()}
    # The runs that exact contact did not complete, which the penalty law made instead (BeadCard.notes).
    notes = [f"{name}: {note}" for name, card in out.items() for note in card.notes] or ["none"]
    os.makedirs(os.path.join(RESULTS, "friction_laws"), exist_ok=True)
    with open(os.path.join(RESULTS, "friction_laws", "card_notes.txt"), "w") as fh:
        fh.write("\n".join(notes) + "\n")
    print("card runs by the penalty law:", *notes, sep="\n  ")
    # The pressures the mu(p) law meets in the bead: its full-depth card run drawn 35 mm again.
    done = run_case(os.path.join(root, "shape1_full_depth"), "blankholder", "shape1", "lcp_ssn",
                    {**laws["mu(p) fit"], "lock_control": "depth", "U_pull": 35.0, "steady_window": (25.0, 35.0)},
                    tag="friction_laws", log=log)
    p = _pressures(done["contact"])
    closed = p > 1e-9
    references = [_reference(root, label, values, {**LAW, **TRUTH}) for label, values in CLAMP_CASES.items()]
    fit_range = max(_pressures(ref["contact"]).max() for ref in references)
    rows = []
    for k, depth in enumerate(out["mu(p) fit"].penetration):
        rows.append({"penetration_mm": depth, **{f"{name} restraining (N/mm)": card.restraining_force[k]
                                                 for name, card in out.items()},
                     **{f"{name} normal (N/mm)": card.normal_force[k] for name, card in out.items()}})
    write_rows(os.path.join(RESULTS, "friction_laws_card.csv"), rows)
    summary = (f"bead pressures at full depth (closed pairs): median {np.median(p[closed]):.1f} MPa, "
               f"90th percentile {np.percentile(p[closed], 90):.1f} MPa, largest {np.max(p):.1f} MPa; "
               f"the flat die's curves reach {fit_range:.1f} MPa")
    print(summary)
    with open(os.path.join(RESULTS, "friction_laws", "bead_pressures.txt"), "w") as fh:
        fh.write(summary + "\n")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
    for (name, card), style in zip(out.items(), ("-o", "--s"), strict=True):
        ax[0].plot(card.penetration, card.restraining_force, style, label=name)
        ax[0].plot(card.penetration, card.normal_force, style, alpha=0.45, label=f"{name}: normal force")
    ax[0].set(xlabel="bead penetration (mm)", ylabel="force per unit bead length (N/mm)",
              title="shape1 bead card with each fitted law")
    ax[0].legend(fontsize=8)
    ax[1].hist(p[closed], bins=40, color="0.5")
    ax[1].axvspan(0.0, fit_range, color="C0", alpha=0.15, label="pressures of the fit's curves (flat die)")
    ax[1].set(xlabel="contact pressure (MPa)", ylabel="closed pairs", title="the bead's pressures at full depth")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(RESULTS, "friction_laws_card.png"), dpi=130)
    print("written", os.path.join(RESULTS, "friction_laws_card.png"))


def _pressures(contact) -> np.ndarray:
    """(m,) every pair's contact pressure at the run's final instant (MPa), tool by tool (its own row of
    candidates: :func:`jaxfric.contact.friction.tributary_lengths`)."""
    from jaxfric.contact.friction import tributary_lengths

    X = contact["x0"][contact["pair_node"]]
    out = np.zeros(len(X))
    for tool in np.unique(contact["pair_tool"]):
        mine = contact["pair_tool"] == tool
        out[mine] = contact["final__rn"][mine] / np.asarray(tributary_lengths(X[mine]))
    return out


def _figure(data, fitted, results, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 4.4))
    colours = plt.cm.viridis(np.linspace(0.0, 0.85, len(CLAMPS)))
    for F, col in zip(CLAMPS, colours, strict=True):
        u, f = data[f"F{F:g}"]
        ax[0].plot(1e3 * u, f, "o", ms=2.5, color=col, label=f"measured, F = {F:g} N/mm")
        ax[0].plot(1e3 * u, fitted["law"][f"F{F:g}"], "-", color=col, lw=1.2)
        ax[0].plot(1e3 * u, fitted["coulomb"][f"F{F:g}"], "--", color=col, lw=1.0)
    ax[0].set(xlabel="drawing displacement (um)", ylabel="drawing force (N/mm)",
              title="curves: points measured, - mu(p) fit, -- constant mu fit")
    ax[0].legend(fontsize=7)
    ax[1].plot(CLAMPS, [data[f"F{F:g}"][1][-1] for F in CLAMPS], "ko", label="measured (reference, mu(p))")
    ax[1].plot(CLAMPS, [fitted["law"][f"F{F:g}"][-1] for F in CLAMPS], "-", color="C0", label="mu(p) fit")
    ax[1].plot(CLAMPS, [fitted["coulomb"][f"F{F:g}"][-1] for F in CLAMPS], "--", color="C3",
               label=f"constant mu = {results['coulomb']['x'][0]:.4f}")
    ax[1].set(xlabel="clamping force (N/mm)", ylabel="drawing force at the end (N/mm)",
              title="force against clamping force")
    ax[1].legend(fontsize=8)
    p = np.linspace(0.0, 30.0, 61)
    mu, mu_p = results["law"]["x"]
    _law_panel(ax[2], p, TRUTH["mu"] + TRUTH["mu_p"] * p, mu + mu_p * p, f"fit: {mu:.4f} {mu_p:+.5f} p",
               results["coulomb"]["x"][0], "contact pressure p (MPa)", "mu(p)")
    _save(fig, path)


if __name__ == "__main__":
    main()
