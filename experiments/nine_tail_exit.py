"""The Nine test's strip tail leaving the entry guide and passing the bead: ``python experiments/nine_tail_exit.py``.

    python experiments/nine_tail_exit.py [--root DIR] [--mesh NXxNY] [--only CASE ...] [--table]

Each case is the full Nine run (U_draw 70 mm, nominal increments) of one variant with one algorithm at
``--mesh`` (default the spec's 300 x 3), a run directory under ``--root`` (default
``runs/nine_tail_exit/<mesh>``, kept: a second call reads it back): the default entry guide (the channel)
with the four algorithms, and for comparison ``lcp_ssn`` with ``entry_guide_kind=end_nodes`` (v = 0 held
on the left-end nodes). Per case, from ``history.csv`` and the final instant of ``contact.npz``:

- the steady drawing and clamping forces (window U in [20, 35] mm) and the largest of each after the
  window, as a multiple of the steady value (the issue's goal: no drawing force above 1.3 times);
- U at which the tail leaves the guide (``tail_x`` passes ``guide_end``), reaches A's top (x = 0) and
  passes B's centre (x = L1), and U at which the drawing force first falls below half its steady value;
- the largest equivalent plastic strain at the steady instant and at the end (plastic strain never
  decreases, so the end's maximum is the run's).

The table goes to ``experiments/results/nine_tail_exit_<mesh>.csv`` and to stdout, the forces against U
(all cases) and the guide's forces at the tail's exit to ``experiments/results/nine_tail_exit_<mesh>.png``;
``--only`` runs some cases (to spread them over processes), ``--table`` only reads back what is on disk.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys

import numpy as np

from benchutil import run_or_read, write_rows
from jaxfric import scenes

HERE = os.path.dirname(os.path.abspath(__file__))
ALGORITHMS = ("penalty", "auglag", "lcp_lemke", "lcp_ssn")
VARIANTS = ("mu000", "mu017")
END_NODES = "_end_nodes"  # case-name suffix: entry_guide_kind=end_nodes
CASES = tuple(f"{v}_{a}" for v in VARIANTS for a in ALGORITHMS) + tuple(f"{v}_lcp_ssn{END_NODES}" for v in VARIANTS)


def _crossing(u: np.ndarray, values: np.ndarray, level: float) -> float | None:
    """First U at which ``values`` reaches ``level`` from below (None if it never does)."""
    hit = np.flatnonzero(values >= level)
    return float(u[hit[0]]) if hit.size else None


def _history(out: str) -> dict:
    """The draw rows of a run's history, as arrays."""
    with open(os.path.join(out, "history.csv")) as fh:
        rows = [r for r in csv.DictReader(fh) if r["phase"] == "draw"]
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0] if k not in ("phase", "phase_name")}


def run_one(name: str, mesh: str, root: str) -> tuple[dict, dict]:
    """The table row of case ``name`` (run it first if not on disk) and its draw history."""
    variant, algorithm = name.removesuffix(END_NODES).split("_", 1)
    kind = "end_nodes" if name.endswith(END_NODES) else "channel"
    out = os.path.join(root, name)
    s = run_or_read(out, lambda: scenes.make("nine", variant, algorithm, {"mesh": mesh, "entry_guide_kind": kind}),
                    "nine_tail_exit", f"{name}: running on {mesh}", figures=True)
    col = _history(out)
    u, force, clamp, tail = (col[k] for k in ("drawing_displacement", "drawing_force", "clamping_force",
                                              "tail_x"))
    lo, hi = s["steady_window"]
    window, after = (u >= lo) & (u <= hi), u > hi
    f_steady, c_steady = float(np.mean(force[window])), float(np.mean(clamp[window]))
    geometry = s["parameters"]["geometry"]
    guide = geometry.get("entry_guide")
    contact = np.load(os.path.join(out, "contact.npz"))
    eqps = {n: float(np.max(contact[f"{n}__eqps"])) for n in ("steady", "final")}
    drop = np.flatnonzero(after & (force < 0.5 * f_steady))
    return {"case": name, "variant": variant, "algorithm": algorithm, "entry_guide_kind": kind, "mesh": mesh,
            "converged": s.get("converged"), "steady_drawing_force": f_steady,
            "max_drawing_after_window": float(np.max(force[after])) / f_steady,
            "U_at_max_drawing": float(u[after][np.argmax(force[after])]),
            "steady_clamping_force": c_steady,
            "max_clamping_after_window": float(np.max(clamp[after])) / c_steady,
            "U_tail_leaves_guide": _crossing(u, tail, guide["x"][1]) if guide else None,
            "U_tail_at_A": _crossing(u, tail, 0.0),
            "U_tail_at_B": _crossing(u, tail, geometry["L1"]),
            "U_force_below_half": float(u[drop[0]]) if drop.size else None,
            "eqps_max_steady": eqps["steady"], "eqps_max_final": eqps["final"],
            "final_drawing_force": float(force[-1]),
            "n_steps": s.get("n_steps"), "newton_iters_total": s.get("newton_iters_total"),
            "wall_s": s.get("wall_s")}, col


def figure(rows: list[dict], histories: dict, path: str) -> None:
    """Drawing force over its steady value against U, per variant and case; the guide faces' and A's
    vertical forces around the tail's exit (lcp_ssn)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(13, 8), constrained_layout=True)
    for j, variant in enumerate(VARIANTS):
        ax = axes[0, j]
        for r in (r for r in rows if r["variant"] == variant):
            h = histories[r["case"]]
            style = {"ls": "--", "color": "k", "lw": 1.0} if r["entry_guide_kind"] == "end_nodes" else {"lw": 1.0}
            ax.plot(h["drawing_displacement"], h["drawing_force"] / r["steady_drawing_force"],
                    label=f"{r['algorithm']} ({r['entry_guide_kind']})", **style)
        ax.axhline(1.3, color="r", lw=0.8, ls=":", label="1.3 x steady")
        ax.axvspan(20.0, 35.0, color="0.9", zorder=0)
        ax.set(title=f"{variant}: drawing force / steady force", xlabel="drawing displacement U (mm)",
               ylim=(0.0, 4.5))
        ax.legend(fontsize=8)
        ax = axes[1, j]
        r = next((r for r in rows if r["case"] == f"{variant}_lcp_ssn"), None)
        if r is None:
            continue
        h = histories[r["case"]]
        for key, label in (("guide_top_fy", "guide top face"), ("guide_bottom_fy", "guide bottom face"),
                           ("cyl_a_fy", "shoulder A"), ("drawing_force", "drawing force")):
            ax.plot(h["drawing_displacement"], h[key], lw=1.0, label=label)
        for key, label in (("U_tail_leaves_guide", "tail leaves the guide"), ("U_tail_at_A", "tail at A's top"),
                           ("U_tail_at_B", "tail at B's centre")):
            if r[key] is not None:
                ax.axvline(r[key], color="0.5", lw=0.8, ls="--")
                ax.text(r[key], ax.get_ylim()[1], label, rotation=90, va="top", ha="right", fontsize=8)
        ax.set(title=f"{variant}, lcp_ssn: vertical forces on the strip (N/mm)", xlabel="drawing displacement U (mm)",
               xlim=(30.0, 70.0))
        ax.legend(fontsize=8, loc="center left")
    fig.savefig(path, dpi=110)
    print(f"written {path}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mesh", default="300x3")
    p.add_argument("--root", default=None, help="default runs/nine_tail_exit/<mesh>")
    p.add_argument("--only", nargs="*", choices=CASES, help="run these cases only")
    p.add_argument("--table", action="store_true", help="read back the cases on disk, run none")
    a = p.parse_args(argv)
    root = a.root or os.path.join("runs", "nine_tail_exit", a.mesh)
    names = a.only or list(CASES)
    if a.table:
        names = [n for n in CASES if os.path.exists(os.path.join(root, n, "summary.json"))]
    runs = {n: run_one(n, a.mesh, root) for n in names}
    rows = [row for row, _ in runs.values()]
    for r in rows:
        print(f"{r['case']:<18} steady {r['steady_drawing_force']:.2f} N/mm, after the window at most "
              f"{r['max_drawing_after_window']:.2f}x (clamping {r['max_clamping_after_window']:.2f}x); tail "
              f"leaves the guide at U = {r['U_tail_leaves_guide']}, at A {r['U_tail_at_A']}; force below half "
              f"at {r['U_force_below_half']}; eqps max {r['eqps_max_steady']:.3f} steady, "
              f"{r['eqps_max_final']:.3f} final; converged {r['converged']}")
    if not a.only:
        write_rows(os.path.join(HERE, "results", f"nine_tail_exit_{a.mesh}.csv"), rows)
        histories = {n: h for n, (_, h) in runs.items()}
        figure(rows, histories, os.path.join(HERE, "results", f"nine_tail_exit_{a.mesh}.png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
