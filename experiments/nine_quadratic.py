"""The Nine test on elements quadratic along the strip: ``python experiments/nine_quadratic.py``.

    python experiments/nine_quadratic.py [--root DIR] [--only CASE ...] [--table]

The steady drawing force of the Nine test (the scene's defaults: the entry channel, exact contact
``lcp_ssn``; U_draw 36 mm and half the nominal increments, as the reference ladder of docs/results.md)
with ``anst`` and 4 Gauss points through each element, on elements quadratic along the strip
(``--set element_order=2``) against the bilinear ones, on 150, 300 and 600 elements along and 3 layers:

- ``o2_MESH``: six-node elements, every surface node (corner and mid-side) a contact candidate;
- ``o2_MESH_corners``: the same with the corner nodes only, so that the contact points are spaced as on the
  bilinear mesh of the same element count while the elements are quadratic;
- ``o2_300x3_steps_x0.5``: a quarter of the nominal increments (the step error at this mesh), and
  ``o2_300x3_steps_x2`` the nominal ones (0.1 mm, the scene's default);
- ``o1_MESH``: the bilinear elements (``element_order=1``), for the cost and the ladder's bilinear side;
- ``o1_1200x3``, ``o2_1200x3``: the finest of both, and ``o1_1200x3_steps_x0.5`` its step error (measured
  with friction only);
- ``o2_100x2``: the coarse mesh of the fits; ``o2_150x3_steps_x2`` and ``o2_100x2_steps_x2`` at the scene's
  increments;
- ``o2_300x6``, ``o2_300x12``: twice and four times the layers (the error through the thickness at the
  spec mesh's length); ``o2_150x6``, ``o2_150x12``, ``o2_150x24`` and ``o2_600x6``: the grid of element
  lengths and layers from which the force converged in both directions is extrapolated;
- ``o2_150xN_end_nodes``: the left-end nodes held instead of the entry channel (``entry_guide_kind=end_nodes``),
  and ``o2_150xN_guide6`` the channel's exit 6 mm before A instead of 3, to separate the channel's share of
  the layers' error.

Each case is a run directory under ``--root`` (default ``runs/nine_quadratic``, kept: a second call reads it
back); the table goes to ``experiments/results/nine_quadratic.csv`` and to stdout, and the force against the
layers to ``nine_quadratic_layers.png``. ``--only`` runs some cases
(to spread them over processes), ``--table`` only reads back what is on disk.
"""

from __future__ import annotations

import dataclasses
import os
import sys

from benchutil import read_rows, run_cases_main, run_or_read
from jaxfric import scenes

HERE = os.path.dirname(os.path.abspath(__file__))
BASE = {"U_draw": 36.0, "dq_clamp": 0.05, "dU": 0.05, "element": "anst", "thickness_points": 4}
END_NODES = {"entry_guide_kind": "end_nodes"}
GUIDE_END = scenes.nine.NineConfig().guide_end   # the scene's channel exit, mm before A's top
# the channel's exit 6 mm before A instead of 3 (the tail reaches it at U = 35.5 mm: the window ends at 30)
GUIDE_6 = {"guide_end": -6.0, "steady_window": (20.0, 30.0)}
# (mesh, element order, increment factor on BASE's, contact on the corner nodes only, other overrides)
VARIATIONS = {
    "o2_150x3": ("150x3", 2, 1.0, False, {}),
    "o2_300x3": ("300x3", 2, 1.0, False, {}),
    "o2_600x3": ("600x3", 2, 1.0, False, {}),
    "o2_300x3_corners": ("300x3", 2, 1.0, True, {}),
    "o2_600x3_corners": ("600x3", 2, 1.0, True, {}),
    "o2_300x3_steps_x0.5": ("300x3", 2, 0.5, False, {}),
    "o2_300x3_steps_x2": ("300x3", 2, 2.0, False, {}),
    "o1_300x3": ("300x3", 1, 1.0, False, {}),
    "o1_1200x3": ("1200x3", 1, 1.0, False, {}),
    "o2_1200x3": ("1200x3", 2, 1.0, False, {}),
    "o1_1200x3_steps_x0.5": ("1200x3", 1, 0.5, False, {}),
    "o2_100x2": ("100x2", 2, 1.0, False, {}),
    "o2_150x3_steps_x2": ("150x3", 2, 2.0, False, {}),
    "o2_100x2_steps_x2": ("100x2", 2, 2.0, False, {}),
    "o2_300x6": ("300x6", 2, 1.0, False, {}),
    "o2_300x12": ("300x12", 2, 1.0, False, {}),
    "o2_150x6": ("150x6", 2, 1.0, False, {}),
    "o2_150x12": ("150x12", 2, 1.0, False, {}),
    "o2_150x24": ("150x24", 2, 1.0, False, {}),
    "o2_600x6": ("600x6", 2, 1.0, False, {}),
    "o2_150x3_end_nodes": ("150x3", 2, 1.0, False, END_NODES),
    "o2_150x6_end_nodes": ("150x6", 2, 1.0, False, END_NODES),
    "o2_150x12_end_nodes": ("150x12", 2, 1.0, False, END_NODES),
    "o2_150x3_guide6": ("150x3", 2, 1.0, False, GUIDE_6),
    "o2_150x12_guide6": ("150x12", 2, 1.0, False, GUIDE_6),
}
CASES = {f"{variant}_{name}": (variant, *v) for variant in ("mu000", "mu017") for name, v in VARIATIONS.items()}


def corners_only(model):
    """``model`` with the contact candidates of every tool on the corner node columns only (even columns of
    an ``order=2`` mesh)."""
    ny1 = model.mesh.ny + 1
    tools = tuple(dataclasses.replace(t, candidates=tuple(int(n) for n in t.candidates if (n // ny1) % 2 == 0))
                  for t in model.tools)
    return dataclasses.replace(model, tools=tools)


def run_one(name: str, root: str) -> dict:
    variant, mesh, order, factor, corners, other = CASES[name]
    overrides = {**BASE, "mesh": mesh, "element_order": order,
                 "dq_clamp": BASE["dq_clamp"] * factor, "dU": BASE["dU"] * factor, **other}

    def build():
        scene = scenes.make("nine", variant, "lcp_ssn", overrides)
        return dataclasses.replace(scene, model=corners_only(scene.model)) if corners else scene

    s = run_or_read(os.path.join(root, name), build, "nine_quadratic",
                    f"{name}: running {overrides}, corner contact {corners}")
    iters = s.get("newton_iters_total")
    return {"case": name, "variant": variant, "mesh": mesh, "element_order": order, "increments": BASE["dU"] * factor,
            "contact_corners_only": corners, "entry_guide_kind": other.get("entry_guide_kind", "channel"),
            "guide_end": other.get("guide_end", GUIDE_END),
            "steady_drawing_force": s.get("steady_drawing_force"),
            "converged": s.get("converged"), "n_steps": s.get("n_steps"), "newton_iters_total": iters,
            "wall_s": s.get("wall_s"), "compile_s": s.get("compile_s")}


def plot_layers(rows: list[dict], path: str) -> None:
    """The steady force of the six-node element at the base increments against the layers through the
    thickness, one line per variant, entry guide and element count along the strip."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11.0, 4.5), constrained_layout=True)
    for ax, variant in zip(axes, ("mu000", "mu017"), strict=True):
        own = [r for r in rows if r["variant"] == variant and r["element_order"] == 2 and r["increments"] == BASE["dU"]
               and not r["contact_corners_only"] and r["mesh"] != "100x2"]
        for guide, nx in sorted({(_guide(r), r["mesh"].split("x")[0]) for r in own}):
            pts = sorted((int(r["mesh"].split("x")[1]), r["steady_drawing_force"]) for r in own
                         if _guide(r) == guide and r["mesh"].split("x")[0] == nx)
            if len(pts) > 1:
                ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-" if guide == DEFAULT_GUIDE else "s--",
                        label=f"{nx} along, {guide}")
        ax.set_xscale("log", base=2)
        ax.set_xticks([3, 6, 12, 24], ["3", "6", "12", "24"])
        ax.set_xlabel("layers through the thickness")
        ax.set_ylabel("steady drawing force (N/mm)")
        ax.set_title(f"Nine {variant}, six-node anst p4, 0.05 mm")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    csv_path = os.path.join(HERE, "results", "nine_quadratic.csv")
    done = run_cases_main(argv, __doc__, CASES, run_one, os.path.join("runs", "nine_quadratic"), csv_path)
    if os.path.exists(csv_path):
        plot_layers(_typed(read_rows(csv_path)), os.path.join(HERE, "results", "nine_quadratic_layers.png"))
    return done


def _guide(row: dict) -> str:
    """How a case leads the strip onto A, in words."""
    if row.get("entry_guide_kind", "channel") != "channel":
        return row["entry_guide_kind"].replace("_", " ")
    return f"channel to {float(row.get('guide_end', GUIDE_END)):g} mm"


DEFAULT_GUIDE = _guide({})


def _typed(rows: list[dict]) -> list[dict]:
    """CSV rows with the fields the figure reads as numbers and booleans."""
    return [{**r, "element_order": int(r["element_order"]), "increments": float(r["increments"]),
             "contact_corners_only": r["contact_corners_only"] == "True",
             "entry_guide_kind": r.get("entry_guide_kind") or "channel",
             "steady_drawing_force": float(r["steady_drawing_force"])} for r in rows]


if __name__ == "__main__":
    sys.exit(main())
