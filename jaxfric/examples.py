"""Ready-made strip problems for the demo, the core benchmark and notebooks."""

from __future__ import annotations

import numpy as np

from .loading import DirichletBC, Phase, Ramp, RigidMotion
from .material import J2Material
from .mesh import strip_mesh
from .simulate import StripModel

__all__ = ["stretch_bend_strip"]


def stretch_bend_strip(nx: int = 300, ny: int = 3, length: float = 30.0, thickness: float = 1.0,
                       stretch: float = 0.3, angle_deg: float = 20.0, n_stretch: int = 10,
                       n_bend: int = 20, material: J2Material | None = None) -> StripModel:
    """A strip clamped on the left; its right end is first pulled by ``stretch`` (mm, plastic: 1 % by
    default), then turned by ``angle_deg`` about its centre (counter-clockwise), which bends the strip
    into an S with plastic hinges at both ends. Material: the Nine test's steel (benchmark Table 4).
    """
    mesh = strip_mesh(0.0, length, 0.0, thickness, nx, ny)
    if material is None:
        material = J2Material(E=200000.0, nu=0.3, sigma_y=171.0, A=121.74485, n=0.23)
    clamp = DirichletBC(mesh.left)
    centre = (length + stretch, thickness / 2)
    pull = DirichletBC(mesh.right, motion=Ramp((0.0, 0.0), (stretch, 0.0)))
    turn = DirichletBC(mesh.right, motion=RigidMotion(pivot=centre, angle_start=0.0,
                                                      angle_end=np.deg2rad(angle_deg),
                                                      shift_start=(stretch, 0.0), shift_end=(stretch, 0.0)))
    return StripModel(mesh, material, (Phase("stretch", [clamp, pull], n_steps=n_stretch),
                                       Phase("bend", [clamp, turn], n_steps=n_bend)))
