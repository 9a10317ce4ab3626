"""The accuracy-against-run-time report (``jaxfric report accuracy-cost``): runs the sweep of
:mod:`jaxfric.identification.accuracy` and writes what it found: ``accuracy_cost.csv``, the Pareto plots
``pareto_<test>.png`` and ``accuracy_cost.md`` (per test and measure, whether the reference resolves the
errors, and the cheapest run that reaches 10 %, 1 % and 0.1 %)."""

from __future__ import annotations

import math
import os

from ..io.batch import write_csv
from . import accuracy as acc

__all__ = ["accuracy_cost", "write_report", "reference_checks", "recommendations", "pareto_front",
           "report_markdown", "reference_lines"]


def accuracy_cost(out: str, quick: bool = False, tests=None, rerun: bool = False, progress: bool = False,
                  log=print) -> list[dict]:
    """Run the sweep of every test (``acc.TESTS``, or ``acc.QUICK_TESTS`` with ``quick``; ``tests``: names to
    keep) into ``out``, then write the CSV, the Pareto plots and the recommendations of every test found
    in ``out`` (also those of earlier invocations). Returns those rows."""
    pool = acc.QUICK_TESTS if quick else acc.TESTS
    chosen = [t for t in pool if tests is None or t.name in tests]
    if not chosen:
        raise ValueError(f"no test selected; choose from {', '.join(t.name for t in pool)}")
    # The CSV written between runs holds every row known: the rows of the tests not run here as the CSV
    # on disk has them at that moment (another process may be running them), and the earlier rows of
    # each chosen test until it has started (run directories are not kept with the results).
    names = {t.name for t in chosen}
    kept = acc.read_rows(out)
    before = {t.name: acc.test_rows(out, t, run_missing=False, kept=kept) for t in chosen}
    done: list[dict] = []
    started: set[str] = set()

    def write_partial(current: list[dict]) -> None:
        others = [r for r in acc.read_rows(out) if r["test"] not in names]
        later = [r for t in chosen if t.name not in started for r in before[t.name]]
        write_csv(os.path.join(out, "accuracy_cost.csv"), others + done + current + later)

    for test in chosen:
        started.add(test.name)
        done += acc.test_rows(out, test, run_missing=True, rerun=rerun, progress=progress, log=log,
                           on_row=write_partial)
    return write_report(out, quick)


def write_report(out: str, quick: bool = False) -> list[dict]:
    """Write the CSV, the Pareto plots and ``accuracy_cost.md`` of every test whose runs are in ``out``
    (nothing is run); returns the rows."""
    rows = acc.collect(out, quick)
    write_csv(os.path.join(out, "accuracy_cost.csv"), rows)
    for test in acc.QUICK_TESTS if quick else acc.TESTS:
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
    for m in acc.MEASURES:
        changes = [r[m] for r in ref_checks if r[m] is not None]
        change = max(changes) if ref_checks and len(changes) == len(ref_checks) else None
        resolution = None if change is None else max(10.0 * change, acc.ROUNDOFF)
        errors = [r[m] for r in sweep if r[m] is not None and resolution is not None and r[m] >= resolution]
        smallest = min(errors) if errors else None
        ok = change is not None and (change <= acc.ROUNDOFF if smallest is None else change < 0.1 * smallest)
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


def _pareto_figure(path: str, test: acc.Test, rows: list[dict]) -> None:
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
            y = [max(r[measure], acc.FLOOR) for r in sel]
            ax.plot(x, y, style, label=family, alpha=0.85)
            pts += [(r["wall_s"], max(r[measure], acc.FLOOR), r["run"]) for r in sel]
        front = pareto_front(pts)
        if front:
            ax.step([p[0] for p in front], [p[1] for p in front], where="post", color="k", lw=1, alpha=0.6,
                    label="Pareto front")
            ax.plot([p[0] for p in front], [p[1] for p in front], "o", mfc="none", mec="k", ms=11)
            for x, y, label in front:
                ax.annotate(label, (x, y), textcoords="offset points", xytext=(5, 3), fontsize=6)
        for level in acc.LEVELS:
            ax.axhline(level, color="gray", ls=":", lw=0.8)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        resolution = check[measure]["resolution"]
        low, high = ax.get_ylim()
        if resolution is not None and resolution > max(acc.FLOOR, low):
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
                 f"{acc.mesh_label(test.ref_mesh)}, increments nominal / {1 / test.ref_step:g})", fontsize=10)
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
    mains = {t.name: t.main for t in (*acc.TESTS, *acc.QUICK_TESTS)}
    mains.update(measures or {})
    out = []
    for test in dict.fromkeys(r["test"] for r in rows):
        measure = mains.get(test, "err_steady")
        selected = [r for r in rows if r["test"] == test]
        resolution = _reference_check(selected)[measure]["resolution"]
        sweep = [r for r in selected if r["family"] not in ("reference", "ref_check")
                 and r["converged"] and r[measure] is not None]
        for level in acc.LEVELS:
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


def _reference_law(test: acc.Test) -> str:
    """The reference's contact law, in words."""
    if test.ref_algorithm == "auglag":
        return f"auglag, target gap {test.ref_gap:g} mm"
    return f"{test.ref_algorithm} (exact contact)"


def reference_lines(rows: list[dict], quick: bool) -> list[str]:
    """A table of what each test's errors are measured against."""
    known = {t.name: t for t in (acc.QUICK_TESTS if quick else acc.TESTS)}
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
                           f"mesh {acc.mesh_label(t.check_mesh_of(c))}" for c in t.ref_checks)
        lines.append(f"| {name} | {_reference_law(t)} | {acc.mesh_label(t.ref_mesh)} | nominal / {1 / t.ref_step:g} | "
                     f"{checks} | {what} |")
    return lines + [""]


def report_markdown(rows: list[dict], checks: dict, quick: bool) -> str:
    lines = ["Error measures (each relative, against the test's reference): " +
             "; ".join(f"`{m}` {doc}" for m, doc in acc.MEASURE_DOC.items()) + ". Wall time is the solve time "
             "(compilation apart, in the CSV). An error below the reference's resolution (10 x its own "
             "uncertainty, table below) is shown as `< resolution`: it cannot be told apart from the "
             "reference's error.", ""]
    lines += reference_lines(rows, quick)
    lines += ["**What to pick** (the cheapest run of the sweep that reaches the level on the test's main "
              "measure; `–`: none of the sweep does; `unverifiable`: the level is below the reference's "
              "resolution):", "", "| test | measure | 10 % | 1 % | 0.1 % |", "|---|---|---|---|---|"]
    recs = recommendations(rows)
    for test in dict.fromkeys(r["test"] for r in recs):
        cells = []
        for level in acc.LEVELS:
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
              + " | ".join(acc.MEASURES) + " | estimate |", "|" + "---|" * (8 + len(acc.MEASURES))]
    for r in rows:
        res = checks.get(r["test"], {})
        cells = [_fmt(r[m]) if r["family"] in ("reference", "ref_check") else
                 _error_cell(r[m], res.get(m, {}).get("resolution")) for m in acc.MEASURES]
        lines.append(f"| {r['test']} | {r['run']} | {'yes' if r['converged'] else '**no**'} | {_fmt(r['n_steps'])} | "
                     f"{_fmt(r['newton_iters_total'])} | {_fmt(r['wall_s'])} | {_fmt(r['max_penetration'])} | "
                     + " | ".join(cells) + f" | {_fmt(r['error_estimate'])} |")
    bad = [r for r in rows if not r["converged"]]
    if bad:
        lines += ["", "Runs that did not complete:", ""] + [f"- {r['test']} `{r['run']}`: {r['message']}" for r in bad]
    return "\n".join(lines) + "\n"
