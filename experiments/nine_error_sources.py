"""Where the Nine test's discretisation error comes from: ``python experiments/nine_error_sources.py``.

    python experiments/nine_error_sources.py [--root DIR] [--only CASE ...] [--table]

The steady drawing force of the Nine test (``mu000``: no friction, so the force is the plastic work of
bending and unbending per unit length drawn; ``mu017``: with the friction of the wraps) on variations
of one mesh, each changing one candidate source of error and nothing else:

- the element: F-bar (``fbar``) against F-bar on assumed natural strains (``ans``, no parasitic shear)
  and against assumed natural strains with a condensed through-thickness mode (``anst``, no parasitic
  shear and no constant dilatation per element);
- the contact discretisation along the wraps: ``ans`` on 600 x 3 with every node of the surfaces a
  contact candidate, and with every second one only, so that the contact points are spaced as on
  300 x 3 while the elements are those of 600 x 3;
- the time step: the nominal increments and a half of them (the cases' default) and a quarter;
- the layers: 3, 6 and 12 through the thickness, on 300 and 600 elements along (and ``anst`` on 1200 x 6);
- the Gauss points through each element's thickness: 2 (the 2 x 2 rule) and 4 (``anst``, cases ``_p4``).

Exact contact (``lcp_ssn``), U_draw 36 mm, half the nominal increments unless named, as the reference
ladder of docs/results.md. Each case is a run directory under ``--root`` (default
``runs/nine_error_sources``, kept: a second call reads it back); the table goes to
``experiments/results/nine_error_sources.csv`` and to stdout. ``--only`` runs some cases (to spread them
over processes), ``--table`` only reads back what is on disk.
"""

from __future__ import annotations

import dataclasses
import os
import sys

from benchutil import run_cases_main, run_or_read
from jaxfric import scenes
from jaxfric.contact.rigid import RigidTool

HERE = os.path.dirname(os.path.abspath(__file__))
BASE = {"U_draw": 36.0, "dq_clamp": 0.05, "dU": 0.05, "entry_guide_kind": "end_nodes"}
# (mesh, element, increment factor on BASE's, contact candidates: every k-th surface node[, Gauss points
# through each element's thickness: 2 unless given])
VARIATIONS = {
    "fbar_300x3": ("300x3", "fbar", 1.0, 1),
    "ans_300x3": ("300x3", "ans", 1.0, 1),
    "fbar_600x3": ("600x3", "fbar", 1.0, 1),
    "ans_600x3": ("600x3", "ans", 1.0, 1),
    "ans_600x3_contact_every_2nd": ("600x3", "ans", 1.0, 2),
    "ans_300x3_steps_x2": ("300x3", "ans", 2.0, 1),
    "ans_300x3_steps_x0.5": ("300x3", "ans", 0.5, 1),
    "ans_300x6": ("300x6", "ans", 1.0, 1),
    "anst_300x3": ("300x3", "anst", 1.0, 1),
    "anst_600x3": ("600x3", "anst", 1.0, 1),
    "anst_300x6": ("300x6", "anst", 1.0, 1),
    "ans_300x12": ("300x12", "ans", 1.0, 1),
    "anst_300x12": ("300x12", "anst", 1.0, 1),
    "ans_600x12": ("600x12", "ans", 1.0, 1),
    "anst_600x6": ("600x6", "anst", 1.0, 1),
    "anst_1200x6": ("1200x6", "anst", 1.0, 1),
    "anst_300x3_p4": ("300x3", "anst", 1.0, 1, 4),
    "anst_300x6_p4": ("300x6", "anst", 1.0, 1, 4),
    "anst_100x2": ("100x2", "anst", 1.0, 1),
    "anst_100x2_p4": ("100x2", "anst", 1.0, 1, 4),
}
CASES = {f"{variant}_{name}": (variant, *v) for variant in ("mu000", "mu017") for name, v in VARIATIONS.items()}


def thinned(model, every: int):
    """``model`` with every ``every``-th candidate node of each tool kept (the first and the last kept)."""
    if every == 1:
        return model
    tools = []
    for t in model.tools:
        keep = list(t.candidates[::every])
        if keep[-1] != t.candidates[-1]:
            keep.append(t.candidates[-1])
        tools.append(RigidTool(t.name, t.geometry, t.drive, keep, t.controls, t.mu, frictional=t.frictional))
    return dataclasses.replace(model, tools=tuple(tools))


def run_one(name: str, root: str) -> dict:
    variant, mesh, element, factor, every, *points = CASES[name]
    points = points[0] if points else 2
    overrides = {**BASE, "mesh": mesh, "element": element, "thickness_points": points,
                 "dq_clamp": BASE["dq_clamp"] * factor, "dU": BASE["dU"] * factor}

    def build():
        scene = scenes.make("nine", variant, "lcp_ssn", overrides)
        return dataclasses.replace(scene, model=thinned(scene.model, every))

    s = run_or_read(os.path.join(root, name), build, "nine_error_sources",
                    f"{name}: running {overrides}, contact on every {every} surface node")
    return {"case": name, "variant": variant, "mesh": mesh, "element": element, "thickness_points": points,
            "increments": BASE["dU"] * factor,
            "contact_every": every, "steady_drawing_force": s.get("steady_drawing_force"),
            "converged": s.get("converged"), "n_steps": s.get("n_steps"),
            "newton_iters_total": s.get("newton_iters_total"), "wall_s": s.get("wall_s")}


def main(argv=None) -> int:
    return run_cases_main(argv, __doc__, CASES, run_one, os.path.join("runs", "nine_error_sources"),
                          os.path.join(HERE, "results", "nine_error_sources.csv"))


if __name__ == "__main__":
    sys.exit(main())
