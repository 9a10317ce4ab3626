"""Which tool's force carries the Nine test's mesh error: ``python experiments/nine_tool_forces.py``.

    python experiments/nine_tool_forces.py [--root DIR] [--only CASE ...]

The steady drawing force of the Nine is the sum of the x components of the tools' forces on the strip:
A's, B's and C's (:data:`COLUMNS`), and the frictionless guide rollers' and entry channel's, which push
about along y and whose x components (not recorded) make up the last 0.1 N/mm.
Refining the mesh along the strip from 300 x 3 to 600 x 3 moves the steady force by -1.0 % without
friction and by -2.8 % with it (docs/results.md, the entry channel's ladder); this splits that change into
the tools' own changes. Each case is the scene's default (``ans``, the entry channel, exact contact),
U_draw 36 mm at half the nominal increments, as the reference ladder of docs/results.md (``jaxfric run nine
--variant V --mesh M --set U_draw=36 --set dq_clamp=0.05 --set dU=0.05``); it is a run directory under
``--root`` (default ``runs/nine_tool_forces``, kept: a second call reads it back, and a run directory of
that command may be put there). Each history column of :data:`COLUMNS` is averaged over the run's steady
window (``summary.json``: U in [20, 35] mm unless the run shortened it); the table goes to
``experiments/results/nine_tool_forces.csv``, one row per case and one per variant with the change from
the coarser mesh to the finer. At the scene's ``steady`` instant (its contact snapshot, ``contact.npz``)
each of A's, B's and C's x components is split into its normal forces' and its friction forces' share
(``experiments/results/nine_tool_forces_instant.csv``): one instant, so the closed nodes entering and
leaving the arcs make these shares less steady than the window's means.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

import jaxfric as jf
from benchutil import write_rows
from jaxfric import scenes
from jaxfric.contact.exact_iterate import tangents
from jaxfric.io import output
from jaxfric.io.batch import read_history

HERE = os.path.dirname(os.path.abspath(__file__))
BASE = {"U_draw": 36.0, "dq_clamp": 0.05, "dU": 0.05}
MESHES = ("300x3", "600x3")
CASES = {f"{variant}_{mesh}": (variant, mesh) for variant in ("mu000", "mu017") for mesh in MESHES}
# The steady drawing force, B's clamping force, and each tool's resultant on the strip (N/mm).
COLUMNS = ("drawing_force", "clamping_force", "cyl_a_fx", "cyl_a_fy", "bead_fx", "cyl_c_fx", "cyl_c_fy",
           "cyl_d_fy", "cyl_e_fy", "guide_top_fy", "guide_bottom_fy")


def steady_means(history: dict, window) -> dict:
    """Each of :data:`COLUMNS` averaged over the rows whose drawing displacement lies in ``window`` (mm)."""
    u = np.asarray(history["drawing_displacement"], dtype=float)
    keep = (u >= window[0]) & (u <= window[1])
    if not keep.any():
        raise ValueError(f"no history row with the drawing displacement in {window} mm")
    return {c: float(np.mean(np.asarray(history[c], dtype=float)[keep])) for c in COLUMNS}


def run_one(name: str, root: str) -> dict:
    variant, mesh = CASES[name]
    out = os.path.join(root, name)
    if not os.path.exists(os.path.join(out, "summary.json")):
        scene = scenes.make("nine", variant, "lcp_ssn", {**BASE, "mesh": mesh})
        print(f"{name}: running", file=sys.stderr, flush=True)
        result = jf.run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                        snapshot=scene.snapshot, progress=False)
        output.write_run(scene, result, out, tag="nine_tool_forces", figures=False)
    with open(os.path.join(out, "summary.json")) as fh:
        window = json.load(fh)["steady_window"]
    return {"case": name, "variant": variant, "mesh": mesh,
            **steady_means(read_history(os.path.join(out, "history.csv")), window)}


def split_at_instant(path: str, instant: str = "steady", tools=("A", "B", "C")) -> list[dict]:
    """Per tool, at ``instant`` of a run's contact snapshot ``path``: its closed pairs, the sum of their normal
    forces R_N, the resultant of R_N n (its components, and its tilt from the vertical towards +x in
    degrees), and the x component of R_T t (the library's tangent t of n: the pair force on the sheet is
    R_N n + R_T t), N/mm."""
    z = np.load(path)
    names = [str(n) for n in z["tool_names"]]
    rows = []
    for tool in tools:
        on = z["pair_tool"] == names.index(tool)
        rn, rt, n = z[f"{instant}__rn"][on], z[f"{instant}__rt"][on], z[f"{instant}__normal"][on]
        closed = rn > 0
        t = np.asarray(tangents(n))
        normal = (rn[:, None] * n)[closed].sum(axis=0)
        rows.append({"tool": tool, "closed_pairs": int(closed.sum()), "normal_force": float(rn[closed].sum()),
                     "normal_x": float(normal[0]), "normal_y": float(normal[1]),
                     "normal_tilt_deg": float(np.degrees(np.arctan2(normal[0], abs(normal[1])))),
                     "friction_x": float((rt[:, None] * t)[closed, 0].sum())})
    return rows


def changes(rows: list[dict]) -> list[dict]:
    """Per variant, each column's change from the first mesh of :data:`MESHES` to the second (N/mm)."""
    by = {(r["variant"], r["mesh"]): r for r in rows}
    out = []
    for variant in sorted({r["variant"] for r in rows}):
        if all((variant, m) in by for m in MESHES):
            coarse, fine = by[(variant, MESHES[0])], by[(variant, MESHES[1])]
            out.append({"case": f"{variant}_change", "variant": variant, "mesh": f"{MESHES[0]} -> {MESHES[1]}",
                        **{c: fine[c] - coarse[c] for c in COLUMNS}})
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--root", default=os.path.join("runs", "nine_tool_forces"))
    p.add_argument("--only", nargs="*", choices=sorted(CASES), help="run these cases only")
    a = p.parse_args(argv)
    names = a.only or list(CASES)
    rows = [run_one(n, a.root) for n in names]
    rows += changes(rows)
    for r in rows:
        print(f"{r['case']:<16} " + " ".join(f"{c} {r[c]:+.3f}" for c in COLUMNS))
    split = [{"case": n, **r} for n in names for r in split_at_instant(os.path.join(a.root, n, "contact.npz"))]
    for r in split:
        print(f"{r['case']:<16} {r['tool']}: {r['closed_pairs']:3d} closed, R_N {r['normal_force']:8.2f}, "
              f"R_N n ({r['normal_x']:+8.2f}, {r['normal_y']:+8.2f}), tilt {r['normal_tilt_deg']:+6.2f} deg, "
              f"x of R_T t {r['friction_x']:+8.2f}")
    if not a.only:
        write_rows(os.path.join(HERE, "results", "nine_tool_forces.csv"), rows)
        write_rows(os.path.join(HERE, "results", "nine_tool_forces_instant.csv"), split)
    return 0


if __name__ == "__main__":
    sys.exit(main())
