"""Error against run time: the tests, their converged references, the sweep of runs and the error measures
(the report: :mod:`jaxfric.identification.accuracy_report`).

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
and 0.1 % the cheapest run that reaches it, per test). Runs are resumable (:mod:`jaxfric.io.batch`). Run
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

from ..io.batch import phase_curve, run_case, stale

__all__ = ["TESTS", "QUICK_TESTS", "Test", "cases", "error_measures", "collect", "test_rows", "read_rows",
           "mesh_label", "MEASURES", "LEVELS", "penalty_tangent", "companion", "step_check", "mesh_check",
           "layers_check", "reference_overrides"]

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
    from .. import scenes

    fields = {f.name for f in dataclasses.fields(scenes.config_class(test.scene))}
    config = scenes.config_class(test.scene)(**{k: v for k, v in test.base.items() if k in fields})
    return scenes.scaled_steps(test.scene, config, factor)


def mesh_label(m) -> str:
    return f"{m[0]}x{m[1]}"


def cases(test: Test) -> list[tuple]:
    """(label, family, algorithm, overrides) of the sweep, the reference (family ``reference``) and its
    checks (``ref_check``)."""
    default_eps = _default_eps(test)
    mesh = mesh_label(test.mesh)
    rows = dict(test.penalty_rows)
    out = [(f"penalty_eps{e:.0e}", "penalty", "penalty",
            {"mesh": mesh, "eps_n": e, **({"max_steps": rows[e]} if e in rows else {})}) for e in test.penalties]
    out += [(f"auglag_eps{e:.0e}_gap{g:.0e}", "auglag", "auglag", {"mesh": mesh, "eps_n": e, "target_gap": g})
            for e, g in test.auglag]
    if test.ssn:
        out.append(("lcp_ssn", "lcp_ssn", "lcp_ssn", {"mesh": mesh}))
        out += [(f"lcp_ssn_step_x{f:g}", "lcp_ssn", "lcp_ssn", {"mesh": mesh, **_steps(test, f)})
                for f in test.ssn_steps]
    out += [(f"mesh_{mesh_label(m)}", "mesh", "penalty", {"mesh": mesh_label(m), "eps_n": default_eps})
            for m in test.meshes]
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
    return {**test.base, "mesh": mesh_label(mesh), "eps_n": _default_eps(test), **gap, **_steps(test, step)}


def _default_eps(test: Test) -> float:
    """The scene's default penalty eps_N."""
    from .. import scenes

    default = next(f.default for f in dataclasses.fields(scenes.config_class(test.scene)) if f.name == "eps_n")
    assert default is not dataclasses.MISSING  # every scene config gives eps_n a default
    return default


# ---- the penalty's share of a run's error ---------------------------------------------------------------

def penalty_tangent(scene, result) -> np.ndarray:
    """eps_N dF/d eps_N of the drawing force at every history row of a completed ``penalty`` run.

    Forward mode along the run's own accepted steps (:func:`jaxfric.identification.params.path_function`), with the
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


# ---- the step size's and the element length's shares of a run's error ----------------------------------

def companion_run(scene, overrides: dict, what: str, progress: bool = False):
    """``scene`` run again with config ``overrides``: (the companion scene, its run's result). Raises
    ValueError (one line, naming the run as ``what``) when it does not reach the end of the load path."""
    from .. import scenes
    from ..loadpath.run import run

    config = dataclasses.replace(scene.config, **overrides)
    other = scenes.SCENES[scene.name].build(config, scene.algorithm, scene.variant)
    result = run(other.model, newton=other.newton, control=other.control, observe=other.observe,
                 progress=progress, raise_on_failure=False, label=f"{what} ")
    if not result.converged:
        raise ValueError(f"the {what} did not complete: {result.message}")
    return other, result


def companion(scene, overrides: dict, what: str, progress: bool = False) -> dict:
    """:func:`companion_run`, reduced to what :func:`jaxfric.io.output.error_estimate` needs: ``{"steady",
    "peak", "n_steps", "mesh", "converged"}``."""
    from ..io import instants, output

    other, result = companion_run(scene, overrides, what, progress)
    _, _, values = output.history_table(other, result)
    window, _ = instants.steady_window(other.name, values, other.steady_window)
    return {"steady": instants.steady_drawing_force({**values, "phase_name": values["phase"]}, window),
            "peak": float(np.max(values["drawing_force"])), "n_steps": len(values["step"]) - 1,
            "mesh": (int(other.model.mesh.nx), int(other.model.mesh.ny)), "converged": True}


def step_check(scene, progress: bool = False) -> dict:
    """The run of ``scene`` again with every nominal increment halved (:func:`jaxfric.scenes.scaled_steps`;
    with ``step_error``, its target halved too), reduced to what :func:`jaxfric.io.output.error_estimate`
    needs for its ``step`` component: ``{"steady": steady drawing force or None, "peak": peak drawing
    force, "n_steps", "mesh", "converged", "ratio": 0.5}``. Costs about twice the run (and a
    compilation). Raises ValueError (one line) when it does not reach the end of the load path.
    """
    from .. import scenes

    check = companion(scene, scenes.scaled_steps(scene.name, scene.config, 0.5),
                      "step check (half increments)", progress)
    return {**check, "ratio": 0.5}


def mesh_check(scene, progress: bool = False, finer: bool = False) -> dict:
    """The run of ``scene`` again with about half (``finer``: twice) the elements along the strip
    (:func:`jaxfric.scenes.coarser_along`, :func:`~jaxfric.scenes.finer_along`), for the ``mesh``
    component of :func:`jaxfric.io.output.error_estimate`: as :func:`step_check`, with ``"ratio"`` the
    companion's element length over the run's (the run's element count along over the companion's).
    Costs about half (``finer``: two to three times) the run, and a compilation."""
    from .. import scenes

    if finer:
        overrides, what = scenes.finer_along(scene.name, scene.config), "mesh check (finer mesh)"
    else:
        if scene.model.mesh.nx < 2:
            raise ValueError("the mesh check needs at least 2 elements along the strip to halve them")
        overrides, what = scenes.coarser_along(scene.name, scene.config), "mesh check (coarser mesh)"
    check = companion(scene, overrides, what, progress)
    return {**check, "ratio": scene.model.mesh.nx / check["mesh"][0]}


def layers_check(scene, progress: bool = False) -> dict:
    """The run of ``scene`` again with twice the elements through the thickness
    (:func:`jaxfric.scenes.finer_through`), for the ``layers`` component of
    :func:`jaxfric.io.output.error_estimate`: as :func:`step_check`, with ``"ratio"`` 0.5 (the layers'
    thickness halved). Costs about twice the run, and a compilation."""
    from .. import scenes

    check = companion(scene, scenes.finer_through(scene.name, scene.config), "layers check (twice the layers)",
                      progress)
    return {**check, "ratio": scene.model.mesh.ny / check["mesh"][1]}


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
    :func:`jaxfric.io.batch.run_case`); None where a quantity is missing (a run that stopped early)."""
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
           "ref_mesh": mesh_label(test.ref_mesh), "ref_step": test.ref_step}
    usable = ref is not None and bool(ref["summary"].get("converged")) and bool(s.get("converged"))
    row.update(error_measures(c, ref, test.instant) if usable else dict.fromkeys(MEASURES))
    row["message"] = s.get("message", "")
    return row


def test_rows(out: str, test: Test, run_missing: bool, rerun: bool = False, progress: bool = False,
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
    return (not mesh or mesh == mesh_label(test.ref_mesh)) and (step is None or math.isclose(step, test.ref_step))


def _run_path(out: str, test: Test, label: str, *rest) -> str:
    return os.path.join(out, "runs", test.run_dir, label, *rest)


_INT_COLUMNS = ("n_steps", "newton_iters_total", "cutbacks")
_TEXT_COLUMNS = ("test", "scene", "variant", "run", "family", "algorithm", "mesh", "message", "ref_mesh")


def read_rows(out: str) -> list[dict]:
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
    kept = read_rows(out)
    return [r for t in (QUICK_TESTS if quick else TESTS) for r in test_rows(out, t, run_missing=False, kept=kept)]


