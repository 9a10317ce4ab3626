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
Where along each tool: at the ``steady`` and ``final`` instants (U = 27.5 and 36 mm) each tool's closed
pairs are split into its entry end, its middle and its exit end (:func:`split_by_patch`, ends of
:data:`END_ARC` of centre-line arc; ``nine_tool_forces_parts.csv``), and the strip's centre line gives
the length over which its curvature turns from one wrap's to the next one's (:func:`reversals`, between
0.9 of the wraps' curvature of either sign; ``nine_tool_forces_reversals.csv``);
``nine_tool_forces_profile.png`` draws the curvature and the normal force summed along the strip.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from benchutil import run_or_read, write_rows
from jaxfric import scenes
from jaxfric.contact.exact_iterate import tangents
from jaxfric.io.batch import read_history

HERE = os.path.dirname(os.path.abspath(__file__))
BASE = {"U_draw": 36.0, "dq_clamp": 0.05, "dU": 0.05}
INSTANTS = ("steady", "final")   # the contact snapshots split into parts (U = 27.5 and 36 mm)
END_ARC = 1.5   # mm of centre-line arc that make a tool's entry and exit ends (split_by_patch)
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
    s = run_or_read(out, lambda: scenes.make("nine", variant, "lcp_ssn", {**BASE, "mesh": mesh}), "nine_tool_forces",
                    f"{name}: running")
    window = s["steady_window"]
    if not s["converged"] or window is None:
        raise SystemExit(f"{name}: the run in {out} did not finish ({s['message']})")
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


def strip_columns(x0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The strip's node columns from its reference coordinates ``x0`` (n, 2): each node's column (ranked by
    its reference x), and per column the node of the bottom face and of the top face."""
    xs = np.unique(np.round(x0[:, 0], 9))
    column = np.searchsorted(xs, np.round(x0[:, 0], 9))
    bottom = np.flatnonzero(x0[:, 1] <= x0[:, 1].min() + 1e-9)
    top = np.flatnonzero(x0[:, 1] >= x0[:, 1].max() - 1e-9)
    by_column = np.full((2, xs.size), -1)
    by_column[0, column[bottom]], by_column[1, column[top]] = bottom, top
    return column, by_column[0], by_column[1]


def centreline(x: np.ndarray, bottom: np.ndarray, top: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arc length s (mm, from the first column) of the deformed centre line (the faces' mean) at each column,
    and its curvature (1/mm, positive turning counter-clockwise; the turn of the adjacent chords over
    their mean length, NaN at the two end columns)."""
    c = 0.5 * (x[bottom] + x[top])
    chord = np.diff(c, axis=0)
    length = np.linalg.norm(chord, axis=1)
    angle = np.unwrap(np.arctan2(chord[:, 1], chord[:, 0]))
    kappa = np.full(c.shape[0], np.nan)
    kappa[1:-1] = np.diff(angle) / (0.5 * (length[1:] + length[:-1]))
    return np.concatenate([[0.0], np.cumsum(length)]), kappa


def reversals(s: np.ndarray, kappa: np.ndarray, level: float) -> list[dict]:
    """Where the centre line's curvature turns from one wrap's to the next one's: each passage from
    kappa <= -level to kappa >= level (or back) between columns, its arc length from the last crossing of
    the one level to the first of the other (linear between columns), and the arc position of its middle."""
    out, last = [], None   # last: (sign, s where kappa left the level of that sign)
    for i in range(1, s.size - 1):
        k0, k1 = kappa[i], kappa[i + 1]
        if np.isnan(k1):
            break
        for sign in (-1.0, 1.0):
            if sign * k0 >= level > sign * k1:        # leaves the level of this sign
                last = (sign, s[i] + (s[i + 1] - s[i]) * (sign * k0 - level) / (sign * k0 - sign * k1))
            if sign * k0 < level <= sign * k1 and last is not None and last[0] == -sign:   # reaches the other
                reached = s[i] + (s[i + 1] - s[i]) * (level - sign * k0) / (sign * k1 - sign * k0)
                out.append({"to": "+" if sign > 0 else "-", "s_mid": 0.5 * (last[1] + reached),
                            "length": reached - last[1]})
                last = None
    return out


def snapshot_strip(path: str, instant: str):
    """A run's contact snapshot ``path`` (the loaded npz), its tool names, each node's column and, at
    ``instant``, the centre line's arc length and curvature per column (:func:`centreline`)."""
    z = np.load(path)
    column, bottom, top = strip_columns(z["x0"])
    s, kappa = centreline(z[f"{instant}__x"], bottom, top)
    return z, [str(n) for n in z["tool_names"]], column, s, kappa


def split_by_patch(path: str, instant: str = "steady", tools=("A", "B", "C"), end_arc: float = END_ARC) -> list[dict]:
    """Each tool's closed pairs at ``instant`` split along the strip: the ``entry`` and ``exit`` ends (the
    closed nodes within ``end_arc`` mm of centre-line arc of the first and of the last closed node in the
    strip's direction of travel, +x) and the ``middle``; per part its closed pairs, the sum of R_N, the x
    components of R_N n and of R_T t (N/mm), and its arc extent from the tool's first closed node (mm)."""
    z, names, column, s, _ = snapshot_strip(path, instant)
    rows = []
    for tool in tools:
        on = (z["pair_tool"] == names.index(tool)) & (z[f"{instant}__rn"] > 0)
        if not on.any():
            continue
        rn, rt, n = z[f"{instant}__rn"][on], z[f"{instant}__rt"][on], z[f"{instant}__normal"][on]
        at = s[column[z["pair_node"][on]]]
        at = at - at.min()
        part = np.where(at <= end_arc, "entry", np.where(at >= at.max() - end_arc, "exit", "middle"))
        friction_x = rt * np.asarray(tangents(n))[:, 0]
        for name in ("entry", "middle", "exit"):
            k = part == name
            if k.any():
                rows.append({"tool": tool, "part": name, "closed_pairs": int(k.sum()),
                             "normal_force": float(rn[k].sum()), "normal_x": float((rn * n[:, 0])[k].sum()),
                             "friction_x": float(friction_x[k].sum()), "arc_from": float(at[k].min()),
                             "arc_to": float(at[k].max())})
    return rows


def level(root: str, name: str) -> float:
    """The curvature a reversal is measured between: 0.9 of the centre line's on a wrap of A, B or C,
    1 / (R1 + t / 2), from the run's ``summary.json``."""
    with open(os.path.join(root, name, "summary.json")) as fh:
        geometry = json.load(fh)["parameters"]["geometry"]
    return 0.9 / (geometry["R1"] + 0.5 * geometry["t"])


def normal_force_profile(path: str, instant: str, tools=("A", "B", "C")) -> tuple[np.ndarray, np.ndarray]:
    """The closed pairs of ``tools`` at ``instant``, ordered along the strip: their centre-line arc position
    (mm) and R_N (N/mm)."""
    z, names, column, s, _ = snapshot_strip(path, instant)
    on = np.isin(z["pair_tool"], [names.index(t) for t in tools]) & (z[f"{instant}__rn"] > 0)
    at, rn = s[column[z["pair_node"][on]]], z[f"{instant}__rn"][on]
    order = np.argsort(at, kind="stable")
    return at[order], rn[order]


def profile_figure(root: str, names, path: str, instant: str = "steady") -> None:
    """Per variant, the centre line's curvature (top) and the normal force of A, B and C summed along the
    strip (bottom: its steps are the concentrated reactions) at ``instant``, each mesh one colour, the arc
    measured from the middle of the reversal between A and B."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    variants = sorted({CASES[n][0] for n in names})
    fig, axes = plt.subplots(2, len(variants), figsize=(6.5 * len(variants), 6.5), sharex=True,
                             squeeze=False, constrained_layout=True)
    for j, variant in enumerate(variants):
        for colour, mesh in zip(("tab:red", "tab:blue"), MESHES):
            name = f"{variant}_{mesh}"
            if name not in names:
                continue
            contact = os.path.join(root, name, "contact.npz")
            _, _, _, s, kappa = snapshot_strip(contact, instant)
            turns = reversals(s, kappa, level(root, name))
            origin = turns[0]["s_mid"] if turns else 0.0
            axes[0, j].plot(s - origin, kappa, ".-", ms=3, lw=0.8, color=colour, label=mesh)
            at, rn = normal_force_profile(contact, instant)
            axes[1, j].step(at - origin, np.cumsum(rn), where="post", lw=1.0, color=colour, label=mesh)
        axes[0, j].set_title(f"{variant}, {instant} instant")
        axes[0, j].set_ylabel("centre-line curvature (1/mm)")
        axes[1, j].set_ylabel("A, B, C: R_N summed along (N/mm)")
        axes[1, j].set_xlabel("arc along the strip from the reversal between A and B (mm)")
        axes[0, j].legend()
        axes[0, j].set_xlim(-8.0, 26.0)
        for ax in axes[:, j]:
            ax.grid(alpha=0.3)
    fig.savefig(path, dpi=110)
    plt.close(fig)


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
    parts, turns = [], []
    for n in names:
        path = os.path.join(a.root, n, "contact.npz")
        for instant in INSTANTS:
            parts += [{"case": n, "instant": instant, **r} for r in split_by_patch(path, instant)]
            _, _, _, s, kappa = snapshot_strip(path, instant)
            turns += [{"case": n, "instant": instant, **r} for r in reversals(s, kappa, level(a.root, n))]
    for r in parts:
        print(f"{r['case']:<12} {r['instant']:<7} {r['tool']} {r['part']:<6} {r['closed_pairs']:3d} closed, "
              f"R_N {r['normal_force']:7.2f}, x of R_N n {r['normal_x']:+7.2f}, x of R_T t {r['friction_x']:+7.2f}")
    for r in turns:
        print(f"{r['case']:<12} {r['instant']:<7} curvature reversal to {r['to']} at s = {r['s_mid']:6.2f} mm "
              f"over {r['length']:.3f} mm")
    if not a.only:
        write_rows(os.path.join(HERE, "results", "nine_tool_forces.csv"), rows)
        write_rows(os.path.join(HERE, "results", "nine_tool_forces_instant.csv"), split)
        write_rows(os.path.join(HERE, "results", "nine_tool_forces_parts.csv"), parts)
        write_rows(os.path.join(HERE, "results", "nine_tool_forces_reversals.csv"), turns)
        profile_figure(a.root, names, os.path.join(HERE, "results", "nine_tool_forces_profile.png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
