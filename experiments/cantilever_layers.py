"""Layers through the thickness in plastic bending with a moment gradient: ``python experiments/cantilever_layers.py``.

A 1 mm thick cantilever of the Nine test's steel, clamped on its left face (u = v = 0), its right face moved
by D across the strip in 20 steps (v only, the face free to rotate): the moment grows linearly from the tip to
the clamp, where the strip yields, and the shear force is the moment over the length. Two lengths, with the
largest plastic strain at the clamp 0.02 to 0.07: 3 mm (D = 0.15 mm; a shear force of about 27 N/mm, that of
the Nine's span between the entry channel's exit and A) and 12 mm (D = 0.75 mm; a fifth of it). ``anst`` with
4 points through each element, elements 1/12 mm long, 3, 6, 12 and 24 layers: the tip force (N/mm) against the
layers. Pure bending, without shear, is within 1 % at 3 layers (``tests/test_element_anst.py``). The clamp's
corners are singular and are refined with the layers too.

Writes ``experiments/results/cantilever_layers.csv`` and prints the table.
"""

from __future__ import annotations

import dataclasses
import os

import jax
import jax.numpy as jnp

import jaxfric as jf
from benchutil import write_rows
from jaxfric import DirichletBC, Phase, Ramp, StripModel, strip_mesh

jax.config.update("jax_enable_x64", True)

STEEL = jf.J2Material(E=200000.0, nu=0.3, sigma_y=171.0, A=121.74485, n=0.23)
CASES = ((3.0, 0.15), (12.0, 0.75))   # length (mm), tip deflection (mm)
ELEMENT_LENGTH = 1.0 / 12.0
LAYERS = (3, 6, 12, 24)


def tip_force(length: float, deflection: float, ny: int) -> tuple[float, float]:
    """Tip force (N/mm) and the largest equivalent plastic strain of the cantilever on ``ny`` layers."""
    mesh = strip_mesh(0.0, length, 0.0, 1.0, round(length / ELEMENT_LENGTH), ny)
    clamp = DirichletBC(mesh.left)
    tip = DirichletBC(mesh.right, components=(1,), motion=Ramp((0.0, 0.0), (0.0, deflection)))
    model = StripModel(mesh, STEEL, (Phase("bend", [clamp, tip], n_steps=20),), formulation="anst")
    result = jf.run(dataclasses.replace(model, thickness_points=4), progress=False)
    return float(jnp.sum(result.final.f_int[mesh.right, 1])), float(jnp.max(result.final.material.eqps))


def main() -> None:
    rows = []
    for length, deflection in CASES:
        forces = {ny: tip_force(length, deflection, ny) for ny in LAYERS}
        finest = forces[LAYERS[-1]][0]
        for ny, (force, eqps) in forces.items():
            rows.append({"length_mm": length, "deflection_mm": deflection, "layers": ny,
                         "tip_force": f"{force:.6f}", "against_24_layers": f"{force / finest - 1.0:+.5f}",
                         "eqps_max": f"{eqps:.4f}"})
            print(length, ny, rows[-1]["tip_force"], rows[-1]["against_24_layers"], rows[-1]["eqps_max"], flush=True)
    write_rows(os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "cantilever_layers.csv"), rows)


if __name__ == "__main__":
    main()
