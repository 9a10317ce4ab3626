"""Increments chosen by the step error estimate (``--set step_error=TOL``) against fixed increments: per
case, the steps, Newton iterations and solve time of each run, and its steady drawing force's error
against the step-converged force.

Runs per case: the nominal increments and a half, a quarter and an eighth of them (the fixed ladder),
and the error-controlled runs at each tolerance of ``--tols``. The reference is Richardson's limit of
the half, quarter and eighth with their observed ratio of successive changes (as
``experiments/error_estimates.py``): the step error only, each case at its own mesh.

    python experiments/step_error_control.py [--cases CASE ...] [--tols 0.03 0.01 0.003] [--jobs 2]
        [--out runs/step_error_control]
    python experiments/step_error_control.py --strip    # a transient: experiments/results/step_error_control_strip.csv

Per error-controlled run, ``fixed_newton_same_error``: the Newton iterations the fixed ladder takes for
the same error (log-log interpolation). Each run's figures are kept in ``OUT/CASE.json`` as it
finishes, so an interrupted study resumes. Writes ``experiments/results/step_error_control.csv`` and
``.png`` (error against Newton iterations). Exact contact (``lcp_ssn``); ``--jobs`` cases at once, one
process each (with one XLA thread each:
``XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor

from error_estimates import read_record, richardson, write_csv, write_record  # experiments/: the script's folder

RESULTS = os.path.join(os.path.dirname(__file__), "results")

#: case -> (scene, variant, config overrides). The Nine is drawn 36 mm: its steady window (20 to 35 mm)
#: and one more.
CASES = {
    "nine_mu000": ("nine", "mu000", {"U_draw": 36.0}),
    "nine_mu017": ("nine", "mu017", {"U_draw": 36.0}),
    "nine_mu000_100x2": ("nine", "mu000", {"U_draw": 36.0, "mesh": "100x2"}),
    "nine_mu017_100x2": ("nine", "mu017", {"U_draw": 36.0, "mesh": "100x2"}),
}

FIXED = {"fixed_1": 1.0, "fixed_1/2": 0.5, "fixed_1/4": 0.25, "fixed_1/8": 0.125}


def _steady(scene, result) -> float:
    from jaxfric.io import instants, output

    _, _, values = output.history_table(scene, result)
    window, _ = instants.steady_window(scene.name, values, scene.steady_window)
    return float(instants.steady_drawing_force({**values, "phase_name": values["phase"]}, window))


def run_case(case: str, out: str, tols: tuple) -> dict:
    """The figures of ``case``'s runs, read from and added to ``out/CASE.json``."""
    from jaxfric import scenes
    from jaxfric.identification import accuracy

    path = os.path.join(out, f"{case}.json")
    done = read_record(path)
    scene_name, variant, overrides = CASES[case]
    scene = scenes.make(scene_name, variant, "lcp_ssn", overrides)
    todo = {name: scenes.scaled_steps(scene.name, scene.config, factor) for name, factor in FIXED.items()}
    # A tight target takes more steps than the default history buffer (10x the nominal steps) holds.
    todo.update({f"error_{tol:g}": {"step_error": float(tol), "max_steps": 20_000} for tol in tols})
    for name, change in todo.items():
        if name in done:
            continue
        print(f"{case}: {name}", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        other, result = accuracy.companion_run(scene, change, f"{case} {name}")
        done[name] = {"steady": _steady(other, result), "steps": int(len(result.history["time"]) - 1),
                      "newton": int(sum(result.history["newton_iters"])),
                      "cutbacks": int(sum(result.history["cutbacks"])), "solve_s": result.wall_s,
                      "cpu_s": result.cpu_s, "compile_s": result.compile_s,
                      "total_s": time.perf_counter() - t0}
        write_record(path, done)
    return done


def fixed_iterations_at(error_pct: float, runs: dict) -> float:
    """The Newton iterations the fixed ladder (nominal, half and quarter increments; the eighth is in the
    reference) would take for a step error of ``error_pct`` (unsigned), interpolated log-log between its
    neighbours (beyond the ladder, along its nearest segment)."""
    ladder = [(runs[k]["newton"], abs(runs[k]["error_pct"])) for k in ("fixed_1", "fixed_1/2", "fixed_1/4")]
    (n0, e0), (n1, e1) = ladder[:2] if abs(error_pct) >= ladder[1][1] else ladder[1:]
    t = (math.log(abs(error_pct)) - math.log(e0)) / (math.log(e1) - math.log(e0))
    return math.exp(math.log(n0) + t * (math.log(n1) - math.log(n0)))


def rows_of(case: str, runs: dict) -> list[dict]:
    """One row per run of ``case`` with its error against the step limit (signed, %): Richardson's limit
    of the half, quarter and eighth of the nominal increments with their observed ratio."""
    limit, q = richardson(*(runs[k]["steady"] for k in ("fixed_1/2", "fixed_1/4", "fixed_1/8")))
    out = []
    for name, r in runs.items():
        tol = float(name.split("_", 1)[1]) if name.startswith("error_") else math.nan
        factor = FIXED.get(name, math.nan)
        out.append({"case": case, "run": name, "step_error": tol, "increment_factor": factor,
                    "steady": r["steady"], "error_pct": 100.0 * (r["steady"] - limit) / limit,
                    "error_over_tol": abs(r["steady"] - limit) / limit / tol if tol == tol else math.nan,
                    "steps": r["steps"], "newton": r["newton"], "cutbacks": r["cutbacks"], "cpu_s": r["cpu_s"],
                    "step_limit": limit, "q_step": q})
    errors = {r["run"]: {"newton": r["newton"], "error_pct": r["error_pct"]} for r in out}
    for r in out:
        r["fixed_newton_same_error"] = (fixed_iterations_at(r["error_pct"], errors) if r["run"].startswith("error_")
                                        else math.nan)
    return out


def strip_rows(tols=(0.02, 0.005, 0.002), nominal=(4, 20), refine=16) -> list[dict]:
    """A transient beside the Nine's steady draw: the stretch-bend strip (``strips.stretch_bend_strip``,
    10 x 2 elements, pulled 1 %, then its end turned 20 degrees, the flow at the hinges turning from
    tension to bending), its end reaction's error against a run on ``refine`` times the nominal steps,
    with fixed increments (the nominal ones, and as many as the controlled run took) and by
    ``step_error``."""
    import numpy as np

    from jaxfric import StepControl, run
    from strips import stretch_bend_strip

    def strip(n_stretch, n_bend):
        return stretch_bend_strip(nx=10, ny=2, length=10.0, stretch=0.1, n_stretch=n_stretch, n_bend=n_bend)

    def reaction(result):
        return np.asarray(result.history["reaction_right"][-1])

    reference = reaction(run(strip(*(refine * n for n in nominal)), progress=False))

    def row(name, result, tol=math.nan):
        error = float(np.linalg.norm(reaction(result) - reference) / np.linalg.norm(reference))
        return {"run": name, "step_error": tol, "steps": int(len(result.history["time"]) - 1),
                "newton": int(sum(result.history["newton_iters"])), "error": error,
                "error_over_tol": error / tol if tol == tol else math.nan}

    rows = [row("fixed_1", run(strip(*nominal), progress=False))]
    for tol in tols:
        controlled = row(f"error_{tol:g}", run(strip(*nominal), control=StepControl(step_error=tol), progress=False),
                         tol)
        factor = controlled["steps"] / sum(nominal)
        same = run(strip(*(max(1, round(factor * n)) for n in nominal)), progress=False)
        rows += [controlled, row(f"fixed_same_steps_{tol:g}", same)]
    return rows


def plot(rows: list[dict], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    cases = list(dict.fromkeys(r["case"] for r in rows))
    fig, axes = plt.subplots(1, len(cases), figsize=(3.6 * len(cases), 3.4), squeeze=False)
    for ax, case in zip(axes[0], cases):
        mine = [r for r in rows if r["case"] == case and r["run"] != "fixed_1/8"]
        for kind, style, label in (("fixed", "o-", "fixed increments"), ("error", "s--", "step_error")):
            pts = sorted((r["newton"], abs(r["error_pct"]), r) for r in mine if r["run"].startswith(kind))
            ax.loglog([p[0] for p in pts], [max(p[1], 1e-3) for p in pts], style, label=label)
            for n, e, r in pts:
                text = f"{r['step_error']:g}" if kind == "error" else r["run"].split("_")[1]
                ax.annotate(text, (n, max(e, 1e-3)), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda x, _: f"{x:.0f}"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_title(case, fontsize=9)
        ax.set_xlabel("Newton iterations")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("|steady force's step error| (%)")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--tols", nargs="+", type=float, default=[0.03, 0.01, 0.003])
    parser.add_argument("--jobs", type=int, default=1, help="cases run at once, one process each")
    parser.add_argument("--out", default="runs/step_error_control", help="folder of the per-case run records")
    parser.add_argument("--strip", action="store_true", help="the stretch-bend strip only (strip_rows)")
    args = parser.parse_args(argv)
    if args.strip:
        rows = strip_rows()
        path = os.path.join(RESULTS, "step_error_control_strip.csv")
        write_csv(path, rows)
        for r in rows:
            print(f"{r['run']:22s} steps {r['steps']:4d}  Newton {r['newton']:5d}  error {100 * r['error']:.3f} %")
        print(f"wrote {path}")
        return 0
    os.makedirs(args.out, exist_ok=True)
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        done = dict(zip(args.cases, pool.map(run_case, args.cases, [args.out] * len(args.cases),
                                                 [tuple(args.tols)] * len(args.cases))))
    for case in CASES:   # every case on disk, so a run of a few cases keeps the others' rows
        path = os.path.join(args.out, f"{case}.json")
        if case not in done and os.path.exists(path):
            with open(path) as f:
                done[case] = json.load(f)
    rows = [r for case in CASES if case in done and all(k in done[case] for k in FIXED)
            for r in rows_of(case, done[case])]
    os.makedirs(RESULTS, exist_ok=True)
    path = os.path.join(RESULTS, "step_error_control.csv")
    write_csv(path, rows)
    plot(rows, path.replace(".csv", ".png"))
    for r in rows:
        print(f"{r['case']:18s} {r['run']:12s} F {r['steady']:9.4f}  error {r['error_pct']:+7.3f} %  "
              f"steps {r['steps']:5d}  Newton {r['newton']:6d}  cpu {r['cpu_s']:7.1f} s")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
