"""Record and compare run histories, to show that a restructuring leaves every run unchanged.

Every scene variant with every algorithm runs at a coarse mesh (the meshes of ``tests/test_scenes.py``)
over a shortened stroke, plus the ``make run`` case (Nine ``mu017``, spec mesh, ``lcp_ssn``, whole
stroke). ``record`` writes each run's history columns to ``DIR/<case>.npz`` (``--set``: a config field
given to every case, e.g. ``preselect=false`` to compare a setting that should not change the results);
``compare`` reads two such
folders and writes, per case, the largest difference of every column scaled by the column's largest
magnitude, and whether the runs took the same steps.

    python experiments/refactor_equivalence.py list        # the case names
    python experiments/refactor_equivalence.py record runs/equivalence/before [CASE] [--set KEY=VALUE ...]
    python experiments/refactor_equivalence.py compare runs/equivalence/before runs/equivalence/after \\
        experiments/results/refactor_equivalence.csv
"""

from __future__ import annotations

import csv
import os
import sys

import numpy as np

import jaxfric
from jaxfric.io.batch import matching_rows
from jaxfric.scenes import ALGORITHMS, make, scene_names, variants

# Coarse meshes and short strokes: the clamping phase and the start of the draw (where contact opens,
# sticks and slides) run whole; the steady draw adds nothing to an equivalence check.
SHORT = {"flat_die": {"mesh": "24x2", "U_draw": 0.3},
         "bead": {"mesh": "50x2", "s_draw": 3.0},
         "nine": {"mesh": "30x2", "U_draw": 3.0},
         "blankholder": {"nx": 40, "U_pull": 3.0}}
MAKE_RUN = ("nine", "mu017", "lcp_ssn", {})


def cases(with_make_run: bool = True):
    """(case name, scene, variant, algorithm, overrides) of every run compared."""
    out = [(f"{s}_{v}_{a}", s, v, a, SHORT[s]) for s in scene_names() for v in variants(s) for a in ALGORITHMS]
    if with_make_run:
        s, v, a, o = MAKE_RUN
        out.append(("make_run", s, v, a, o))
    return out


def record(folder: str, only: str | None = None, extra: dict | None = None) -> None:
    """Run every case (or the one named ``only``, or else those whose name contains it), with the config
    fields ``extra`` (field -> text) on top of its own, and write its history to ``folder``."""
    os.makedirs(folder, exist_ok=True)
    chosen = cases()
    if only is not None:
        exact = [c for c in chosen if c[0] == only]
        chosen = exact or [c for c in chosen if only in c[0]]
    for name, scene_name, variant, algorithm, overrides in chosen:
        scene = make(scene_name, variant, algorithm, {**overrides, **(extra or {})})
        result = jaxfric.run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                             progress=False, raise_on_failure=False)
        columns = {k: np.asarray(v) for k, v in result.history.items()
                   if k != "wall_s" and np.asarray(v).dtype.kind in "biuf"}
        np.savez(os.path.join(folder, f"{name}.npz"), converged=result.converged, code=int(result.code),
                 **columns)
        print(f"{name}: {len(result.history['time'])} rows, converged {result.converged}, "
              f"compile {result.compile_s:.1f} s, solve {result.wall_s:.1f} s", flush=True)


FORCES = ("drawing_force", "clamping_force")


def force_difference(a: dict, b: dict) -> float:
    """Largest difference of the drawing and clamping forces, each over its largest magnitude in ``a``, at
    the step ends both runs share (:func:`jaxfric.io.batch.matching_rows`): runs that round-off sends onto
    different step sequences are still compared where they meet."""
    ia, ib = matching_rows(a["time"], b["time"])
    return max(float(np.max(np.abs(a[k][ia] - b[k][ib]), initial=0.0)) / max(float(np.max(np.abs(a[k]))), 1e-300)
               for k in FORCES)


def compare_case(a: dict, b: dict) -> dict:
    """Largest scaled difference over the columns both runs have, and whether their steps agree; the
    forces' difference where their steps meet (:func:`force_difference`), both runs' Newton iterations
    and, for exact contact, their semismooth active-set passes (``ssn_iters``; blank for the others)."""
    same_steps = a["time"].shape == b["time"].shape and bool(np.array_equal(a["time"], b["time"]))
    extra = {"force_diff": force_difference(a, b), "newton_iters_before": int(np.sum(a["newton_iters"])),
             "newton_iters_after": int(np.sum(b["newton_iters"])),
             **{f"passes_{when}": int(np.sum(r["ssn_iters"])) if "ssn_iters" in r else ""
                for when, r in (("before", a), ("after", b))}}
    worst, column = 0.0, ""
    for key in sorted(set(a) & set(b)):
        x, y = np.asarray(a[key], float), np.asarray(b[key], float)
        if x.shape != y.shape:
            return {"same_steps": False, "max_scaled_diff": np.inf, "column": key, **extra}
        scale = max(np.max(np.abs(x), initial=0.0), np.max(np.abs(y), initial=0.0), 1e-300)
        diff = float(np.max(np.abs(x - y), initial=0.0)) / scale
        if diff > worst:
            worst, column = diff, key
    return {"same_steps": same_steps, "max_scaled_diff": worst, "column": column, **extra}


def compare(before: str, after: str, out_csv: str | None = None) -> list:
    """One row per case recorded in both folders; a case missing from one is reported as such."""
    rows = []
    for name, *_ in cases():
        paths = [os.path.join(d, f"{name}.npz") for d in (before, after)]
        if not all(os.path.exists(p) for p in paths):
            rows.append({"case": name, "same_steps": "", "max_scaled_diff": "", "column": "missing"})
            continue
        a, b = (dict(np.load(p)) for p in paths)
        rows.append({"case": name, "rows": len(a["time"]), **compare_case(a, b)})
    if out_csv is not None:
        os.makedirs(os.path.dirname(out_csv) or ".", exist_ok=True)
        with open(out_csv, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=["case", "rows", "same_steps", "max_scaled_diff", "column",
                                                   "force_diff", "newton_iters_before", "newton_iters_after",
                                                   "passes_before", "passes_after"])
            writer.writeheader()
            writer.writerows(rows)
    return rows


if __name__ == "__main__":
    if len(sys.argv) >= 3 and sys.argv[1] == "record":
        words = sys.argv[3:]
        sets = [words[i + 1] for i, w in enumerate(words) if w == "--set" and i + 1 < len(words)]
        names = [w for i, w in enumerate(words) if w != "--set" and (i == 0 or words[i - 1] != "--set")]
        record(sys.argv[2], names[0] if names else None, dict(text.split("=", 1) for text in sets))
    elif len(sys.argv) == 2 and sys.argv[1] == "list":
        print("\n".join(c[0] for c in cases()))
    elif len(sys.argv) >= 4 and sys.argv[1] == "compare":
        for row in compare(sys.argv[2], sys.argv[3], sys.argv[4] if len(sys.argv) > 4 else None):
            print(row)
    else:
        sys.exit(__doc__)
