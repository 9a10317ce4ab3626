"""Elements through the thickness in plastic bending: ``python experiments/layer_patches.py``.

Three strip problems (the Nine's steel, a 2 x 1 mm strip, end faces turned about their centres and
shifted along the strip, y held at one node of each face), each run with ``ans`` and ``anst`` on 3, 6, 12
and 24 layers, the element length fixed:

- ``bend``: pure bending to 4 % surface strain (curvature 0.08 / mm, 6 elements along, 10 steps);
- ``bend_tension``: bending to 15 % surface strain (curvature 0.3 / mm, as on the Nine's shoulders) with
  a 1 % stretch, in one ramp (12 elements along, 20 steps);
- ``cycle``: the same stretch and curvature, then reversed to -0.3 / mm and back to straight (12
  elements along, 3 x 20 steps), the bend-unbend sequence of a strip drawn over a bead.

Output per run: the end moment (and axial force) at the end, and the plastic work per unit length,
sum over the points of w_g int_0^eqps sigma_Y, divided by the strip's length; relative to the 24-layer
run of the same element. Writes ``experiments/results/layer_patches.csv`` and prints it.
"""

from __future__ import annotations

import os

import jax
import numpy as np

import jaxfric as jf
from benchutil import write_rows
from jaxfric.fem.assembly import mesh_geometry
from strips import bending_path, end_axial_force, end_moment

jax.config.update("jax_enable_x64", True)

LENGTH, T = 2.0, 1.0
STEEL = jf.J2Material(E=200000.0, nu=0.3, sigma_y=171.0, A=121.74485, n=0.23)
# name: (elements along, end rotation and shift (mm) reached by each phase, steps per phase)
CASES = {
    "bend": (6, ((0.08, 0.0),), 10),
    "bend_tension": (12, ((0.3, 0.01),), 20),
    "cycle": (12, ((0.3, 0.01), (-0.3, 0.01), (0.0, 0.01)), 20),
}
LAYERS = (3, 6, 12, 24)


def plastic_work(result, mesh, material) -> float:
    """Plastic work per unit length of the strip (N mm / mm / mm): sum_g w_g int_0^eqps_g sigma_Y / L."""
    eqps = np.asarray(result.final.material.eqps)
    sy, a, n = float(material.sigma_y), float(material.A), float(material.n)
    density = sy * ((1.0 + a * eqps) ** (n + 1.0) - 1.0) / (a * (n + 1.0))
    return float(np.sum(np.asarray(mesh_geometry(mesh).weight) * density)) / LENGTH


def run_case(name: str, formulation: str, ny: int) -> dict:
    nx, path, n_steps = CASES[name]
    model = bending_path(LENGTH, T, nx, ny, path, STEEL, n_steps, formulation)
    result = jf.run(model, progress=False)
    return {"case": name, "formulation": formulation, "ny": ny, "nx": nx,
            "moment": end_moment(result, model.mesh), "axial_force": end_axial_force(result, model.mesh),
            "plastic_work": plastic_work(result, model.mesh, STEEL)}


def main() -> None:
    rows = [run_case(name, f, ny) for name in CASES for f in ("ans", "anst") for ny in LAYERS]
    for r in rows:
        ref = next(q for q in rows if (q["case"], q["formulation"], q["ny"]) == (r["case"], r["formulation"], 24))
        r["moment_rel"] = r["moment"] / ref["moment"] - 1.0
        r["plastic_work_rel"] = r["plastic_work"] / ref["plastic_work"] - 1.0
        print(f"{r['case']:<13} {r['formulation']:<5} ny={r['ny']:<3} M {r['moment']:9.4f} ({r['moment_rel']:+.2%})"
              f"  N {r['axial_force']:8.3f}  W_p {r['plastic_work']:9.4f} ({r['plastic_work_rel']:+.2%})")
    write_rows(os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "layer_patches.csv"),
               [{k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()} for r in rows])


if __name__ == "__main__":
    main()
