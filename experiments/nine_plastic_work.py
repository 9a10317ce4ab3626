"""Where along the Nine test the plastic work is done: ``python experiments/nine_plastic_work.py``.

    python experiments/nine_plastic_work.py [--cases CASE ...] [--U-draw U] [--x-left X] [--out DIR]

Without friction the steady drawing force is the work dissipated per unit length of strip drawn. With
J2 plasticity and isotropic hardening sigma_Y(e) = sigma_y (1 + A e)^n the dissipation per unit reference
volume at a point is w(e) = int_0^e sigma_Y de = sigma_y ((1 + A e)^(n+1) - 1) / (A (n + 1)), a function of
its equivalent plastic strain alone. Summed over a column of elements with the element's quadrature, it
gives the work W per unit reference length that the column has received. At the end of a run W against
the column's position X in the undeformed strip is a staircase: flat strip, bent onto A, reverse-bent
from A onto B, from B onto C, straightened off C (D and E only bend it elastically), for every column
that came from the flat strip before A (the strip is lengthened, ``--x-left``, so that its tail stays
before A). Each step is that stage's share of the work; the last level W_end with the strip's stretch
after the tools (ds/dX - 1) gives the force by the energy balance, F = W_end / (1 + stretch), to the
elastic energy left in the strip. Comparing meshes stage by stage locates where the layers through
the thickness, the element or its quadrature change the force, and whether through the work or the
stretch.

Cases ``[VARIANT_]ELEMENT_NXxNY[_pK]``: ``anst_300x12``; ``anst_300x3_p4`` with 4 Gauss points through
each element's thickness (``thickness_points``); ``mu017_anst_300x12`` with friction, whose force is the
plastic work and the friction's (F (1 + stretch) - W_end per unit length). NX is the spec's element
count per 100 mm. ``mu000`` unless named, exact
contact (``lcp_ssn``), the left-end nodes held (``entry_guide_kind=end_nodes``, as the reference ladder),
nominal increments. Writes ``experiments/results/nine_plastic_work.csv`` (per case: the levels, W_end,
the stretch, the force by the balance, the run's steady force and the work it did beyond the plastic
work, F (1 + stretch) - W_end: the friction's with mu017) and ``nine_plastic_work.png`` (W against X;
``_mu017`` in their names when every case has friction); each case's profile and facts stay in
``--out`` (default ``runs/nine_plastic_work``), so a second call reads them back and runs only the
missing cases.
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
from jaxfric.fem.assembly import mesh_geometry
from jaxfric.scenes.nine import NineConfig

HERE = os.path.dirname(os.path.abspath(__file__))
SPEC = NineConfig()   # the spec's strip: its right end, and its length for the element length


def column_work(model, state) -> tuple[np.ndarray, np.ndarray]:
    """(current mid-line point of each column's centre (nx, 2), plastic work per unit reference length
    of each column, N mm/mm)."""
    mesh, mat = model.mesh, model.material
    eqps = np.asarray(state.material.eqps)
    sy, A, n = float(mat.sigma_y), float(mat.A), float(mat.n)
    if A * n == 0.0:
        w = sy * eqps
    else:
        w = sy * ((1.0 + A * eqps) ** (n + 1.0) - 1.0) / (A * (n + 1.0))
    area = np.asarray(mesh_geometry(mesh, model.thickness_points).weight)   # reference area per point
    X = np.asarray(mesh.nodes)
    dx = np.diff(X[mesh.node_index(np.arange(mesh.nx + 1), 0), 0])
    W = (w * area).reshape(mesh.nx, -1).sum(axis=1) / dx
    mid = (X + np.asarray(state.u)).reshape(mesh.nx + 1, mesh.ny + 1, 2).mean(axis=1)
    return 0.5 * (mid[1:] + mid[:-1]), W


def plateaus(X: np.ndarray, W: np.ndarray, span: float = 1.0, min_length: float = 2.0) -> list:
    """The levels of the staircase W(X) in order along the strip: the medians of the runs of columns
    (at least ``min_length`` mm long) over which W moves by less than 2 % of its largest value within
    ``span`` mm either side, up to the highest level (beyond it lies material that was already in the
    tools when the run began)."""
    dX = X[1] - X[0]
    k = max(1, int(round(span / dX)))
    flat = np.zeros(len(W), bool)
    flat[k:-k] = np.abs(W[2 * k:] - W[:-2 * k]) < 0.02 * W.max()
    levels, start = [], None
    for i, f in enumerate(np.append(flat, False)):
        if f and start is None:
            start = i
        elif not f and start is not None:
            if (i - start) * dX >= min_length and W[start:i].mean() > 0.05 * W.max():
                levels.append((float(X[start]), float(X[i - 1]), float(np.median(W[start:i]))))
            start = None
    top = int(np.argmax([v for *_, v in levels]))
    return levels[:top + 1]


def reference_x(row: dict, n: int) -> np.ndarray:
    """The position X in the undeformed strip of each of the ``n`` columns of a case's row (mm)."""
    return row["x_left"] + (np.arange(n) + 0.5) * (SPEC.x_right - row["x_left"]) / n


def analyse(row: dict, s: np.ndarray, W: np.ndarray) -> dict:
    """The work received tool by tool (the plateaus of W along the reference X, in order: onto A, from
    A to B, from B to C, off C and the rest), the strip's stretch after the tools (ds/dX - 1 over the
    last plateau) and the force the energy balance gives, W_end / (1 + stretch)."""
    X = reference_x(row, len(W))
    dX = X[1] - X[0]
    levels = plateaus(X, W)
    out = {f"W_level_{k + 1}": v for k, (_, _, v) in enumerate(levels)}
    lo, hi, last = levels[-1]
    inside = (X[:-1] >= lo) & (X[:-1] < hi)
    stretch = float(np.mean(np.diff(s)[inside] / dX) - 1.0)
    out.update(W_end=last, stretch_end=stretch, force_from_work=last / (1.0 + stretch))
    if "steady_drawing_force" in row:   # the work the force did that the plastic work does not account for
        out["other_work"] = row["steady_drawing_force"] * (1.0 + stretch) - last
    return out


def run_case(case: str, U_draw: float, x_left: float, out: str) -> tuple[dict, np.ndarray, np.ndarray]:
    """Run ``case`` (or read it back from ``out``): its run's facts and its profile: the arc length s
    along the strip's current mid-line of every column (mm) and the work W it received (N mm/mm)."""
    profile, summary = os.path.join(out, f"{case}.csv"), os.path.join(out, f"{case}.json")
    if os.path.exists(summary):
        with open(summary) as fh:
            row = json.load(fh)
        x, W = np.loadtxt(profile, delimiter=",", skiprows=1).T
        return row, x, W
    parts = case.split("_")
    variant = parts.pop(0) if parts[0] in ("mu000", "mu017") else "mu000"
    element, mesh, *points = parts
    nx, ny = (int(v) for v in mesh.split("x"))
    nx = round(nx * (SPEC.x_right - x_left) / (SPEC.x_right - SPEC.x_left))   # the spec's element length
    overrides = {"nx": nx, "ny": ny, "x_left": x_left, "element": element, "U_draw": U_draw,
                 "entry_guide_kind": "end_nodes", "thickness_points": int(points[0][1:]) if points else 2}
    scene = scenes.make("nine", variant, "lcp_ssn", overrides)
    print(f"{case}: running {overrides}", file=sys.stderr, flush=True)
    result = jf.run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                    progress=False, raise_on_failure=False)
    mid, W = column_work(scene.model, result.final)
    x = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(mid, axis=0), axis=1))])
    np.savetxt(profile, np.stack([x, W], 1), delimiter=",", header="s_mm,W_Nmm_per_mm", comments="")
    h = result.history
    U, F = np.asarray(h["drawing_displacement"]), np.asarray(h["drawing_force"])
    lo, hi = scene.config.steady_window
    steady = float(np.mean(F[(U >= lo) & (U <= hi)]))
    row = {"case": case, "variant": variant, "element": element, "mesh": f"{nx}x{ny}",
           "thickness_points": overrides["thickness_points"],
           "x_left": x_left, "U_draw": U_draw, "converged": result.converged, "steady_drawing_force": steady,
           "newton_iters_total": int(np.sum(h["newton_iters"])), "wall_s": result.wall_s}
    with open(summary, "w") as fh:
        json.dump(row, fh)
    return row, x, W


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", nargs="+", default=["ans_300x3", "ans_300x3_p4", "ans_300x12", "anst_300x3",
                                                  "anst_300x3_p4", "anst_300x3_p8", "anst_300x12"])
    p.add_argument("--U-draw", type=float, default=56.0)
    p.add_argument("--x-left", type=float, default=-80.0,
                   help="the strip's left end (spec -50): long enough that the tail stays before A to U_draw")
    p.add_argument("--out", default=os.path.join("runs", "nine_plastic_work"))
    a = p.parse_args(argv)
    os.makedirs(a.out, exist_ok=True)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = []
    fig, ax = plt.subplots(figsize=(9, 4.5))
    for case in a.cases:
        row, x, W = run_case(case, a.U_draw, a.x_left, a.out)
        row = {k: v for k, v in row.items() if not k.startswith(("W_after", "s_after"))}
        row.update(analyse(row, x, W))
        rows.append(row)
        print(", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()))
        X = reference_x(row, len(W))
        keep = X < row["x_left"] + a.U_draw + 10.0
        ax.plot(X[keep], W[keep], label=f"{case}: steady {row['steady_drawing_force']:.2f} N/mm, "
                f"W_end {row['W_end']:.2f}, stretch {100 * row['stretch_end']:.2f} %")
    ax.set_xlabel("the column's position in the undeformed strip X (mm)")
    ax.set_ylabel("plastic work received W (N mm/mm)")
    variants = sorted({row["variant"] if "variant" in row else "mu000" for row in rows})
    ax.set_title(f"Nine {', '.join(variants)}, lcp_ssn, end of the run (U = {a.U_draw:g} mm): work per unit length, "
                 "steps: onto A, A to B, B to C, off C", fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    keys = list(dict.fromkeys(k for row in rows for k in row))   # cases run before a column was added lack it
    rows = [{k: row.get(k, "") for k in keys} for row in rows]
    stem = "nine_plastic_work" + ("" if variants == ["mu000"] else "_" + "_".join(variants))
    fig.savefig(os.path.join(HERE, "results", f"{stem}.png"), dpi=120)
    write_rows(os.path.join(HERE, "results", f"{stem}.csv"), rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
