"""The three figures of a run directory (outputs spec section 5): ``forces.png``, ``contact.png`` and
``mesh.png``.

They are drawn from the data as written (history columns, ``summary.json``, ``contact.npz`` arrays)
plus the tool outlines, so they can be redrawn from a run directory. Units: mm, N/mm, s. Display
exaggeration of y (``y_scale``) multiplies y coordinates only; contact-force arrows keep their true
direction and a length proportional to |f| (one scale for all panels).
"""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import matplotlib.ticker
import numpy as np
from matplotlib.collections import PolyCollection
from matplotlib.lines import Line2D

__all__ = ["forces_figure", "contact_figure", "mesh_figure", "contact_forces"]

_DPI = 100
_STICK, _SLIP = "tab:blue", "tab:red"


def _title(title: str, y_scale: float) -> str:
    return title if y_scale == 1.0 else f"{title}  (display: y exaggerated x{y_scale:g})"


def _save(fig, path: str) -> None:
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)


def forces_figure(path: str, title: str, scene_name: str, values: dict, summary: dict,
                  n_phases: int) -> None:
    """``forces.png``: (a) drawing and clamping force (N/mm) against drawing displacement (mm) on the
    ``draw`` rows, steady window shaded, steady drawing force as a horizontal line; (b) the same
    against pseudo-time (s) over all rows, phase boundaries dashed. ``flat_die`` adds ``sum_ft`` and
    ``mu_sum_fn``."""
    phase = np.asarray(values["phase"]).astype(str)
    time = np.asarray(values["time"], dtype=np.float64)
    u = np.asarray(values["drawing_displacement"], dtype=np.float64)
    curves = [("drawing_force", "drawing force", "tab:blue"),
              ("clamping_force", "clamping force", "tab:orange")]
    if scene_name == "flat_die":
        curves += [("sum_ft", "|sum R_T| (sum_ft)", "tab:green"),
                   ("mu_sum_fn", "mu x sum R_N (mu_sum_fn)", "tab:red")]
    curves = [c for c in curves if c[0] in values]
    fig, (ax_u, ax_t) = plt.subplots(1, 2, figsize=(1500 / _DPI, 650 / _DPI), dpi=_DPI,
                                     layout="constrained")
    fig.suptitle(title)
    draw = phase == "draw"
    u_label = "jaw travel s (mm)" if scene_name == "bead" else "drawing displacement U (mm)"
    if np.any(draw):
        for key, label, colour in curves:
            ax_u.plot(u[draw], np.asarray(values[key], dtype=np.float64)[draw], color=colour, label=label)
        a, b = summary["steady_window"]
        ax_u.axvspan(a, b, color="0.85", zorder=0, label=f"steady window [{a:g}, {b:g}] mm")
        steady = summary.get("steady_drawing_force")
        if steady is not None:
            ax_u.axhline(steady, color="k", ls=":", lw=1.2, label=f"steady drawing force {steady:.5g} N/mm")
        ax_u.legend(fontsize=8, loc="best")
    else:
        ax_u.text(0.5, 0.5, "no draw step was reached", ha="center", va="center", transform=ax_u.transAxes)
    ax_u.set_xlabel(u_label)
    ax_u.set_ylabel("force (N/mm)")
    ax_u.set_title("(a) draw phase")
    ax_u.grid(alpha=0.3)

    for key, label, colour in curves:
        ax_t.plot(time, np.asarray(values[key], dtype=np.float64), color=colour, label=label)
    for k in range(1, n_phases):
        ax_t.axvline(k, color="0.4", ls="--", lw=0.9)
    ax_t.set_xlim(0.0, max(float(n_phases), 1e-9))
    names = list(dict.fromkeys(phase))
    for k, name in enumerate(names):
        ax_t.text(k + 0.5 if k < n_phases else k, 1.01, name, ha="center", va="bottom",
                  transform=ax_t.get_xaxis_transform(), fontsize=9)
    ax_t.set_xlabel("pseudo-time t (s); phase k covers [k-1, k]")
    ax_t.set_ylabel("force (N/mm)")
    ax_t.set_title("(b) all phases", pad=16)
    ax_t.legend(fontsize=8, loc="best")
    ax_t.grid(alpha=0.3)
    _save(fig, path)


def contact_forces(contact: dict, name: str) -> np.ndarray:
    """(m, 2) force on the sheet f_p = R_N n + R_T t, t = (-n_y, n_x), at instant ``name`` (N/mm)."""
    rn, rt = contact[f"{name}__rn"], contact[f"{name}__rt"]
    n = contact[f"{name}__normal"]
    t = np.stack([-n[:, 1], n[:, 0]], axis=1)
    return rn[:, None] * n + rt[:, None] * t


def _region(contact: dict, names, roi, y_scale: float) -> tuple:
    """(x_min, x_max, y_min, y_max) in display coordinates (y multiplied by y_scale); entries of
    ``roi`` that are None are taken from the sheet's extent with a margin."""
    xs = np.concatenate([contact[f"{n}__x"] for n in names]) if names else contact["x0"]
    lo, hi = xs.min(axis=0), xs.max(axis=0)
    pad = 0.05 * (hi - lo) + 1e-3
    auto = (lo[0] - pad[0], hi[0] + pad[0], lo[1] - pad[1], hi[1] + pad[1])
    roi = tuple(roi) if roi is not None else (None,) * 4
    x0, x1, y0, y1 = (a if r is None else float(r) for r, a in zip(roi, auto))
    return x0, x1, y0 * y_scale, y1 * y_scale


def _layout(region, k: int) -> tuple[int, int, tuple]:
    """Rows, columns and figure size (inches) for k panels of the region's aspect ratio (at least
    1000 x 600 px)."""
    width, height = region[1] - region[0], region[3] - region[2]
    aspect = width / max(height, 1e-12)
    ncols = 1 if (aspect > 2.5 or k == 1) else 2
    nrows = math.ceil(k / ncols)
    panel_w = 1300 / ncols
    panel_h = panel_w / aspect
    if panel_h > 900:  # tall region: narrower panels
        panel_h = 900
        panel_w = max(900 * aspect, 300)
    panel_h = max(panel_h, 220)
    fig_w = max(1000, ncols * panel_w + 200)
    fig_h = max(600, min(nrows * (panel_h + 90) + 80, 3000))
    return nrows, ncols, (fig_w / _DPI, fig_h / _DPI)


def _draw_sheet(ax, x, elements, y_scale, values=None, edge="0.75", lw=0.3, cmap="viridis", norm=None):
    xy = np.asarray(x) * np.array([1.0, y_scale])
    coll = PolyCollection(xy[np.asarray(elements)], edgecolors=edge, linewidths=lw,
                          facecolors="none" if values is None else None, cmap=cmap, norm=norm)
    if values is not None:
        coll.set_array(np.asarray(values))
    ax.add_collection(coll)
    return coll


def _draw_tools(ax, outlines, y_scale):
    for line in outlines:
        ax.plot(line[:, 0], line[:, 1] * y_scale, color="k", lw=1.2)


def _frame(ax, region, y_scale):
    ax.set_xlim(region[0], region[1])
    ax.set_ylim(region[2], region[3])
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    if y_scale == 1.0:
        ax.set_ylabel("y (mm)")
    else:  # ticks show the true y; the display is stretched
        ax.yaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v / y_scale:g}"))
        ax.set_ylabel(f"y (mm), display x{y_scale:g}")


def _nice(value: float) -> float:
    """Largest 1, 2 or 5 x 10^k not above ``value``."""
    e = 10.0 ** math.floor(math.log10(value))
    return max(c * e for c in (1.0, 2.0, 5.0) if c * e <= value * (1 + 1e-12))


def contact_figure(path: str, title: str, contact: dict, outlines: dict, roi, y_scale: float = 1.0) -> None:
    """``contact.png``: one panel per instant; deformed mesh edges (light grey), tools, and at every
    closed pair an arrow of the force on the sheet f_p from the node (blue stick, red slip), with one
    length scale for all panels and a key arrow in N/mm."""
    names = [str(n) for n in contact["instant_names"]]
    region = _region(contact, names, roi, y_scale)
    nrows, ncols, size = _layout(region, len(names))
    fig, axes = plt.subplots(nrows, ncols, figsize=size, dpi=_DPI, layout="constrained", squeeze=False)
    fig.suptitle(_title(title, y_scale))
    forces = {n: contact_forces(contact, n) for n in names}
    f_max = max([float(np.max(np.linalg.norm(f[contact[f"{n}__status"] > 0], axis=1), initial=0.0))
                 for n, f in forces.items()], default=0.0)
    # one scale for all panels: the largest force is drawn 15% of the smaller region side long
    length = 0.15 * min(region[1] - region[0], region[3] - region[2])
    scale = f_max / length if f_max > 0 else 1.0  # N/mm per mm of display
    pair_node = contact["pair_node"]
    for ax, name in zip(axes.ravel(), names):
        x = contact[f"{name}__x"]
        _draw_sheet(ax, x, contact["elements"], y_scale)
        _draw_tools(ax, outlines.get(name, []), y_scale)
        status = contact[f"{name}__status"]
        closed = status > 0
        if np.any(closed):
            at = x[pair_node] * np.array([1.0, y_scale])
            f = forces[name]
            colours = np.where(status == 1, _STICK, _SLIP)[closed]
            q = ax.quiver(at[closed, 0], at[closed, 1], f[closed, 0], f[closed, 1], color=list(colours),
                          angles="xy", scale_units="xy", scale=scale, width=0.002, zorder=3)
            key = _nice(f_max)
            ax.quiverkey(q, 0.82, 1.02, key, f"{key:g} N/mm", labelpos="E", coordinates="axes",
                         color="k")
        else:
            ax.text(0.02, 0.95, "no closed pair", transform=ax.transAxes, va="top", fontsize=9)
        step = int(contact["instant_steps"][names.index(name)])
        u = float(contact["instant_drawing_displacement"][names.index(name)])
        ax.set_title(f"{name} (step {step}, U = {u:.4g} mm)", loc="left", fontsize=10)
        _frame(ax, region, y_scale)
    for ax in axes.ravel()[len(names):]:
        ax.set_visible(False)
    handles = [Line2D([], [], color=_STICK, lw=2, label="stick"), Line2D([], [], color=_SLIP, lw=2, label="slip"),
               Line2D([], [], color="k", lw=1.2, label="tools")]
    fig.legend(handles=handles, loc="outside lower center", ncols=3, fontsize=9)
    _save(fig, path)


def mesh_figure(path: str, title: str, contact: dict, outlines: dict, roi, y_scale: float = 1.0) -> None:
    """``mesh.png``: the deformed mesh at ``final``, elements filled by equivalent plastic strain, thin
    edges, tools drawn, colour bar "equivalent plastic strain"."""
    names = [str(n) for n in contact["instant_names"]]
    name = "final" if "final" in names else names[-1]
    region = _region(contact, [name], roi, y_scale)
    _, _, size = _layout(region, 1)
    fig, ax = plt.subplots(figsize=size, dpi=_DPI, layout="constrained")
    fig.suptitle(_title(title, y_scale))   # the spec's title; what is shown goes on the axes
    ax.set_title(f"deformed mesh at '{name}'")
    eqps = contact[f"{name}__eqps"]
    top = float(np.max(eqps)) if eqps.size and np.max(eqps) > 0 else 1.0
    coll = _draw_sheet(ax, contact[f"{name}__x"], contact["elements"], y_scale, values=eqps, edge="k",
                       lw=0.15, norm=matplotlib.colors.Normalize(0.0, top))
    _draw_tools(ax, outlines.get(name, []), y_scale)
    _frame(ax, region, y_scale)
    fig.colorbar(coll, ax=ax, label="equivalent plastic strain", shrink=0.8)
    _save(fig, path)
