"""Error against run time: converged references, error measures, the sweep and its report.

``jaxfric report accuracy-cost [--quick] [--out DIR]`` (and ``experiments/accuracy_cost.py``) runs, per
test (flat die ``const_force`` / ``const_position``, Nine ``mu000`` / ``mu017``):

- a **reference**: ``auglag`` with the test's target gap ``ref_gap`` (default ``REF_GAP``), or exact
  contact (``ref_algorithm`` ``lcp_ssn``), on the
  reference mesh (each sweep mesh at most as fine) with a fraction ``ref_step`` of the nominal
  increments (half by default); and its
  **checks** (``ref_checks``), the mesh refined once more (element size halved in both directions, or
  along x and through the thickness apart) and the increments halved once more. The reference counts as
  converged for a measure when its checks change it by less than a tenth of the smallest error of that
  measure in the sweep (the table says, per measure, whether it did);
- a test may also be a **same-mesh** test (``tag``, e.g. ``nine_mu017_at_100x2``): its reference is on
  the sweep's own mesh and has only the step check (at a thirty-second of the nominal increments, so
  that its own step error is resolved below 0.1 %), so its errors are those of the contact algorithm
  and the step size on that mesh, with the discretisation error left out (on the Nine the total error at
  the sweep's mesh is over 20 %, and the fine reference's own uncertainty, about 1 %, hides the contact
  algorithms' and step sizes' errors of 0.1 to 1 %).
  It shares its sweep runs with the parent test (``runs``) and has no mesh family;
- the **sweep**: ``penalty`` over five decades of eps_N, ``auglag`` over eps_N x target gap, ``lcp_ssn``,
  and, with the scene's default algorithm and penalty, coarser/finer meshes and larger/smaller steps;
- for every run: solve wall time and compile time apart, Newton iterations, and the **error measures**
  (:func:`error_measures`) against the reference.

It writes ``accuracy_cost.csv`` (one row per run), ``pareto_<test>.png`` (error against wall time, one
curve per family, the Pareto front marked) and ``accuracy_cost.md`` (the recommendations: for 10 %, 1 %
and 0.1 % the cheapest run that reaches it, per test). Runs are resumable (:mod:`jaxfric.batch`). Run
directories are not kept with the results: a test whose reference is not on disk keeps its rows from
the ``accuracy_cost.csv`` already in the output directory, so a report written after running one test
still holds the others.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
from importlib import resources

import numpy as np

from .batch import phase_curve, run_case, stale, write_csv

__all__ = ["TESTS", "QUICK_TESTS", "Test", "cases", "error_measures", "accuracy_cost", "collect", "reference_checks",
           "recommendations", "pareto_front", "report_markdown", "write_report", "MEASURES", "LEVELS",
           "penalty_tangent", "step_check"]

REF_GAP = 1e-8          # mm, target gap of the reference's augmented Lagrangian
LEVELS = (0.1, 0.01, 0.001)
GRID = 200
FLOOR = 1e-12           # errors below this are shown at it on log axes
ROUNDOFF = 1e-10        # relative differences below this are round-off (Newton's tolerance is 1e-8)
MEASURES = ("err_steady", "err_peak", "err_clamp", "err_curve_l2", "err_pressure")
MEASURE_DOC = {
    "err_steady": "relative error of the mean steady drawing force",
    "err_peak": "relative error of the peak drawing force",
    "err_clamp": "relative error of the final clamping force",
    "err_curve_l2": "L2 error of the drawing-force curve over the draw stroke, relative to the reference's L2 norm",
    "err_pressure": "contact-pressure distribution at the named instant: integral over x of the difference of "
                    "the cumulative normal forces (Wasserstein-1), relative to the reference's total normal force "
                    "times its contact length (per tool, summed)",
}


@dataclasses.dataclass(frozen=True)
class Test:
    """One test of the report: a scene variant and its sweep.

    Attributes:
        scene, variant: the scene variant.
        base: overrides common to every run (e.g. a shortened stroke).
        mesh: (nx, ny) of the sweep's algorithm runs.
        ref_mesh: (nx, ny) of the reference (its check refines it once more).
        meshes: the mesh family (default algorithm).
        step_factors: the step family (default algorithm), factors on the nominal increments.
        penalties: eps_N of the penalty family.
        auglag: (eps_N, target gap) pairs of the auglag family.
        instant: the named instant of the pressure comparison.
        ssn: include ``lcp_ssn``.
        ref_gap: target gap of the reference's augmented Lagrangian (mm).
        main: the measure the recommendations use (the flat die at constant force draws mu F_clamp
            exactly once it slides, so its steady and peak forces carry no error; its curve does).
        ref_checks: the reference's checks: ``"step"`` (increments halved), ``"mesh"`` (element size
            halved in both directions), ``"mesh_x"`` / ``"mesh_y"`` (halved along x / through the
            thickness only).
        ref_algorithm: the reference's algorithm, ``"auglag"`` (at ``ref_gap``) or ``"lcp_ssn"`` (exact
            contact, no penetration).
        tag: suffix of the test's name and of its reference's labels (a second test of one variant).
        runs: directory of the runs under ``runs/`` when shared with another test (default: the name).
        ref_step: the reference's increments, a factor on the nominal ones (its step check halves
            them once more).
        ssn_steps: factors on the nominal increments of further ``lcp_ssn`` runs (exact contact, so
            that their errors are the step size's).
        penalty_rows: (eps_N, rows) pairs: the history buffer (config field ``max_steps``) of the penalty
            runs that need more than the scene's default.
    """

    scene: str
    variant: str
    base: dict
    mesh: tuple
    ref_mesh: tuple
    meshes: tuple
    step_factors: tuple
    penalties: tuple
    auglag: tuple
    instant: str
    ssn: bool = True
    ref_gap: float = REF_GAP
    main: str = "err_steady"
    ref_checks: tuple = ("mesh", "step")
    tag: str = ""
    runs: str | None = None
    ref_step: float = 0.5
    ssn_steps: tuple = ()
    penalty_rows: tuple = ()
    ref_algorithm: str = "auglag"

    @property
    def name(self) -> str:
        return f"{self.scene}_{self.variant}{self.tag}"

    @property
    def run_dir(self) -> str:
        return self.runs or self.name

    def check_mesh_of(self, check: str) -> tuple:
        """(nx, ny) of the mesh check ``check`` (``"mesh"``, ``"mesh_x"`` or ``"mesh_y"``)."""
        nx, ny = self.ref_mesh
        return {"mesh": (2 * nx, 2 * ny), "mesh_x": (2 * nx, ny), "mesh_y": (nx, 2 * ny)}[check]

    @property
    def reference(self) -> str:
        """Label of the reference run."""
        return f"reference{self.tag}"


def _load_tests(kind: str) -> tuple:
    """The report's tests of ``kind`` ("tests" or "quick") from ``accuracy_tests.json`` (lists read as
    tuples; fields left out take the :class:`Test` defaults). Why each value was chosen:
    ``docs/results.md``, accuracy against run time."""
    def tuples(value):
        return tuple(tuples(v) for v in value) if isinstance(value, list) else value

    data = json.loads(resources.files(__package__).joinpath("accuracy_tests.json").read_text())
    return tuple(Test(**{k: tuples(v) for k, v in entry.items()}) for entry in data[kind])


TESTS = _load_tests("tests")
# --quick: the flat die at force control on small meshes, a short sweep (a few minutes on 2 cores).
QUICK_TESTS = _load_tests("quick")


def _steps(test: Test, factor: float) -> dict:
    """Overrides for the test's nominal increments (its ``base`` over the scene's defaults) scaled by
    ``factor`` (:func:`jaxfric.scenes.scaled_steps`)."""
    from . import scenes

    fields = {f.name for f in dataclasses.fields(scenes.config_class(test.scene))}
    config = scenes.config_class(test.scene)(**{k: v for k, v in test.base.items() if k in fields})
    return scenes.scaled_steps(test.scene, config, factor)


def _mesh(m) -> str:
    return f"{m[0]}x{m[1]}"


def cases(test: Test) -> list[tuple]:
    """(label, family, algorithm, overrides) of the sweep, the reference (family ``reference``) and its
    checks (``ref_check``)."""
    default_eps = _default_eps(test)
    mesh = _mesh(test.mesh)
    rows = dict(test.penalty_rows)
    out = [(f"penalty_eps{e:.0e}", "penalty", "penalty",
            {"mesh": mesh, "eps_n": e, **({"max_steps": rows[e]} if e in rows else {})}) for e in test.penalties]
    out += [(f"auglag_eps{e:.0e}_gap{g:.0e}", "auglag", "auglag", {"mesh": mesh, "eps_n": e, "target_gap": g})
            for e, g in test.auglag]
    if test.ssn:
        out.append(("lcp_ssn", "lcp_ssn", "lcp_ssn", {"mesh": mesh}))
        out += [(f"lcp_ssn_step_x{f:g}", "lcp_ssn", "lcp_ssn", {"mesh": mesh, **_steps(test, f)})
                for f in test.ssn_steps]
    out += [(f"mesh_{_mesh(m)}", "mesh", "penalty", {"mesh": _mesh(m), "eps_n": default_eps}) for m in test.meshes]
    out += [(f"step_x{f:g}", "step", "penalty", {"mesh": mesh, "eps_n": default_eps, **_steps(test, f)})
            for f in test.step_factors]
    out.append((test.reference, "reference", test.ref_algorithm,
                reference_overrides(test, test.ref_mesh, test.ref_step)))
    # The step check first: the mesh checks are the longest runs of a test.
    if "step" in test.ref_checks:
        out.append((f"ref_check_step{test.tag}", "ref_check", test.ref_algorithm,
                    reference_overrides(test, test.ref_mesh, test.ref_step / 2)))
    for check in ("mesh", "mesh_x", "mesh_y"):
        if check in test.ref_checks:
            out.append((f"ref_check_{check}{test.tag}", "ref_check", test.ref_algorithm,
                        reference_overrides(test, test.check_mesh_of(check), test.ref_step)))
    return [(label, family, algorithm, {**test.base, **ov}) for label, family, algorithm, ov in out]


def reference_overrides(test: Test, mesh: tuple, step: float) -> dict:
    """Overrides of a run made as ``test``'s reference (its algorithm, target gap and base), on ``mesh``
    with ``step`` times the nominal increments: the reference and its checks, and the runs that choose
    the reference's mesh (``experiments/reference_candidate.py``)."""
    gap = {"target_gap": test.ref_gap} if test.ref_algorithm == "auglag" else {}
    return {**test.base, "mesh": _mesh(mesh), "eps_n": _default_eps(test), **gap, **_steps(test, step)}


def _default_eps(test: Test) -> float:
    """The scene's default penalty eps_N."""
    from . import scenes

    default = next(f.default for f in dataclasses.fields(scenes.config_class(test.scene)) if f.name == "eps_n")
    assert default is not dataclasses.MISSING  # every scene config gives eps_n a default
    return default


# ---- the penalty's share of a run's error ---------------------------------------------------------------

def penalty_tangent(scene, result) -> np.ndarray:
    """eps_N dF/d eps_N of the drawing force at every history row of a completed ``penalty`` run.

    Forward mode along the run's own accepted steps (:func:`jaxfric.params.path_function`), with the
    tangent eps_N itself, i.e. the change of the force per relative change of the penalty. eps_T
    follows when it is the spec's mu eps_N (config eps_t unset); a set eps_t stays fixed. Why it
    estimates the penalty's error: where F = F_exact + c / eps_N, eps_N F' = F_exact - F exactly; for
    a penalty spring in series with a compliance k, F = F_exact eps_N / (eps_N + k), eps_N F' / F =
    (F_exact - F) / F_exact exactly; for any smooth F(eps_N) with limit F_exact it is the first-order
    term in 1 / eps_N. Costs about one more run (a replay with one tangent) plus its compilation.

    Raises ValueError (one line) for another algorithm, and when the replay does not reproduce the
    run (another result code, row count or force).
    """
    import jax
    import jax.numpy as jnp

    from .params import parameterize, path_function

    if scene.algorithm != "penalty":
        raise ValueError(f"field 'error_estimate': the penalty sensitivity applies to algorithm penalty, "
                         f"not {scene.algorithm}")
    config = scene.config
    overrides = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}
    par = parameterize(scene.name, ["eps_n"], variant=scene.variant, algorithm=scene.algorithm, overrides=overrides)
    path = path_function(par, newton=scene.newton, plan=result.history)

    def force(p):
        h, code = path(p)
        return h.observed["drawing_force"], (h.n_rows, code)

    p0 = jnp.asarray(par.p0)
    f, df, (n_rows, code) = jax.jit(lambda p: jax.jvp(force, (p,), (p,), has_aux=True))(p0)
    n = len(result.history["time"])
    f, df = np.asarray(f)[:n], np.asarray(df)[:n]
    ref = np.asarray(result.history["drawing_force"], dtype=np.float64)
    scale = max(float(np.max(np.abs(ref))), 1e-300)
    if int(code) != 0 or int(n_rows) != n or float(np.max(np.abs(f - ref))) > 1e-6 * scale:
        raise ValueError(f"the replay of the run's steps does not reproduce it (result code {int(code)}, "
                         f"{int(n_rows)} rows against {n}); no penalty sensitivity")
    return df


# ---- the step size's share of a run's error -------------------------------------------------------------

def step_check(scene, progress: bool = False) -> dict:
    """The run of ``scene`` again with every nominal increment halved (:func:`jaxfric.scenes.scaled_steps`),
    reduced to what :func:`jaxfric.output.error_estimate` needs for its ``step`` component:
    ``{"steady": steady drawing force or None, "peak": peak drawing force, "n_steps", "converged"}``.
    Costs about twice the run (and a compilation). Raises ValueError (one line) when it does not reach
    the end of the load path.
    """
    from . import instants, output, scenes
    from .run import run

    config = dataclasses.replace(scene.config, **scenes.scaled_steps(scene.name, scene.config, 0.5))
    half = scenes.SCENES[scene.name].build(config, scene.algorithm, scene.variant)
    result = run(half.model, newton=half.newton, control=half.control, observe=half.observe,
                 progress=progress, raise_on_failure=False, label="step check (half increments) ")
    if not result.converged:
        raise ValueError(f"the step check (half the nominal increments) did not complete: {result.message}")
    _, _, values = output.history_table(half, result)
    window, _ = instants.steady_window(half.name, values, half.steady_window)
    return {"steady": instants.steady_drawing_force({**values, "phase_name": values["phase"]}, window),
            "peak": float(np.max(values["drawing_force"])), "n_steps": len(values["step"]) - 1,
            "converged": True}


# ---- error measures -----------------------------------------------------------------------------------

def _rel(a, b):
    if a is None or b is None or not math.isfinite(a) or not math.isfinite(b):
        return None
    return abs(a - b) / abs(b) if b != 0 else (0.0 if a == 0 else None)


def _cumulative_difference(contact: dict, ref: dict, instant: str):
    """Distance of the normal-force distributions at ``instant``, needing no common mesh: per tool, the
    integral over x of |F(x) - F_ref(x)|, F the cumulative normal force of the nodes left of x (the
    Wasserstein-1 distance of the two distributions), summed over tools and divided by the reference's
    total normal force times the length of its contact zone. (A largest difference of F would jump by a
    whole nodal force when two nodes at the same place differ by round-off in x.)"""
    keys = (f"{instant}__rn", f"{instant}__x")
    if not all(k in contact and k in ref for k in keys):
        return None
    distance, scale = 0.0, 0.0
    for k in np.unique(ref["pair_tool"]):
        curves = []
        for c in (contact, ref):
            sel = c["pair_tool"] == k
            x = c[f"{instant}__x"][c["pair_node"][sel], 0]
            rn = c[f"{instant}__rn"][sel]
            order = np.argsort(x)
            curves.append((x[order], rn[order]))
        (xa, ra), (xb, rb) = curves
        total = float(np.sum(rb))
        if total <= 0:
            continue
        grid = np.union1d(xa, xb)
        cum = lambda xs, rs: np.concatenate([[0.0], np.cumsum(rs)])[np.searchsorted(xs, grid, side="right")]  # noqa: E731
        gap = np.abs(cum(xa, ra) - cum(xb, rb))[:-1]
        distance += float(np.sum(gap * np.diff(grid)))
        touching = xb[rb > 1e-9 * total]
        scale += total * max(float(np.ptp(touching)) if touching.size else 0.0, 1e-12)
    return distance / scale if scale > 0 else None


def error_measures(run: dict, ref: dict, instant: str) -> dict:
    """The error measures of a run against the reference (each run as returned by
    :func:`jaxfric.batch.run_case`); None where a quantity is missing (a run that stopped early)."""
    s, r = run["summary"], ref["summary"]
    out = {"err_steady": _rel(s.get("steady_drawing_force"), r.get("steady_drawing_force")),
           "err_peak": _rel(s.get("peak_drawing_force"), r.get("peak_drawing_force")),
           "err_clamp": _rel(s.get("final_clamping_force"), r.get("final_clamping_force")),
           "err_curve_l2": None, "err_pressure": None}
    draw = ("drawing_displacement", "drawing_force", "draw")
    # From the state the draw starts from: the runs' first increments differ, and a curve starting later
    # than the reference's would otherwise be extrapolated flat over the steep start of the draw.
    a = phase_curve(run["history"], *draw, start=True) if run["history"] else None
    b = phase_curve(ref["history"], *draw, start=True) if ref["history"] else None
    if a is not None and b is not None and s.get("converged"):
        grid = np.linspace(b[0][0], b[0][-1], GRID)
        fa, fb = np.interp(grid, *a), np.interp(grid, *b)
        norm = math.sqrt(np.trapezoid(fb**2, grid))
        out["err_curve_l2"] = math.sqrt(np.trapezoid((fa - fb) ** 2, grid)) / norm if norm > 0 else None
    if run["contact"] and ref["contact"]:
        out["err_pressure"] = _cumulative_difference(run["contact"], ref["contact"], instant)
    return out


# ---- the report ---------------------------------------------------------------------------------------

def _row(test: Test, label, family, algorithm, overrides, c, ref) -> dict:
    s = c["summary"]
    row = {"test": test.name, "scene": test.scene, "variant": test.variant, "run": label, "family": family,
           "algorithm": algorithm, "mesh": overrides.get("mesh"), "eps_n": overrides.get("eps_n"),
           "target_gap": overrides.get("target_gap") if algorithm == "auglag" else None,
           "converged": bool(s.get("converged")), "n_steps": s.get("n_steps"),
           "newton_iters_total": s.get("newton_iters_total"), "cutbacks": s.get("n_cutbacks"),
           "wall_s": s.get("wall_s"), "compile_s": s.get("compile_s"),
           "max_penetration": s.get("max_penetration"),
           "steady_drawing_force": s.get("steady_drawing_force"),
           "peak_drawing_force": s.get("peak_drawing_force"),
           "final_clamping_force": s.get("final_clamping_force"),
           "error_estimate": (s.get("error_estimate") or {}).get("relative"),
           "ref_mesh": _mesh(test.ref_mesh), "ref_step": test.ref_step}
    usable = ref is not None and bool(ref["summary"].get("converged")) and bool(s.get("converged"))
    row.update(error_measures(c, ref, test.instant) if usable else dict.fromkeys(MEASURES))
    row["message"] = s.get("message", "")
    return row


def _test_rows(out: str, test: Test, run_missing: bool, rerun: bool = False, progress: bool = False,
               log=print, kept: list | None = None, on_row=None) -> list[dict]:
    """Rows of one test: its runs run (``run_missing``; ``on_row`` is called with the rows so far after
    each) or only read back from ``out``. Without ``run_missing`` nothing runs, and a test whose
    reference is not on disk takes its rows from ``kept`` (the rows of the CSV already in ``out``,
    those measured against the test's present reference): run directories are not kept with the
    results."""
    plan = sorted(cases(test), key=lambda p: p[1] != "reference")  # the reference first

    def on_disk(label, ov):  # made with these overrides (a run made with others is as good as missing)
        path = _run_path(out, test, label, "summary.json")
        return os.path.exists(path) and stale(path, ov) is None

    if not run_missing and not on_disk(test.reference, plan[0][3]):
        return [r for r in kept or [] if r["test"] == test.name and _same_reference(r, test)]
    rows, done = [], {}
    for label, family, algorithm, ov in plan:
        path = _run_path(out, test, label)
        if not run_missing and not on_disk(label, ov):
            continue
        done[label] = run_case(path, test.scene, test.variant, algorithm, ov, rerun=rerun, progress=progress,
                               log=log, rerun_stale=run_missing)
        rows.append(_row(test, label, family, algorithm, ov, done[label], done.get(test.reference)))
        if on_row is not None:
            on_row(rows)
    return rows


def _same_reference(row: dict, test: Test) -> bool:
    """Whether a row read from the CSV was measured against ``test``'s present reference (rows written
    before the reference was recorded in them are taken as they are)."""
    mesh, step = row.get("ref_mesh"), row.get("ref_step")  # "" / None in such rows
    return (not mesh or mesh == _mesh(test.ref_mesh)) and (step is None or math.isclose(step, test.ref_step))


def _run_path(out: str, test: Test, label: str, *rest) -> str:
    return os.path.join(out, "runs", test.run_dir, label, *rest)


_INT_COLUMNS = ("n_steps", "newton_iters_total", "cutbacks")
_TEXT_COLUMNS = ("test", "scene", "variant", "run", "family", "algorithm", "mesh", "message", "ref_mesh")


def _read_rows(out: str) -> list[dict]:
    """The rows of ``out``'s ``accuracy_cost.csv`` (none if there is no such file), typed as
    :func:`_row` writes them."""
    path = os.path.join(out, "accuracy_cost.csv")
    if not os.path.exists(path):
        return []

    def typed(key, v):
        if key in _TEXT_COLUMNS:
            return v
        if v == "":
            return None
        if v in ("True", "False"):
            return v == "True"
        return int(float(v)) if key in _INT_COLUMNS else float(v)

    with open(path, newline="") as fh:
        return [{k: typed(k, v) for k, v in r.items()} for r in csv.DictReader(fh)]


def collect(out: str, quick: bool = False) -> list[dict]:
    """The rows of every test whose runs are in ``out``, or, for a test whose reference is not on disk,
    whose rows are in ``out``'s CSV (nothing is run)."""
    kept = _read_rows(out)
    return [r for t in (QUICK_TESTS if quick else TESTS) for r in _test_rows(out, t, run_missing=False, kept=kept)]


def accuracy_cost(out: str, quick: bool = False, tests=None, rerun: bool = False, progress: bool = False,
                  log=print) -> list[dict]:
    """Run the sweep of every test (``TESTS``, or ``QUICK_TESTS`` with ``quick``; ``tests``: names to
    keep) into ``out``, then write the CSV, the Pareto plots and the recommendations of every test found
    in ``out`` (also those of earlier invocations). Returns those rows."""
    pool = QUICK_TESTS if quick else TESTS
    chosen = [t for t in pool if tests is None or t.name in tests]
    if not chosen:
        raise ValueError(f"no test selected; choose from {', '.join(t.name for t in pool)}")
    # The CSV written between runs holds every row known: the rows of the tests not run here as the CSV
    # on disk has them at that moment (another process may be running them), and the earlier rows of
    # each chosen test until it has started (run directories are not kept with the results).
    names = {t.name for t in chosen}
    kept = _read_rows(out)
    before = {t.name: _test_rows(out, t, run_missing=False, kept=kept) for t in chosen}
    done: list[dict] = []
    started: set[str] = set()

    def write_partial(current: list[dict]) -> None:
        others = [r for r in _read_rows(out) if r["test"] not in names]
        later = [r for t in chosen if t.name not in started for r in before[t.name]]
        write_csv(os.path.join(out, "accuracy_cost.csv"), others + done + current + later)

    for test in chosen:
        started.add(test.name)
        done += _test_rows(out, test, run_missing=True, rerun=rerun, progress=progress, log=log,
                           on_row=write_partial)
    return write_report(out, quick)


def write_report(out: str, quick: bool = False) -> list[dict]:
    """Write the CSV, the Pareto plots and ``accuracy_cost.md`` of every test whose runs are in ``out``
    (nothing is run); returns the rows."""
    rows = collect(out, quick)
    write_csv(os.path.join(out, "accuracy_cost.csv"), rows)
    for test in QUICK_TESTS if quick else TESTS:
        sel = [r for r in rows if r["test"] == test.name]
        if sel:
            _pareto_figure(os.path.join(out, f"pareto_{test.name}.png"), test, sel)
    with open(os.path.join(out, "accuracy_cost.md"), "w") as fh:
        fh.write(report_markdown(rows, reference_checks(rows), quick))
    return rows


def reference_checks(rows: list[dict]) -> dict:
    """:func:`_reference_check` per test."""
    return {t: _reference_check([r for r in rows if r["test"] == t]) for t in dict.fromkeys(r["test"] for r in rows)}


def _reference_check(rows: list[dict]) -> dict:
    """Per measure: the reference's uncertainty (the largest change under its checks), the resolution
    (10 x the uncertainty, or round-off), the smallest sweep error at or above it, and whether the
    uncertainty is below a tenth of that error. An error below the resolution cannot be told from the
    reference's own error: it is reported as unresolved, never as a number. When no error is resolved,
    the reference counts as converged only if its uncertainty is at round-off (every run then agrees
    with it to round-off); otherwise nothing was verified."""
    sweep = [r for r in rows if r["family"] not in ("reference", "ref_check") and r["converged"]]
    ref_checks = [r for r in rows if r["family"] == "ref_check"]
    out = {}
    for m in MEASURES:
        changes = [r[m] for r in ref_checks if r[m] is not None]
        change = max(changes) if ref_checks and len(changes) == len(ref_checks) else None
        resolution = None if change is None else max(10.0 * change, ROUNDOFF)
        errors = [r[m] for r in sweep if r[m] is not None and resolution is not None and r[m] >= resolution]
        smallest = min(errors) if errors else None
        ok = change is not None and (change <= ROUNDOFF if smallest is None else change < 0.1 * smallest)
        out[m] = {"change": change, "resolution": resolution, "smallest_error": smallest, "converged": ok,
                  "n_unresolved": sum(1 for r in sweep if r[m] is not None and resolution is not None
                                      and r[m] < resolution),
                  "checks_converged": all(r["converged"] for r in ref_checks)}
    return out


def pareto_front(points: list[tuple]) -> list[tuple]:
    """The (cost, error, ...) points no other point beats in both cost and error, by increasing cost."""
    front, best = [], math.inf
    for p in sorted(points, key=lambda p: (p[0], p[1])):
        if p[1] < best:
            front.append(p)
            best = p[1]
    return front


def _pareto_figure(path: str, test: Test, rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    panels = list(dict.fromkeys([test.main, "err_curve_l2", "err_pressure"]))
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4.8))
    markers = {"penalty": "o-", "auglag": "s-", "lcp_ssn": "D-", "mesh": "^-", "step": "v-"}
    check = _reference_check(rows)
    for ax, measure in zip(axes, panels):
        pts = []
        for family, style in markers.items():
            sel = [r for r in rows if r["family"] == family and r["converged"] and r[measure] is not None]
            if not sel:
                continue
            sel.sort(key=lambda r: r["wall_s"])
            x = [r["wall_s"] for r in sel]
            y = [max(r[measure], FLOOR) for r in sel]
            ax.plot(x, y, style, label=family, alpha=0.85)
            pts += [(r["wall_s"], max(r[measure], FLOOR), r["run"]) for r in sel]
        front = pareto_front(pts)
        if front:
            ax.step([p[0] for p in front], [p[1] for p in front], where="post", color="k", lw=1, alpha=0.6,
                    label="Pareto front")
            ax.plot([p[0] for p in front], [p[1] for p in front], "o", mfc="none", mec="k", ms=11)
            for x, y, label in front:
                ax.annotate(label, (x, y), textcoords="offset points", xytext=(5, 3), fontsize=6)
        for level in LEVELS:
            ax.axhline(level, color="gray", ls=":", lw=0.8)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        resolution = check[measure]["resolution"]
        low, high = ax.get_ylim()
        if resolution is not None and resolution > max(FLOOR, low):
            # Errors in the band cannot be told apart from the reference's own error.
            ax.axhspan(low, resolution, color="0.8", alpha=0.5, lw=0, label="below the reference's resolution")
            ax.set_ylim(low, max(high, 2 * resolution))
        ax.set_xlabel("solve wall time (s, compilation apart)")
        ax.set_ylabel({"err_steady": "relative error, steady drawing force", "err_peak": "relative error, peak force",
                       "err_curve_l2": "relative L2 error, drawing-force curve",
                       "err_pressure": "contact-pressure distribution error"}[measure])
        ax.grid(True, which="both", alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    fig.suptitle(f"{test.name}: error against run time (reference: {_reference_law(test)}, mesh "
                 f"{_mesh(test.ref_mesh)}, increments nominal / {1 / test.ref_step:g})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _fmt(v) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.3g}"
    return str(v)


def recommendations(rows: list[dict], measures: dict | None = None) -> list[dict]:
    """Per test and level: the cheapest converged sweep run whose main measure (``measures``: test name
    -> measure; default each test's ``main``) is within the level. A level below the reference's
    resolution (:func:`_reference_check`) cannot be verified and gets no run (``unverifiable``)."""
    mains = {t.name: t.main for t in (*TESTS, *QUICK_TESTS)}
    mains.update(measures or {})
    out = []
    for test in dict.fromkeys(r["test"] for r in rows):
        measure = mains.get(test, "err_steady")
        test_rows = [r for r in rows if r["test"] == test]
        resolution = _reference_check(test_rows)[measure]["resolution"]
        sweep = [r for r in test_rows if r["family"] not in ("reference", "ref_check")
                 and r["converged"] and r[measure] is not None]
        for level in LEVELS:
            unverifiable = resolution is None or level < resolution
            ok = [] if unverifiable else [r for r in sweep if r[measure] <= level]
            best = min(ok, key=lambda r: r["wall_s"]) if ok else None
            out.append({"test": test, "level": level, "measure": measure, "unverifiable": unverifiable,
                        "run": best and best["run"], "algorithm": best and best["algorithm"],
                        "mesh": best and best["mesh"], "error": best and best[measure],
                        "resolution": resolution, "wall_s": best and best["wall_s"]})
    return out


def _error_cell(value, resolution) -> str:
    if value is None:
        return "–"
    if resolution is not None and value < resolution:
        return f"< {resolution:.1g}"
    return _fmt(value)


def _reference_law(test: Test) -> str:
    """The reference's contact law, in words."""
    if test.ref_algorithm == "auglag":
        return f"auglag, target gap {test.ref_gap:g} mm"
    return f"{test.ref_algorithm} (exact contact)"


def _reference_lines(rows: list[dict], quick: bool) -> list[str]:
    """A table of what each test's errors are measured against."""
    known = {t.name: t for t in (QUICK_TESTS if quick else TESTS)}
    lines = ["**What each test measures** (a same-mesh test leaves the discretisation error out):", "",
             "| test | reference law | reference mesh | reference increments | reference checks | "
             "errors measured |", "|---|---|---|---|---|---|"]
    for name in dict.fromkeys(r["test"] for r in rows):
        t = known.get(name)
        if t is None:
            continue
        what = ("contact algorithm and step size on the sweep's mesh" if t.ref_mesh == t.mesh and not t.meshes
                else "total: contact algorithm, step size and mesh")
        checks = ", ".join(f"increments nominal / {2 / t.ref_step:g}" if c == "step" else
                           f"mesh {_mesh(t.check_mesh_of(c))}" for c in t.ref_checks)
        lines.append(f"| {name} | {_reference_law(t)} | {_mesh(t.ref_mesh)} | nominal / {1 / t.ref_step:g} | "
                     f"{checks} | {what} |")
    return lines + [""]


def report_markdown(rows: list[dict], checks: dict, quick: bool) -> str:
    lines = ["Error measures (each relative, against the test's reference): " +
             "; ".join(f"`{m}` {doc}" for m, doc in MEASURE_DOC.items()) + ". Wall time is the solve time "
             "(compilation apart, in the CSV). An error below the reference's resolution (10 x its own "
             "uncertainty, table below) is shown as `< resolution`: it cannot be told apart from the "
             "reference's error.", ""]
    lines += _reference_lines(rows, quick)
    lines += ["**What to pick** (the cheapest run of the sweep that reaches the level on the test's main "
              "measure; `–`: none of the sweep does; `unverifiable`: the level is below the reference's "
              "resolution):", "", "| test | measure | 10 % | 1 % | 0.1 % |", "|---|---|---|---|---|"]
    recs = recommendations(rows)
    for test in dict.fromkeys(r["test"] for r in recs):
        cells = []
        for level in LEVELS:
            r = next(x for x in recs if x["test"] == test and x["level"] == level)
            cells.append("unverifiable" if r["unverifiable"] else "–" if r["run"] is None else
                         f"`{r['run']}` (mesh {r['mesh']}): {_error_cell(r['error'], r['resolution'])} in "
                         f"{r['wall_s']:.3g} s")
        measure = next(x for x in recs if x["test"] == test)["measure"]
        lines.append(f"| {test} | `{measure}` | " + " | ".join(cells) + " |")
    lines += ["", "**Is the reference converged?** Its uncertainty is the largest change of a measure under its "
              "checks (its mesh or its steps halved once more, as the test has them); it must be below a tenth of "
              "the smallest error reported (errors below 10 x the uncertainty are reported as unresolved):", "",
              "| test | measure | uncertainty | resolution | smallest resolved error | unresolved runs | converged |",
              "|---|---|---|---|---|---|---|"]
    for test, per in checks.items():
        for m, c in per.items():
            lines.append(f"| {test} | {m} | {_fmt(c['change'])} | {_fmt(c['resolution'])} | "
                         f"{_fmt(c['smallest_error'])} | {c['n_unresolved']} | "
                         f"{'yes' if c['converged'] else '**no**'} |")
    lines += ["", "**Every run:**", "", "| test | run | converged | steps | Newton it. | wall s | max pen. (mm) | "
              + " | ".join(MEASURES) + " | estimate |", "|" + "---|" * (8 + len(MEASURES))]
    for r in rows:
        res = checks.get(r["test"], {})
        cells = [_fmt(r[m]) if r["family"] in ("reference", "ref_check") else
                 _error_cell(r[m], res.get(m, {}).get("resolution")) for m in MEASURES]
        lines.append(f"| {r['test']} | {r['run']} | {'yes' if r['converged'] else '**no**'} | {_fmt(r['n_steps'])} | "
                     f"{_fmt(r['newton_iters_total'])} | {_fmt(r['wall_s'])} | {_fmt(r['max_penetration'])} | "
                     + " | ".join(cells) + f" | {_fmt(r['error_estimate'])} |")
    bad = [r for r in rows if not r["converged"]]
    if bad:
        lines += ["", "Runs that did not complete:", ""] + [f"- {r['test']} `{r['run']}`: {r['message']}" for r in bad]
    return "\n".join(lines) + "\n"
