"""The five studies of the benchmark specification (section 7), and the algorithms on common steps.

    python experiments/studies.py STUDY [--only TEXT] [--rerun] [--no-run-figures]

STUDY is one of ``penalty_sensitivity``, ``auglag_sensitivity``, ``mesh_convergence``,
``blankholder_shapes``, ``algorithm_agreement``, ``common_steps`` (every algorithm on the step sequence
of the semismooth Newton run) or ``all``. Each case is an ordinary run: its run
directory (outputs contract) goes to ``experiments/results/studies/<study>/runs/<case>/`` (not
committed), and the study writes ``table.csv`` and ``figure.png`` (plus the figures the spec names) into
``experiments/results/studies/<study>/`` and its section of ``docs/results.md`` (between
``<!-- BEGIN study:<study> -->`` and ``<!-- END study:<study> -->``).

Nothing is lost when a run fails or the script is interrupted:

- the table is rewritten after every case, so it always holds every case finished so far;
- a case whose run directory already holds a ``summary.json`` is read back instead of run again
  (``--rerun`` forces a new run), so an interrupted study resumes where it stopped;
- a case keeps its checkpoint in its run directory while it runs (about every minute,
  :func:`jaxfric.io.batch.run_case`), so a study killed in the middle of a case (a time limit's SIGTERM,
  Ctrl-C) continues that case from where it stood, bit for bit: a case of hours can run over several
  sittings;
- a run that stops early keeps its partial run directory and enters the table with
  ``converged = False`` and the reason in ``message``;
- the Nine sensitivity and mesh studies and the algorithm agreement also keep the rows of their
  committed ``table.csv`` whose run directories are absent (a fresh checkout), so a study continues
  across invocations; the agreement keeps each case's curves and contact states beside it
  (``curves/<case>.npz``, committed), so new cases are compared with old ones without rerunning them.

Wall times are solve times (compilation apart, in ``compile_s``) and are comparable only within one
study taken on one machine; the device is recorded in every run's ``summary.json``.
"""

from __future__ import annotations

import argparse
import collections
import csv
import json
import math
import os
import sys

# Studies run side by side on a 2-core machine. An unpinned process then gets OpenBLAS's two threads,
# which spin against the other processes: the LU of a 384 x 384 basis (Lemke's host pivoting, Nine band)
# took 31 ms instead of 5.9 ms, and one Lemke call 0.27 s instead of 0.019 s (a process pinned with
# taskset gets one thread anyway). Set before NumPy loads OpenBLAS.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

from jaxfric import scenes
from jaxfric.contact.formulations import ALGORITHMS
from jaxfric.io.batch import matching_rows, phase_curve, run_case, stale, write_csv

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.join(HERE, "results", "studies")
RESULTS_MD = os.path.join(HERE, "..", "docs", "results.md")
NINE_MESH = "300x3"
EPS_PENALTY = (1e2, 1e3, 1e4, 1e5, 1e6)
EPS_AUGLAG = (1e4, 1e5)
TARGET_GAPS = (1e-3, 1e-4, 1e-5, 1e-6)
# Augmentations allowed per step: the spec's 20 [chosen], except eps_N = 1e4 with a target gap of 1e-6 mm,
# whose accepted steps take 28 (mu000) and 32 (mu017) augmentations on average (the study's table,
# `mean_augmentations`). A node entering contact starts from lambda_N = 0, i.e. a penetration of
# R_N / eps_N, and each augmentation shrinks it by a fixed factor (Uzawa), so the count it needs does not
# fall with the step and a cut step cannot pass; 60 leaves room for the tail of that distribution.
MAX_AUGMENTATIONS = {(1e4, 1e-6): 60}
# History buffer (accepted steps) of the penalty runs: the scenes' default, 10x the nominal steps + 200
# (8300 rows on the Nine), except eps_N = 1e6. With 8300, both variants filled it in the draw at U = 32
# of 70 mm (the clamp and 32 mm of draw in 8300 accepted steps, against 810 nominal steps for the whole
# path; 858 and 598 cutbacks): the spec's controller has no step limit, so those runs get room for the
# whole stroke.
MAX_STEPS = {1e6: 30_000}
MESHES = [(nx, ny) for ny in (3, 6) for nx in (150, 300, 600, 1200)]
# The settings the studies' tables in docs/results.md were run with, where they differ from the scenes'
# defaults: F-bar elements with 2 x 2 points (the Nine's and the bead's default is ``ans``, the
# blankholder's ``anst`` with 4 points per layer; the Nine's discretisation error with each element:
# experiments/nine_error_sources.py) and, on the Nine, v = 0 on the strip's left-end nodes instead of the
# entry guide's channel (the tail stays far from A in every study's draw). The studies in AT_DEFAULTS were
# run again with the scenes' defaults.
STUDY_SETTINGS = {"element": "fbar"}
SCENE_STUDY_SETTINGS = {"nine": {"entry_guide_kind": "end_nodes"}, "blankholder": {"thickness_points": 2}}
AT_DEFAULTS = ("mesh_convergence", "common_steps", "penalty_sensitivity", "auglag_sensitivity",
               "blankholder_shapes", "algorithm_agreement")


def settings_label(study: str) -> str:
    """A table's ``settings`` column for the cases ``study`` runs now: ``defaults`` (in AT_DEFAULTS) or
    ``study`` (STUDY_SETTINGS and SCENE_STUDY_SETTINGS). Rows without the column were run at ``study``."""
    return "defaults" if study in AT_DEFAULTS else "study"


def row_settings(row: dict) -> str:
    """The settings a table row was run at (:func:`settings_label`; ``study`` where it has none)."""
    return row.get("settings") or "study"


def study_settings(scene_name: str, study: str = "") -> dict:
    """The overrides every case of ``study`` on ``scene_name`` starts from (see STUDY_SETTINGS)."""
    if study in AT_DEFAULTS:
        return {}
    return {**STUDY_SETTINGS, **SCENE_STUDY_SETTINGS.get(scene_name, {})}
GRID = 200


# --------------------------------------------------------------------------------------------- runs
def case(study: str, name: str, scene_name: str, variant: str, algorithm: str, overrides: dict,
         opts, steps=None) -> dict:
    """Run one case into ``runs/<name>`` of the study (or read it back): :func:`jaxfric.io.batch.run_case`
    (``steps``: end times of the steps to take instead of the nominal increments). With ``--collect`` a run
    on disk made at other settings is read back as it is, not run again."""
    return run_case(os.path.join(ROOT, study, "runs", name), scene_name, variant, algorithm,
                    {**study_settings(scene_name, study), **overrides}, rerun=opts.rerun and _selected(opts, name),
                    rerun_stale=not opts.collect, progress=opts.progress, steps=steps,
                    figures=opts.run_figures, tag=study, log=lambda m: print(f"[{study}] {m}", flush=True))


def _full_steps(algorithm: str) -> dict:
    """A case's overrides in ``algorithm_agreement`` and ``common_steps``: their ``lcp_lemke`` rows take full
    Newton steps (``lemke_search`` False; the scenes line-search them)."""
    return {"lemke_search": False} if algorithm == "lcp_lemke" else {}


def common(summary: dict) -> dict:
    """The run-cost and contact columns every study table shares."""
    get = summary.get
    return {"n_steps": get("n_steps"), "cutbacks": get("n_cutbacks"),
            "newton_iters_total": get("newton_iters_total"), "wall_s": _r(get("wall_s")),
            "cpu_s": _r(get("cpu_s")), "compile_s": _r(get("compile_s")),
            "max_penetration": _r(get("max_penetration")),
            "steady_drawing_force": _r(get("steady_drawing_force")), "converged": bool(get("converged"))}


def _r(value, digits=6):
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return value
    return float(f"{value:.{digits}g}")


def write_table(study: str, rows: list[dict]) -> str:
    return write_csv(os.path.join(ROOT, study, "table.csv"), rows)


def markdown_table(rows: list[dict], columns: list[str]) -> str:
    def fmt(v):
        if v is None or v == "":
            return "–"
        if isinstance(v, bool):
            return "yes" if v else "**no**"
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(fmt(r.get(c)) for c in columns) + " |" for r in rows]
    return "\n".join(lines)


def write_section(study: str, body: str, command: str | None = None) -> None:
    """Replace (or append) the generated section of ``study`` in docs/results.md."""
    begin, end = f"<!-- BEGIN study:{study} -->", f"<!-- END study:{study} -->"
    command = command or f"python experiments/studies.py {study}"
    block = f"{begin}\n<!-- generated by `{command}`; edits here are overwritten -->\n{body.strip()}\n{end}"
    text = "# jaxfric: measured results\n"
    if os.path.exists(RESULTS_MD):
        with open(RESULTS_MD) as fh:
            text = fh.read()
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        text = head + block + rest.split(end, 1)[1]
    else:
        if "## Studies of the benchmark specification" not in text:
            text = text.rstrip() + ("\n\n## Studies of the benchmark specification (issue 4)\n\nEach "
                                    "block below is written by `experiments/studies.py`.\n")
        text = text.rstrip() + "\n\n" + block + "\n"
    with open(RESULTS_MD, "w") as fh:
        fh.write(text)


def failures(rows: list[dict], missing=()) -> str:
    bad = [r for r in rows if not r.get("converged")]
    text = "All runs converged." if not bad else (
        "Runs that did not complete (partial results kept in their run directories):\n\n" + "\n".join(
            f"- `{r['case']}`: {r.get('message') or 'no message'}" for r in bad))
    if missing:
        text += "\n\n**Not run yet** (the study is incomplete): " + ", ".join(f"`{m}`" for m in missing) + "."
    return text


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _selected(opts, name: str) -> bool:
    """Whether case ``name`` is to be run (``--only``; none with ``--collect``)."""
    return not opts.collect and (not opts.only or any(s in name for s in opts.only))


def _committed_rows(study: str, opts) -> dict:
    """The rows of the study's committed ``table.csv`` by case name, with their types restored, for the
    cases that have no run directory (run directories are not committed): a study resumed on a fresh
    checkout keeps the cases an earlier invocation finished instead of running them again: the Nine
    sensitivity and mesh studies (their tables hold everything their sections and figures use) and the
    algorithm agreement (which keeps each case's curves beside its row). ``--rerun`` runs the selected cases
    again instead."""

    def value(text):
        if text in ("", "None"):
            return None
        if text in ("True", "False"):
            return text == "True"
        try:
            return int(text)
        except ValueError:
            pass
        try:
            return float(text)
        except ValueError:
            return text

    out = {}
    for row in _read_table(study):
        if opts.rerun and _selected(opts, row["case"]):
            continue
        if not _on_disk(study, row["case"]):
            out[row["case"]] = {k: value(v) for k, v in row.items()}
    return out


def _write_partial(study: str, rows: list[dict]) -> None:
    """The table between two cases: the rows so far, then the rows of the table on disk that the loop
    has not reached yet (committed, or read back from their run directories by an earlier process), so
    that a study stopped between cases loses no row."""
    seen = {r["case"] for r in rows}
    write_table(study, rows + [r for r in _read_table(study) if r["case"] not in seen])


def _on_disk(study: str, name: str) -> bool:
    """Whether case ``name`` of ``study`` has a finished run in ``runs/``."""
    return os.path.exists(os.path.join(ROOT, study, "runs", name, "summary.json"))


def _want(opts, study: str, name: str, optional: bool = False) -> bool:
    """Whether case ``name`` enters the table: selected, or not selected but already on disk (read back).
    Cases left out are listed in the section (``opts.missing``), unless ``optional``."""
    ok = _selected(opts, name) or _on_disk(study, name)
    if not ok and not optional:
        opts.missing.append(name)
    return ok


def _machine(rows_cases: list[dict]) -> str:
    devices = {c["summary"].get("device") for c in rows_cases if c["summary"].get("device")}
    return ", ".join(sorted(devices)) or "not in the table (rows kept from an earlier invocation)"


def _header(study: str, cases: list[dict], what: str) -> str:
    return (f"### Study `{study}`\n\n{what}\n\nRegenerate: `python experiments/studies.py {study}` "
            f"(add `--rerun` to recompute cases already on disk). Device: {_machine(cases)}. Table: "
            f"`experiments/results/studies/{study}/table.csv`; figure: "
            f"`experiments/results/studies/{study}/figure.png`.")


# ------------------------------------------------------------------------- (1) and (2) Nine cost
def penalty_sensitivity(opts) -> None:
    study = "penalty_sensitivity"
    rows, cases = [], []
    kept = _committed_rows(study, opts)
    for variant in ("mu000", "mu017"):
        for eps in EPS_PENALTY:
            name = f"{variant}_eps{eps:.0e}"
            if name in kept:
                rows.append(kept[name])
                continue
            if not _want(opts, study, name):
                continue
            c = case(study, name, "nine", variant, "penalty",
                     {"mesh": NINE_MESH, "eps_n": eps, **({"max_steps": MAX_STEPS[eps]} if eps in MAX_STEPS else {})},
                     opts)
            s = c["summary"]
            eps_t = (s.get("parameters") or {}).get("contact", {}).get("eps_t")
            rows.append({"case": name, "variant": variant, "eps_n": eps, "eps_t": eps_t, **common(s),
                         "message": s.get("message", "")})
            cases.append(c)
            _wall_rel(rows)
            _write_partial(study, rows)
    _wall_rel(rows)
    write_table(study, rows)
    cost_accuracy_figure()
    cols = ["variant", "eps_n", "eps_t", "n_steps", "cutbacks", "newton_iters_total", "wall_s", "wall_rel",
            "max_penetration", "steady_drawing_force", "converged"]
    write_section(study, _header(study, cases, "Nine test, `penalty`, mesh 300 x 3, eps_T = mu eps_N, "
                                 "the step controller of spec 1.9 for every run; the history buffer holds "
                                 "10x the nominal steps + 200 (8300), 30,000 for eps_N = 1e6 (with 8300 both "
                                 "variants stopped at U = 32 mm; `MAX_STEPS` in the script).") + "\n\n"
                  + markdown_table(rows, cols) + "\n\n" + failures(rows, opts.missing)
                  + "\n\n![cost against accuracy](../experiments/results/studies/penalty_sensitivity/figure.png)")


def _wall_rel(rows: list[dict]) -> None:
    ref = _reference_wall()
    for r in rows:
        r["wall_rel"] = _r(r["wall_s"] / ref) if ref and r.get("wall_s") else None


def _reference_wall():
    """wall_s of (mu000, eps_n = 1e2), the reference of studies (1) and (2), if it has run: from its run
    directory, else from the committed table of study (1) (run directories are not committed)."""
    path = os.path.join(ROOT, "penalty_sensitivity", "runs", "mu000_eps1e+02", "summary.json")
    if os.path.exists(path):
        with open(path) as fh:
            return json.load(fh).get("wall_s")
    row = next((r for r in _read_table("penalty_sensitivity") if r.get("case") == "mu000_eps1e+02"), None)
    return float(row["wall_s"]) if row and row.get("wall_s") else None


def auglag_sensitivity(opts) -> None:
    study = "auglag_sensitivity"
    rows, cases = [], []
    kept = _committed_rows(study, opts)
    for variant in ("mu000", "mu017"):
        for eps in EPS_AUGLAG:
            for gap in TARGET_GAPS:
                name = f"{variant}_eps{eps:.0e}_gap{gap:.0e}"
                if name in kept:
                    # Rows committed before the column existed ran with the spec's 20.
                    rows.append({**kept[name], "max_augmentations": kept[name].get("max_augmentations") or 20})
                    continue
                if not _want(opts, study, name):
                    continue
                n_aug = MAX_AUGMENTATIONS.get((eps, gap), 20)
                c = case(study, name, "nine", variant, "auglag",
                         {"mesh": NINE_MESH, "eps_n": eps, "target_gap": gap,
                          **({"max_augmentations": n_aug} if n_aug != 20 else {})}, opts)
                s = c["summary"]
                rows.append({"case": name, "variant": variant, "eps_n": eps, "target_gap": gap,
                             "max_augmentations": n_aug, **common(s),
                             "mean_augmentations": _r(s.get("mean_augmentations")),
                             "message": s.get("message", "")})
                cases.append(c)
                _wall_rel(rows)
                _write_partial(study, rows)
    _wall_rel(rows)
    write_table(study, rows)
    cost_accuracy_figure()
    cols = ["variant", "eps_n", "target_gap", "n_steps", "cutbacks", "newton_iters_total", "wall_s",
            "cpu_s", "wall_rel", "max_augmentations", "mean_augmentations", "max_penetration",
            "steady_drawing_force", "converged"]
    write_section(study, _header(study, cases, "Nine test, `auglag`, mesh 300 x 3, eps_T = mu eps_N; "
                                 "`wall_rel` is relative to the (mu000, eps_N = 1e2) penalty run of "
                                 "study (1). `max_augmentations` is the limit per step: the spec's 20, "
                                 "60 for eps_N = 1e4 with a 1e-6 mm target, whose steps need more than 20 "
                                 "on average (`mean_augmentations`), because each node entering contact "
                                 "starts from lambda_N = 0 (`MAX_AUGMENTATIONS` in the script).") + "\n\n"
                  + markdown_table(rows, cols) + "\n\n"
                  + failures(rows, opts.missing)
                  + "\n\n![cost against accuracy](../experiments/results/studies/auglag_sensitivity/figure.png)")


def _read_table(study: str) -> list[dict]:
    path = os.path.join(ROOT, study, "table.csv")
    if not os.path.exists(path):
        return []
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def cost_accuracy_figure() -> None:
    """wall_s against max_penetration, log-log: penalty curves per friction case, AL points labelled; one
    figure for both studies where they share their settings (both in AT_DEFAULTS or neither), else one
    figure per study with its own runs."""
    pen, al = _read_table("penalty_sensitivity"), _read_table("auglag_sensitivity")
    if ("penalty_sensitivity" in AT_DEFAULTS) == ("auglag_sensitivity" in AT_DEFAULTS):
        _cost_accuracy_figure(pen, al, ("penalty_sensitivity", "auglag_sensitivity"))
    else:
        _cost_accuracy_figure(pen, [], ("penalty_sensitivity",))
        _cost_accuracy_figure([], al, ("auglag_sensitivity",))


def _cost_accuracy_figure(pen: list[dict], al: list[dict], studies: tuple) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7.5, 5.5))
    colours = {"mu000": "tab:blue", "mu017": "tab:red"}
    for variant, colour in colours.items():
        pts = [(float(r["max_penetration"]), float(r["wall_s"]), float(r["eps_n"]), r["converged"] == "True")
               for r in pen if r["variant"] == variant and r["max_penetration"] and r["wall_s"]]
        if pts:
            pts.sort(key=lambda p: p[2])
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", color=colour,
                    label=f"penalty, {variant}")
            stopped = [p for p in pts if not p[3]]
            if stopped:  # a run that stopped early: its cost and penetration up to where it stopped
                ax.plot([p[0] for p in stopped], [p[1] for p in stopped], "x", ms=12, color="k",
                        label="stopped early (cost up to there)" if variant == "mu000" else None)
            pts = [p[:3] for p in pts]
            for x, y, e in pts:
                ax.annotate(f"{e:.0e}", (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7,
                            color=colour)
        pts = [(float(r["max_penetration"]), float(r["wall_s"]), float(r["eps_n"]), float(r["target_gap"]),
                r["converged"] == "True")
               for r in al if r["variant"] == variant and r["max_penetration"] and r["wall_s"]]
        if pts:
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "s", mfc="none", color=colour,
                    label=f"auglag, {variant}")
            stopped = [p for p in pts if not p[4]]
            if stopped:
                ax.plot([p[0] for p in stopped], [p[1] for p in stopped], "x", ms=12, color="k")
            for x, y, e, g, _ in pts:
                ax.annotate(f"({e:.0e}, {g:.0e})", (x, y), textcoords="offset points", xytext=(4, -9),
                            fontsize=6, color=colour)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("largest penetration over the run (mm)")
    ax.set_ylabel("solve wall time (s)")
    labels = [text for rows, text in ((pen, "penalty labelled by eps_N (N/mm/mm)"),
                                      (al, "auglag by (eps_N, target gap mm)")) if rows]
    ax.set_title("Nine test 300 x 3: cost against contact accuracy\n" + ", ".join(labels))
    ax.grid(True, which="both", alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    fig.tight_layout()
    for study in studies:
        if os.path.isdir(os.path.join(ROOT, study)):
            fig.savefig(os.path.join(ROOT, study, "figure.png"), dpi=130)
    plt.close(fig)


# --------------------------------------------------------------------------- (3) mesh convergence
def mesh_convergence(opts) -> None:
    study = "mesh_convergence"
    found, cases = {}, []
    kept = _committed_rows(study, opts)

    def add(nx, ny, name):
        c = case(study, name, "nine", "mu000", "penalty", {"mesh": name, "eps_n": 1e5}, opts)
        s = c["summary"]
        found[name] = {"case": name, "nx": nx, "ny": ny, "n_elements": nx * ny, **common(s),
                       "message": s.get("message", "")}
        cases.append(c)

    def in_order():
        return [found[f"{nx}x{ny}"] for nx, ny in MESHES if f"{nx}x{ny}" in found]

    # The cases finished earlier first (committed rows, run directories), so that the table written after
    # each case run compares every row with the finest mesh finished, not the finest reached so far.
    for nx, ny in MESHES:
        name = f"{nx}x{ny}"
        if name in kept:
            found[name] = kept[name]
        elif _on_disk(study, name) and not (opts.rerun and _selected(opts, name)):
            add(nx, ny, name)
    for nx, ny in MESHES:
        name = f"{nx}x{ny}"
        if name in found or not _want(opts, study, name):
            continue
        add(nx, ny, name)
        _write_partial(study, _with_rel_diff(in_order()))
    rows = _with_rel_diff(in_order())
    write_table(study, rows)
    plt = _plt()
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.5))
    for ny, marker in ((3, "o-"), (6, "s-")):
        sel = [r for r in rows if r["ny"] == ny and r["steady_drawing_force"] is not None]
        a.plot([r["nx"] for r in sel], [r["steady_drawing_force"] for r in sel], marker, label=f"{ny} through")
        sel = [r for r in rows if r["ny"] == ny and r["wall_s"]]
        b.plot([r["nx"] for r in sel], [r["wall_s"] for r in sel], marker, label=f"{ny} through")
    a.set_xscale("log")
    a.set_xlabel("elements along the strip nx")
    a.set_ylabel("mean steady drawing force (N/mm)")
    a.set_title("Nine mu000, penalty 1e5: steady drawing force")
    b.set_xscale("log")
    b.set_yscale("log")
    b.set_xlabel("elements along the strip nx")
    b.set_ylabel("solve wall time (s)")
    b.set_title("cost")
    for ax in (a, b):
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(os.path.join(ROOT, study, "figure.png"), dpi=130)
    plt.close(fig)
    cols = ["nx", "ny", "n_elements", "steady_drawing_force", "rel_diff_to_finest", "finest", "n_steps",
            "newton_iters_total", "wall_s", "converged"]
    write_section(study, _header(study, cases, "Nine test `mu000`, `penalty`, eps_N = 1e5, the scene's "
                                 "defaults (element `ans`, the entry guide's channel), the same "
                                 "nominal increments for every mesh. `rel_diff_to_finest` is against "
                                 "1200 x 6 (against the finest converged mesh, named, when 1200 x 6 is "
                                 "missing).") + "\n\n" + markdown_table(rows, cols) + "\n\n"
                  + failures(rows, opts.missing)
                  + "\n\n![mesh convergence](../experiments/results/studies/mesh_convergence/figure.png)")


def _with_rel_diff(rows: list[dict]) -> list[dict]:
    good = [r for r in rows if r["converged"] and r["steady_drawing_force"] is not None]
    if not good:
        return rows
    finest = max(good, key=lambda r: (r["n_elements"], r["ny"]))
    ref = finest["steady_drawing_force"]
    for r in rows:
        f = r["steady_drawing_force"]
        r["rel_diff_to_finest"] = None if f is None else _r(abs(f - ref) / abs(ref))
        r["finest"] = finest["case"]
    return rows


# -------------------------------------------------------------------------- (4) blankholder shapes
def blankholder_shapes(opts) -> None:
    study = "blankholder_shapes"
    from jaxfric.scenes import blankholder

    rows, cases = [], []
    for variant in blankholder.VARIANTS:
        if not _want(opts, study, variant):
            continue
        c = case(study, variant, "blankholder", variant, "penalty", {}, opts)
        s, h = c["summary"], c["history"]
        geo = blankholder.VARIANTS[variant]
        close = h["phase"] == "close" if h else np.zeros(0, bool)
        eqps = c["contact"].get("final__eqps")
        rows.append({"case": variant, "shape": int(variant.removeprefix("shape")),
                     **{k: geo.get(k) for k in ("H", "R", "r", "Rp", "L")},
                     "steady_drawing_force": _r(s.get("steady_drawing_force")),
                     "peak_drawing_force": _r(s.get("peak_drawing_force")),
                     "clamping_force_end_close": _r(float(h["clamping_force"][close][-1])) if close.any() else None,
                     "final_clamping_force": _r(s.get("final_clamping_force")),
                     "max_eqps": _r(float(np.max(eqps))) if eqps is not None else None,
                     **{k: v for k, v in common(s).items() if k not in ("steady_drawing_force",)},
                     "message": s.get("message", "")})
        cases.append(c)
        write_table(study, rows)
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(17, 4.8))
    for c, r in zip(cases, rows):
        h = c["history"]
        if not h:
            continue
        draw, close = h["phase"] == "draw", h["phase"] == "close"
        axes[0].plot(h["drawing_displacement"][draw], h["drawing_force"][draw], label=r["case"])
        axes[1].plot(h["tool_position"][close], h["clamping_force"][close], label=r["case"])
    good = [r for r in rows if r["steady_drawing_force"] is not None]
    axes[2].bar([str(r["shape"]) for r in good], [r["steady_drawing_force"] for r in good],
                color=["tab:blue" if r["converged"] else "tab:gray" for r in good])
    axes[0].set(xlabel="drawing displacement U (mm)", ylabel="drawing force (N/mm)",
                title="drawing force, nine shapes")
    axes[1].set(xlabel="closing stroke s (mm)", ylabel="clamping force (N/mm)",
                title="clamping force during 'close'")
    axes[2].set(xlabel="shape", ylabel="steady drawing force (N/mm)", title="steady drawing force")
    for ax in axes[:2]:
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(os.path.join(ROOT, study, "figure.png"), dpi=130)
    plt.close(fig)
    cols = ["shape", "H", "R", "r", "Rp", "L", "steady_drawing_force", "peak_drawing_force",
            "clamping_force_end_close", "final_clamping_force", "max_eqps", "n_steps", "wall_s", "converged"]
    write_section(study, _header(study, cases, "The nine blankholder shapes of Table 7, `penalty`, spec "
                                 "mesh and parameters.") + "\n\n" + markdown_table(rows, cols) + "\n\n"
                  + failures(rows, opts.missing)
                  + "\n\n![blankholder shapes](../experiments/results/studies/blankholder_shapes/figure.png)")


# -------------------------------------------------------------------------- (5) algorithm agreement
def _variants():
    for name in ("flat_die", "bead", "nine", "blankholder"):
        for variant in scenes.variants(name):
            yield name, variant


def _curve_diff(h, ref, x_name, y_name, phase):
    a, b = phase_curve(h, x_name, y_name, phase), phase_curve(ref, x_name, y_name, phase)
    if a is None or b is None:
        return None
    lo, hi = max(a[0][0], b[0][0]), min(a[0][-1], b[0][-1])
    if not hi > lo:
        return None
    grid = np.linspace(lo, hi, GRID)
    fa, fb = np.interp(grid, *a), np.interp(grid, *b)
    scale = np.max(np.abs(fb))
    return _r(float(np.max(np.abs(fa - fb)) / scale)) if scale > 0 else None


def _status_mismatch(contact, ref):
    worst = None
    for name in set(contact.get("instant_names", [])) & set(ref.get("instant_names", [])):
        a, b = contact[f"{name}__status"], ref[f"{name}__status"]
        if a.shape == b.shape and a.size:
            worst = max(worst or 0.0, float(np.mean(a != b)))
    return None if worst is None else _r(worst)


def _shared_run(name: str, variant: str, algorithm: str):
    """A case another study already ran with the same inputs, read back from its directory: the
    blankholder's penalty runs are the ``blankholder_shapes`` cases (penalty), where both studies run at
    the same settings and the run on disk was made at them (a stale one is left to its own study).
    ``--rerun`` does not reach them here: rerun them with ``studies.py blankholder_shapes --rerun``."""
    settings = study_settings(name, "blankholder_shapes")
    if name != "blankholder" or algorithm != "penalty" or settings != study_settings(name, "algorithm_agreement"):
        return None
    directory = os.path.join(ROOT, "blankholder_shapes", "runs", variant)
    path = os.path.join(directory, "summary.json")
    if not os.path.exists(path) or stale(path, settings, variant, algorithm) is not None:
        return None
    return run_case(directory, name, variant, algorithm, settings, rerun=False, progress=False, figures=False,
                    tag="blankholder_shapes", log=lambda m: None, rerun_stale=False)


CURVE_COLUMNS = ("phase", "drawing_displacement", "drawing_force", "clamping_force", "theta_deg")


def _curves_path(study: str, name: str) -> str:
    return os.path.join(ROOT, study, "curves", f"{name}.npz")


def _save_curves(study: str, name: str, c: dict, columns=CURVE_COLUMNS) -> None:
    """Keep (committed) what the agreement table and figure read from a run: the history columns of
    ``columns`` and the contact status at the named instants. A later invocation then compares a new
    case with this one without running it again (run directories are not committed)."""
    h, contact = c["history"], c["contact"]
    path, summary = _curves_path(study, name), os.path.join(c["dir"], "summary.json")
    if not h or (os.path.exists(path) and os.path.getmtime(path) >= os.path.getmtime(summary)):
        return  # rewritten only after a new run (a zip archive differs at every write)
    arrays = {k: np.asarray(h[k]) for k in columns if k in h}
    names = [str(n) for n in contact.get("instant_names", [])]
    arrays["instant_names"] = np.array(names, dtype=str)
    arrays.update({f"{n}__status": contact[f"{n}__status"] for n in names if f"{n}__status" in contact})
    os.makedirs(os.path.dirname(path), exist_ok=True)
    np.savez_compressed(path, **arrays)


def _case_from_curves(study: str, name: str, row: dict, columns=CURVE_COLUMNS) -> dict:
    """A case of an earlier invocation from its committed table row and curves (the shape :func:`case`
    returns)."""
    with np.load(_curves_path(study, name), allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    summary = {k: row.get(k) for k in ("converged", "message", "n_steps", "newton_iters_total", "wall_s",
                                        "cpu_s", "compile_s", "max_penetration", "steady_drawing_force",
                                        "device")}
    summary["n_cutbacks"] = row.get("cutbacks")
    summary["cutback_causes"] = row.get("cut_causes")
    history = {k: arrays[k] for k in columns if k in arrays}
    contact = {k: v for k, v in arrays.items() if k not in columns}
    return {"summary": summary, "history": history, "contact": contact, "dir": None, "row": row}


def _steady_difference(c: dict, ref: dict, signed: bool = True, reference: str | None = None):
    """Case ``c``'s steady drawing force relative to ``ref``'s (signed, or its magnitude), as a table keeps it.
    Where both were read back from committed rows, whose steady forces keep 6 digits, and ``c``'s row was
    compared with the same ``reference`` (the ``reference`` column; none in ``common_steps``), the difference
    the invocation that ran them computed from the runs' own values stands."""
    row = c.get("row")
    if row is not None and ref.get("row") is not None and row.get("reference") == reference:
        return row.get("rel_diff_steady")
    fs, fr = c["summary"].get("steady_drawing_force"), ref["summary"].get("steady_drawing_force")
    if fs is None or not fr:
        return None
    return _r((fs - fr) / abs(fr) if signed else abs(fs - fr) / abs(fr))


def _finished(runs: dict, algorithm: str) -> bool:
    """Whether ``runs`` holds a converged run of ``algorithm``."""
    return bool(runs.get(algorithm, {}).get("summary", {}).get("converged"))


def algorithm_agreement(opts) -> None:
    """Each case comes from its run directory, else from its committed row and curves (a case of an
    earlier invocation at the study's settings), else it is run if selected. Rows of earlier invocations
    that have no curves (before curves were kept) or were run at other settings (column ``settings``,
    :func:`settings_label`) stay as they were committed until their case runs again, with the reference
    they were compared with (column ``reference``); a group's comparisons are among cases at the study's
    settings only."""
    study = "algorithm_agreement"
    settings = settings_label(study)
    kept = _committed_rows(study, opts)
    rows, panels, cases = [], [], []
    for name, variant in _variants():
        runs, legacy = {}, {}

        def take(algorithm, label, run_algorithm, overrides, run=True, optional=False):
            """Put case ``label`` into ``runs`` or ``legacy``; with ``run`` False, never run it (``optional``:
            not listed as missing where it is not run)."""
            on_disk = _on_disk(study, label)
            shared = _shared_run(name, variant, algorithm)
            same = label in kept and row_settings(kept[label]) == settings
            if shared is not None:
                runs[algorithm] = shared
            elif same and os.path.exists(_curves_path(study, label)):
                runs[algorithm] = _case_from_curves(study, label, kept[label])
            elif label in kept and not (run and _selected(opts, label)):
                legacy[algorithm] = kept[label]
            elif on_disk and not run:
                runs[algorithm] = run_case(os.path.join(ROOT, study, "runs", label), name, variant,
                                           run_algorithm, {**study_settings(name, study), **overrides},
                                           log=lambda m: None, rerun_stale=False)
            elif run and _want(opts, study, label, optional):
                runs[algorithm] = case(study, label, name, variant, run_algorithm, overrides, opts)
            if runs.get(algorithm, {}).get("dir"):
                _save_curves(study, label, runs[algorithm])

        for algorithm in ALGORITHMS:
            take(algorithm, f"{name}_{variant}_{algorithm}", algorithm, _full_steps(algorithm))
        ref_alg = "lcp_lemke" if _finished(runs, "lcp_lemke") else None
        # The AL reference runs only where Lemke has not converged (in this invocation or an earlier one,
        # whose row without curves still shows the group has its exact reference); one that ran before
        # stays a row.
        lemke_done = ref_alg is not None or bool(legacy.get("lcp_lemke", {}).get("converged")
                                                 and row_settings(legacy["lcp_lemke"]) == settings)
        # Needed only where Lemke ran at these settings and did not converge: not missing before that.
        take("auglag_gap1e-06", f"{name}_{variant}_auglag_gap1e-06", "auglag", {"target_gap": 1e-6},
             run=not lemke_done, optional="lcp_lemke" not in runs)
        if ref_alg is None and _finished(runs, "auglag_gap1e-06"):
            ref_alg = "auglag_gap1e-06"
        elif ref_alg is None and "auglag_gap1e-06" in runs and _finished(runs, "lcp_ssn"):
            # Neither Lemke nor the AL reference finished (blankholder shape4 at the defaults: Lemke's full
            # steps crawl early in the pull, the AL stops at its start): the semismooth Newton solution,
            # which is Lemke's on common steps
            # (test_semismooth_newton_equals_lemke_on_a_common_step_sequence, study common_steps).
            ref_alg = "lcp_ssn"
        if not runs and not legacy:
            continue
        ref = runs.get(ref_alg)
        for algorithm in [*ALGORITHMS, "auglag_gap1e-06"]:
            if algorithm in legacy:  # its differences are from its own `reference`, at its own settings
                row = {**legacy[algorithm], "settings": row_settings(legacy[algorithm])}
                if algorithm == "auglag_gap1e-06" and row["settings"] != settings and ref_alg == "lcp_lemke":
                    # The AL reference of other settings, which Lemke's convergence at these makes unneeded.
                    path = _curves_path(study, row["case"])
                    if os.path.exists(path):
                        os.remove(path)
                    continue
                rows.append(row)
                continue
            if algorithm not in runs:
                continue
            c = runs[algorithm]
            s, h = c["summary"], c["history"]
            row = {"case": f"{name}_{variant}_{algorithm}", "scene": name, "variant": variant,
                   "algorithm": algorithm, "settings": settings, "reference": ref_alg, **common(s)}
            if ref is not None and h:
                row["rel_diff_steady"] = _steady_difference(c, ref, signed=False, reference=ref_alg)
                row["curve_diff_drawing"] = _curve_diff(h, ref["history"], "drawing_displacement",
                                                        "drawing_force", "draw")
                row["curve_diff_clamping"] = _curve_diff(h, ref["history"], "drawing_displacement",
                                                         "clamping_force", "draw")
                if name == "bead":
                    row["curve_diff_wind"] = _curve_diff(h, ref["history"], "theta_deg", "drawing_force", "wind")
                row["max_status_mismatch"] = _status_mismatch(c["contact"], ref["contact"])
            row["device"] = s.get("device")
            row["message"] = s.get("message", "")
            rows.append(row)
            cases.append(c)
        if runs:
            panels.append((name, variant, runs))
        _write_partial(study, rows)
    write_table(study, rows)
    _agreement_figure(panels)
    cols = ["scene", "variant", "algorithm", "settings", "reference", "converged", "n_steps", "newton_iters_total",
            "wall_s", "cpu_s", "max_penetration", "steady_drawing_force", "rel_diff_steady",
            "curve_diff_drawing", "curve_diff_clamping", "max_status_mismatch"]
    drawn = ", ".join(f"{n} / {v}" for n, v, _ in panels) or "none"
    behind = collections.Counter(f"{r['scene']} {r['variant']}" for r in rows if r.get("settings") != settings)
    write_section(study, _header(study, cases,
                                 "Every scene variant with every algorithm at default parameters, at the "
                                 "settings in column `settings`: `defaults`, the scenes' defaults (the "
                                 "element `ans` on the Nine and the bead, `anst` with 4 points per layer on "
                                 "the blankholder, the Nine's entry channel), or `study`, the settings the "
                                 "study ran at before (F-bar, the Nine's left-end nodes held, 2 points per "
                                 "layer on the blankholder; `STUDY_SETTINGS` in the script). Cases are "
                                 "compared only with the reference at their own settings; this invocation "
                                 f"runs `{settings}`. The "
                                 "reference (column `reference`) is `lcp_lemke`, or `auglag` with target "
                                 "gap 1e-6 where Lemke did not converge or has not run, or `lcp_ssn` where "
                                 "that did not converge either. The blankholder's "
                                 "penalty rows are the runs of study `blankholder_shapes` where both studies "
                                 "run at the same settings and those runs are on disk. Curves compared on 200 points "
                                 "over the common `draw` range (and `theta_deg` over `wind` for the bead). "
                                 "Each case keeps its curves in `curves/<case>.npz` (committed), so a later "
                                 "invocation adds cases without rerunning the others; rows finished before "
                                 "curves were kept have none, are not in the figure and keep the "
                                 "reference they were compared with.")
                  + "\n\n" + markdown_table(rows, cols) + "\n\n" + failures(rows, opts.missing)
                  + (f"\n\n**Not yet run at `{settings}`** ({sum(behind.values())} of {len(rows)} rows, kept "
                     f"from the study's earlier settings until their cases run again; rows per group): "
                     + ", ".join(f"{g} ({n})" for g, n in behind.items()) + "." if behind else "")
                  + f"\n\nFigure panels (groups with curves at `{settings}`): {drawn}."
                  + ("\n\n![algorithm agreement](../experiments/results/studies/algorithm_agreement/figure.png)"
                     if panels else ""))


def _agreement_figure(panels, study: str = "algorithm_agreement") -> None:
    """The study's figure of ``panels``; none (an older one removed) where there is nothing to draw."""
    if not panels:
        if os.path.exists(os.path.join(ROOT, study, "figure.png")):
            os.remove(os.path.join(ROOT, study, "figure.png"))
        return
    plt = _plt()
    n = len(panels)
    ncol = min(4, n)
    nrow = math.ceil(n / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.3 * nrow), squeeze=False)
    styles = {"penalty": "-", "auglag": "--", "lcp_lemke": ":", "lcp_ssn": "-.", "auglag_gap1e-06": "--",
              SEARCHED: ":"}
    for ax, (name, variant, runs) in zip(axes.flat, panels):
        for algorithm, c in runs.items():
            h = c["history"]
            if not h:
                continue
            draw = h["phase"] == "draw"
            ok = c["summary"].get("converged")
            ax.plot(h["drawing_displacement"][draw], h["drawing_force"][draw], styles.get(algorithm, "-"),
                    lw=1.2, label=algorithm + ("" if ok else " (stopped)"))
        ax.set_title(f"{name} / {variant}", fontsize=9)
        ax.set_xlabel("drawing displacement (mm)", fontsize=8)
        ax.set_ylabel("drawing force (N/mm)", fontsize=8)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=6)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(os.path.join(ROOT, study, "figure.png"), dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------- (5b) every algorithm, one step sequence
COMMON_REPLAYS = ("lcp_lemke", "penalty", "auglag")
# The common steps' ``lcp_lemke`` rows take full Newton steps (``lemke_search`` False); ``lcp_lemke_search``, with
# the line search (the scenes' default), runs where they left the plan's steps.
SEARCHED = "lcp_lemke_search"
COMMON_COLUMNS = (*CURVE_COLUMNS, "time", "n_active", "n_slip", "cutbacks", "ssn_iters")


def union_steps(histories) -> np.ndarray:
    """The end times of every step that any of ``histories`` accepted (their ``time`` after row 0),
    increasing, times within 1e-9 of each other taken as one."""
    t = np.unique(np.concatenate([np.asarray(h["time"][1:], float) for h in histories]))
    return t[np.concatenate([[True], np.diff(t) > 1e-9])] if t.size else t


def _common_row(name: str, variant: str, algorithm: str, c: dict, plan: dict, steps: str = "plan") -> dict:
    """One row of ``common_steps``: the run ``c`` against the plan (``lcp_ssn`` on the same steps) at the
    plan's step ends. ``steps``: ``plan`` (the semismooth Newton run's own steps) or ``union``."""
    s, h, p = c["summary"], c["history"], plan["history"]
    suffix = "" if steps == "plan" else f"_{steps}"
    row = {"case": f"{name}_{variant}_{algorithm}{suffix}", "scene": name, "variant": variant,
           "algorithm": algorithm, "steps": steps, **common(s)}
    if row["n_steps"] is not None and plan["summary"].get("n_steps") is not None:
        row["extra_steps"] = int(row["n_steps"]) - int(plan["summary"]["n_steps"])
    if algorithm != "lcp_ssn" and h and p:
        row["rel_diff_steady"] = _steady_difference(c, plan)
        # The rows of this run that end where the plan's steps end (all of them, unless it stopped).
        ip, k = matching_rows(p["time"], h["time"])
        scale = float(np.max(np.abs(p["drawing_force"])) + np.max(np.abs(p["clamping_force"])))
        row["force_diff"] = _r(max(float(np.max(np.abs(h[col][k] - p[col][ip])))
                                   for col in ("drawing_force", "clamping_force")) / scale)
        differ = (h["n_active"][k] != p["n_active"][ip]) | (h["n_slip"][k] != p["n_slip"][ip])
        row["status_differ"] = _r(float(np.mean(differ)))
        row["common_rows"] = int(ip.size)
    if algorithm in ("lcp_lemke", SEARCHED) and "ssn_iters" in h:
        row["refined_steps"] = int(np.sum(h["ssn_iters"] > 0))
    row["cut_causes"] = cause_cell(s.get("cutback_causes"))
    row["device"] = s.get("device")
    row["message"] = s.get("message", "")
    return row


def cause_cell(counts) -> str | None:
    """A table's ``cut_causes``: summary.json's ``cutback_causes`` as "name:steps ..." ("" for none); a
    committed row's text as it is; None where the run did not record them."""
    if counts is None or isinstance(counts, str):
        return counts
    return " ".join(f"{name}:{n}" for name, n in counts.items())


def common_steps(opts) -> None:
    """Every algorithm on one step sequence: each scene variant with its defaults runs with ``lcp_ssn``
    (the plan), then ``lcp_lemke``, ``penalty`` and ``auglag`` replay the plan's accepted steps as their
    nominal increments (:func:`jaxfric.io.batch.replay_steps`; their controllers still cut a step that
    fails). The differences from the plan at its step ends are then those of the algorithms, not of their
    step sequences. Where some cut steps of the plan, ``--union`` runs a second pass: every algorithm,
    ``lcp_ssn`` included, on the union of the steps the first pass accepted (cases ``..._union``). Cases
    are kept as in ``algorithm_agreement`` (committed rows and ``curves/``)."""
    study = "common_steps"
    kept = _committed_rows(study, opts)
    rows, panels, cases = [], [], []
    for name, variant in _variants():
        got: dict = {}

        def take(key, algorithm, label, steps=None, overrides=None, optional=False):
            """Case ``label`` into ``got[key]``: read back, or run where wanted (``optional``: not listed as
            missing where it is not)."""
            if label in kept and os.path.exists(_curves_path(study, label)):
                got[key] = _case_from_curves(study, label, kept[label], COMMON_COLUMNS)
            elif _want(opts, study, label, optional):
                got[key] = case(study, label, name, variant, algorithm, overrides or {}, opts, steps=steps)
                cases.append(got[key])
                if got[key]["dir"]:
                    _save_curves(study, label, got[key], COMMON_COLUMNS)

        group = f"{name}_{variant}"
        take("lcp_ssn", "lcp_ssn", f"{group}_lcp_ssn")
        plan = got.get("lcp_ssn")
        if plan is None:
            continue
        first = ("lcp_ssn", *COMMON_REPLAYS)
        if plan["summary"].get("converged") and plan["history"]:
            for algorithm in COMMON_REPLAYS:
                take(algorithm, algorithm, f"{group}_{algorithm}", np.asarray(plan["history"]["time"][1:]),
                     _full_steps(algorithm))
            lemke = got.get("lcp_lemke")
            if lemke is None or lemke["summary"].get("n_steps") != plan["summary"].get("n_steps"):
                # Lemke's full Newton steps left the plan: line-searched as lcp_ssn's (the scenes' default); where
                # they were not run (they crawl on the blankholder's long lands), only if asked for or on disk.
                take(SEARCHED, "lcp_lemke", f"{group}_{SEARCHED}", np.asarray(plan["history"]["time"][1:]),
                     {"lemke_search": True}, optional=lemke is None)
        rows += [_common_row(name, variant, a, got[a], plan) for a in (*first, SEARCHED) if a in got]
        done = [got[a] for a in first if a in got and got[a]["summary"].get("converged") and got[a]["history"]]
        if opts.union and len(done) == len(first) and any(c["summary"].get("n_steps") != plan["summary"].get("n_steps")
                                                          for c in done):
            steps = union_steps([c["history"] for c in done])
            for algorithm in first:
                take(f"{algorithm}_union", algorithm, f"{group}_{algorithm}_union", steps, _full_steps(algorithm))
            plan_u = got.get("lcp_ssn_union")
            if plan_u is not None:
                rows += [_common_row(name, variant, a, got[f"{a}_union"], plan_u, "union") for a in first
                         if f"{a}_union" in got]
        panels.append((name, variant, {k: v for k, v in got.items() if not k.endswith("_union")}))
        _write_partial(study, rows)
    write_table(study, rows)
    _agreement_figure(panels, study)
    cols = ["scene", "variant", "algorithm", "steps", "converged", "n_steps", "extra_steps", "newton_iters_total",
            "wall_s", "max_penetration", "steady_drawing_force", "rel_diff_steady", "force_diff",
            "status_differ", "refined_steps", "cut_causes"]
    write_section(study, _header(study, cases,
                                 "Every algorithm on one step sequence, each scene variant with its "
                                 "defaults: `lcp_ssn` plans the steps (its own controller), then "
                                 "`lcp_lemke` (full Newton steps: `lemke_search=false`), `penalty` "
                                 "(eps_N = 1e5) and `auglag` (target gap 1e-5 mm) "
                                 "take the plan's accepted steps as their nominal increments; a step that "
                                 "fails is still cut (`extra_steps`: steps beyond the plan's). Against the "
                                 "plan at its step ends: `rel_diff_steady` (signed), `force_diff` (largest "
                                 "difference of the drawing and clamping forces over the plan's drawing "
                                 "plus clamping force scale), `status_differ` (fraction of the step ends "
                                 "where the numbers of closed or slipping pairs differ); `refined_steps`: "
                                 "Lemke steps whose answer needed the semismooth polish; `cut_causes`: "
                                 "the steps cut per result code of their failed attempts (history.csv's "
                                 "`cut_codes`; blank where a run's summary has none); `contact_band` "
                                 "there is an attempt that ended with a closing pair outside Lemke's "
                                 "proximity band, after which the run widened the band (its `message` "
                                 "in the table's CSV). Where "
                                 "Lemke left the plan's steps, `lcp_lemke_search` replays them again with "
                                 "Lemke's Newton steps line-searched as `lcp_ssn`'s (the scenes' default "
                                 "`lemke_search`); on blankholder shapes 2, 4 and 7 only that row was run: "
                                 "there Lemke's full Newton steps crawl from the draw's start (shape4: "
                                 "124 to 131 Newton iterations a step after two failed attempts, about 95 s "
                                 "a step; `--only blankholder_shape4_lcp_lemke`, stopped). Rows with `steps` = "
                                 "`union` (`--union`, where the first pass cut the plan's steps): every "
                                 "algorithm, `lcp_ssn` included, on the union of the steps the first pass "
                                 "accepted, against `lcp_ssn` on those steps.")
                  + "\n\n" + markdown_table(rows, cols) + "\n\n" + failures(rows, opts.missing)
                  + "\n\n![common steps](../experiments/results/studies/common_steps/figure.png)")


STUDIES = {f.__name__: f for f in (penalty_sensitivity, auglag_sensitivity, mesh_convergence,
                                   blankholder_shapes, algorithm_agreement, common_steps)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("study", choices=[*STUDIES, "all"])
    p.add_argument("--only", action="append", default=[],
                   help="run only cases whose name contains TEXT (repeatable); cases already on disk "
                        "are read back into the table")
    p.add_argument("--rerun", action="store_true", help="recompute cases already on disk")
    p.add_argument("--no-run-figures", dest="run_figures", action="store_false",
                   help="skip the three per-run PNGs (the study figures are always drawn)")
    p.add_argument("--quiet", dest="progress", action="store_false", help="no progress bars")
    p.add_argument("--union", action="store_true",
                   help="common_steps: replay every algorithm on the union of the steps its first pass accepted "
                        "where some algorithm cut the plan's steps")
    p.add_argument("--collect", action="store_true",
                   help="run nothing: rewrite the table, figures and section from the runs on disk")
    opts = p.parse_args(argv)
    opts.missing = []
    for name in (STUDIES if opts.study == "all" else [opts.study]):
        opts.missing = []
        os.makedirs(os.path.join(ROOT, name), exist_ok=True)
        STUDIES[name](opts)
    return 0


if __name__ == "__main__":
    sys.exit(main())
