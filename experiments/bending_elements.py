"""Elements in bending: ``python experiments/bending_elements.py``.

Pure bending of a 0.5 x 1 mm strip (10 elements along, end faces rotated about their centres) with
each element formulation, in two regimes:

- elastic (nu = 0.3, rotation 1e-4 rad): moment against plane-strain beam theory,
  M = E / (1 - nu^2) t^3 / 12 kappa;
- plastic (the Nine test's steel, rotations 0.005 and 0.02 rad in 10 steps, surface strains of
  about 1 % and 4 %): moment against F-bar with 12 elements through the thickness;

and, with 3 elements through a 1 mm strip whose elements are ``aspect`` = 1, 2 and 4 times as long as
they are thick (the parasitic shear of a bent Q4 grows with the element length):

- elastic: moment against beam theory, 10 elements along;
- plastic (curvature 0.08 / mm, surface strains of 4 %, 10 steps): the moment on 6 elements along over
  the moment on 24, the change from refining along the strip only.

Writes ``experiments/results/bending_elements.csv`` (formulation, elements through the thickness,
case, moment ratio) and prints the table.
"""

from __future__ import annotations

import os

import jax

import jaxfric as jf
from benchutil import write_rows
from strips import bending_ratio, end_moment, pure_bending

jax.config.update("jax_enable_x64", True)

LENGTH, T, NX = 0.5, 1.0, 10
STEEL = jf.J2Material(E=200000.0, nu=0.3, sigma_y=171.0, A=121.74485, n=0.23)


def moment(material, angle, formulation, ny, n_steps):
    model = pure_bending(LENGTH, T, nx=NX, ny=ny, angle=angle, material=material, n_steps=n_steps,
                         formulation=formulation)
    return end_moment(jf.run(model, progress=False), model.mesh)


def aspect_rows() -> list:
    rows = []
    for aspect in (1, 2, 4):
        for formulation in ("fbar", "ans", "eas"):
            ratio = bending_ratio(3, formulation, nx=10, length=10 * aspect / 3)
            rows.append({"case": f"elastic, aspect {aspect}, against beam theory", "formulation": formulation,
                         "ny": 3, "ratio": f"{ratio:.6f}"})
    for aspect in (1, 2, 4):
        length = 6 * aspect / 3
        for formulation in ("fbar", "ans", "eas"):
            m = [end_moment(jf.run(model, progress=False), model.mesh) for model in
                 (pure_bending(length, 1.0, nx=nx, ny=3, angle=0.04 * length, material=STEEL, n_steps=10,
                               formulation=formulation) for nx in (6, 24))]
            rows.append({"case": f"plastic, aspect {aspect}, M(6 along) / M(24 along)", "formulation": formulation,
                         "ny": 3, "ratio": f"{m[0] / m[1]:.6f}"})
    return rows


def main() -> None:
    rows = []
    for formulation in ("fbar", "ans", "q4", "eas"):
        for ny in (3, 6):
            ratio = bending_ratio(ny, formulation, nx=NX, length=LENGTH)
            rows.append({"case": "elastic, against beam theory", "formulation": formulation, "ny": ny,
                         "ratio": f"{ratio:.6f}"})
    for angle in (0.005, 0.02):
        ref = moment(STEEL, angle, "fbar", 12, 10)
        for formulation in ("fbar", "ans", "q4", "eas"):
            ratio = moment(STEEL, angle, formulation, 3, 10) / ref
            rows.append({"case": f"plastic {angle} rad, against F-bar 12 through", "formulation": formulation,
                         "ny": 3, "ratio": f"{ratio:.6f}"})
    rows += aspect_rows()
    for r in rows:
        print(f"{r['case']:<50} {r['formulation']:<5} ny={r['ny']:<3} {r['ratio']}")
    write_rows(os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "bending_elements.csv"), rows)


if __name__ == "__main__":
    main()
