"""The error estimate of a run against its true error: per case (a scene variant at a mesh), the run,
the companions that ``jaxfric run --error-estimate mesh`` and ``--error-estimate step`` make (half the
elements along the strip; half the nominal increments), and a reference built from other runs:

- along the strip, the run's mesh with 2 and 4 times the elements, Richardson's limit with the observed
  ratio of successive changes (the finest run where the changes do not shrink);
- through the thickness, twice the layers at the run's length, added as a correction (one doubling: a
  lower bound of the layers' share where they converge from one side), or, with ``--extra layers4``,
  Richardson's limit of 1, 2 and 4 times the layers;
- the step, a quarter of the nominal increments beside the half, Richardson's limit with the observed
  order (with ``--extra eighth_step``, of the half, quarter and eighth), added as a correction.

The estimates are those of ``jaxfric run --error-estimate``: ``mesh`` (coarser companion), ``mesh_fine``
(the ladder's first rung, so its ratio to the length's true error is 2 (q - 1) / q, q the observed ratio),
``step`` (half increments) and ``layers`` (twice the layers, the reference's first rung too). The
coarser companion shares no run with the reference.

    python experiments/error_estimates.py [--cases CASE ...] [--jobs 2] [--out runs/error_estimates]

Cases ``SCENE_VARIANT`` at the spec mesh, and the Nine at the fitting mesh 100 x 2 (:data:`CASES`; the Nine
drawn 36 mm). Each run's steady drawing force is kept
in ``OUT/CASE.json`` as it finishes, so an interrupted study resumes where it stopped. Writes
``experiments/results/error_estimates.csv`` with every case whose runs are all in ``OUT``, and the
committed row of every other case (records are not committed): a run of a few cases on a fresh checkout
keeps the others' rows. Exact contact (``lcp_ssn``), the scenes' defaults otherwise.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
from concurrent.futures import ProcessPoolExecutor

RESULTS = os.path.join(os.path.dirname(__file__), "results")

#: case -> (scene, variant, config overrides of the run). The Nine is drawn 36 mm: its steady window
#: (20 to 35 mm) and one more, as the accuracy study's tests.
CASES = {
    "flat_die_const_position": ("flat_die", "const_position", {}),
    "flat_die_const_force": ("flat_die", "const_force", {}),
    "bead_th045_mu000": ("bead", "th045_mu000", {}),
    "bead_th045_mu017": ("bead", "th045_mu017", {}),
    "bead_th090_mu000": ("bead", "th090_mu000", {}),
    "bead_th090_mu017": ("bead", "th090_mu017", {}),
    "bead_th135_mu000": ("bead", "th135_mu000", {}),
    "bead_th135_mu017": ("bead", "th135_mu017", {}),
    **{f"blankholder_shape{i}": ("blankholder", f"shape{i}", {}) for i in range(1, 10)},
    "nine_mu000": ("nine", "mu000", {"U_draw": 36.0}),
    "nine_mu017": ("nine", "mu017", {"U_draw": 36.0}),
    "nine_mu000_100x2": ("nine", "mu000", {"U_draw": 36.0, "mesh": "100x2"}),
    "nine_mu017_100x2": ("nine", "mu017", {"U_draw": 36.0, "mesh": "100x2"}),
}

#: the runs of a case, cheapest first: name -> what it changes
RUNS = ("run", "coarse", "half_step", "layers", "fine2", "quarter_step", "fine4")
#: runs made only when asked for (``--extra``): an eighth of the increments, for a step ladder that
#: starts at half of them where the run's own increments are outside the asymptotic range; four times
#: the layers, for a layers' limit by Richardson instead of one doubling
EXTRA_RUNS = ("eighth_step", "layers4")


def _overrides(scene, name: str) -> dict:
    """Config overrides of run ``name`` of ``scene`` (its spec configuration)."""
    from jaxfric import scenes

    config = scene.config
    if name == "run":
        return {}
    if name == "coarse":
        return scenes.coarser_along(scene.name, config)
    if name in ("half_step", "quarter_step", "eighth_step"):
        factor = {"half_step": 0.5, "quarter_step": 0.25, "eighth_step": 0.125}[name]
        return scenes.scaled_steps(scene.name, config, factor)
    if name in ("layers", "layers4"):
        return scenes.finer_through(scene.name, config, 2 if name == "layers" else 4)
    return scenes.finer_along(scene.name, config, {"fine2": 2, "fine4": 4}[name])


def run_case(case: str, out: str, extra: tuple = ()) -> dict:
    """The steady drawing forces of ``case``'s runs, read from and added to ``out/CASE.json``."""
    from jaxfric import scenes
    from jaxfric.identification import accuracy

    path = os.path.join(out, f"{case}.json")
    done = read_record(path)
    scene_name, variant, overrides = CASES[case]
    scene = scenes.make(scene_name, variant, "lcp_ssn", overrides)
    for name in RUNS + tuple(extra):
        if name in done:
            continue
        print(f"{case}: {name}", file=sys.stderr, flush=True)
        check = accuracy.companion(scene, _overrides(scene, name), f"{case} {name}", progress=False)
        done[name] = {"steady": check["steady"], "n_steps": check["n_steps"], "mesh": list(check["mesh"])}
        write_record(path, done)
    return done


def committed_rows(path: str) -> dict:
    """The rows of the table at ``path`` by case, as written (none if there is no table)."""
    from benchutil import read_rows

    return {row["case"]: row for row in read_rows(path)}


def table(rows: list[dict], committed: dict) -> list[dict]:
    """The table in :data:`CASES`' order: the summarised ``rows``, and the ``committed`` row of every other
    case (its runs not all recorded here, as on a fresh checkout)."""
    fresh = {r["case"]: r for r in rows}
    return [fresh.get(case) or committed[case] for case in CASES if case in fresh or case in committed]


def read_record(path: str) -> dict:
    """The runs recorded in ``path`` (JSON, run name -> figures), or none."""
    if not os.path.exists(path):
        return {}
    with open(path) as f:
        return json.load(f)


def write_record(path: str, done: dict) -> None:
    """Write the runs ``done`` to ``path`` whole or not at all (a temporary file renamed over it), so that
    an interrupted study resumes from the last run written."""
    with open(path + ".tmp", "w") as f:
        json.dump(done, f, indent=1)
    os.replace(path + ".tmp", path)


def write_csv(path: str, rows: list[dict]) -> None:
    """``rows`` as a CSV table, floats to 6 significant digits; the columns of every row (a committed row of
    an earlier version of :func:`summarise` leaves the columns it lacks empty)."""
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(dict.fromkeys(k for r in rows for k in r)))
        writer.writeheader()
        writer.writerows({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()} for r in rows)


def richardson(f1: float, f2: float, f4: float) -> tuple[float, float]:
    """The limit of f1, f2, f4 (each step refining by the same factor) with the observed ratio of their
    successive changes q = (f1 - f2) / (f2 - f4), and q; where the changes do not shrink (q <= 1 or of
    opposite signs) the finest value f4 and q as observed."""
    d1, d2 = f1 - f2, f2 - f4
    q = d1 / d2 if d2 != 0 else math.inf
    if not math.isfinite(q) or q <= 1.0:
        return f4, q
    return f4 - d2 / (q - 1.0), q


def summarise(case: str, runs: dict) -> dict:
    """The estimate against the true error of ``case``'s run (all in % of the run's force, signed where
    it is an error, unsigned where it is an estimate). The estimates are those ``jaxfric run`` prints
    (:func:`jaxfric.io.output.richardson_error`): ``mesh`` from the coarser companion, ``mesh_fine`` from
    ``fine2`` (the companion of ``--error-estimate mesh_fine``, also the reference's first rung, so its
    ratio to the true error is 2 (q - 1) / q with q the observed ratio ``q_along``), ``step`` from the
    half increments. Where ``eighth_step`` was run, the step limit comes from the half, quarter and eighth."""
    from jaxfric.io.output import richardson_error

    F = {k: v["steady"] for k, v in runs.items()}
    run = F["run"]
    along, q_along = richardson(run, F["fine2"], F["fine4"])
    step_ladder = ("half_step", "quarter_step", "eighth_step") if "eighth_step" in F else ("run", "half_step",
                                                                                          "quarter_step")
    step, q_step = richardson(*(F[k] for k in step_ladder))
    if "layers4" in F:
        layers_limit, q_layers = richardson(run, F["layers"], F["layers4"])
    else:
        layers_limit, q_layers = F["layers"], math.nan
    layers = layers_limit - run
    reference = along + layers + (step - run)
    coarse_ratio = runs["run"]["mesh"][0] / runs["coarse"]["mesh"][0]
    est_mesh = abs(richardson_error(run, F["coarse"], coarse_ratio)) / abs(run)
    est_fine = abs(richardson_error(run, F["fine2"], 0.5)) / abs(run)
    est_step = abs(richardson_error(run, F["half_step"], 0.5)) / abs(run)
    est_layers = abs(richardson_error(run, F["layers"], 0.5)) / abs(run)
    estimate = math.hypot(est_mesh, est_step)
    estimate_fine = math.hypot(est_fine, est_step)
    estimate_all = math.hypot(est_fine, est_step, est_layers)
    true = (run - reference) / reference
    pct = 100.0
    return {
        "case": case, "mesh": "x".join(map(str, runs["run"]["mesh"])), "force": run,
        **{f"F_{k}": F[k] for k in RUNS}, **{f"F_{k}": F.get(k, math.nan) for k in EXTRA_RUNS},
        "along_limit": along, "q_along": q_along, "step_limit": step, "q_step": q_step,
        "reference": reference,
        "true_along_pct": pct * (run - along) / along, "est_mesh_pct": pct * est_mesh,
        "est_mesh_fine_pct": pct * est_fine,
        "true_step_pct": pct * (run - step) / step, "est_step_pct": pct * est_step,
        "q_layers": q_layers, "true_layers_pct": -pct * layers / layers_limit, "est_layers_pct": pct * est_layers,
        "true_pct": pct * true, "estimate_pct": pct * estimate, "estimate_fine_pct": pct * estimate_fine,
        "estimate_over_true": estimate / abs(true) if true else math.inf,
        "estimate_fine_over_true": estimate_fine / abs(true) if true else math.inf,
        "estimate_all_pct": pct * estimate_all,
        "estimate_all_over_true": estimate_all / abs(true) if true else math.inf,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--jobs", type=int, default=1, help="cases run at once, one process each")
    parser.add_argument("--extra", nargs="*", default=[], choices=list(EXTRA_RUNS), help="runs beyond RUNS")
    parser.add_argument("--out", default="runs/error_estimates", help="folder of the per-case run records")
    args = parser.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        done = dict(zip(args.cases, pool.map(run_case, args.cases, [args.out] * len(args.cases),
                                                 [tuple(args.extra)] * len(args.cases))))
    # Every case with all its runs on disk, not only those asked for: a run of a few cases keeps the others' rows.
    for case in CASES:
        path = os.path.join(args.out, f"{case}.json")
        if case not in done and os.path.exists(path):
            with open(path) as f:
                done[case] = json.load(f)
    rows = [summarise(case, done[case]) for case in CASES if case in done and all(k in done[case] for k in RUNS)]
    os.makedirs(RESULTS, exist_ok=True)
    path = os.path.join(RESULTS, "error_estimates.csv")
    write_csv(path, table(rows, committed_rows(path)))
    for r in rows:
        print(f"{r['case']:26s} F {r['force']:9.4f}  true {r['true_pct']:+7.3f} %  estimate {r['estimate_pct']:6.3f} %"
              f" (fine {r['estimate_fine_pct']:6.3f} %)  along {r['true_along_pct']:+.3f} / est {r['est_mesh_pct']:.3f}"
              f" (fine {r['est_mesh_fine_pct']:.3f}); step {r['true_step_pct']:+.3f} / est {r['est_step_pct']:.3f};"
              f" layers {r['true_layers_pct']:+.3f}")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
