"""Ready-made strip problems: the stretch-bend strip of the demo (``experiments/demo.py``) and the core
benchmark (``experiments/bench_core.py``), and the pure-bending patch of the element studies
(``experiments/bending_elements.py``, ``tests/test_solver.py``)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxfric import DirichletBC, J2Material, Phase, Ramp, RigidMotion, StripModel, run, strip_mesh

__all__ = ["stretch_bend_strip", "end_rotation", "pure_bending", "bending_path", "end_moment", "end_axial_force",
           "bending_ratio"]


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


def end_rotation(mesh, angle, side):
    """x-components of an end face follow a rotation by ``angle`` (rad) about the face centre."""
    nodes = getattr(mesh, side)
    x_c = float(mesh.nodes[nodes[0], 0])
    y_c = float(jnp.mean(mesh.nodes[nodes, 1]))
    return DirichletBC(nodes, components=(0,),
                          motion=RigidMotion(pivot=(x_c, y_c), angle_start=0.0, angle_end=angle))


def pure_bending(length, thickness, nx, ny, angle, material, n_steps=1, formulation="fbar", order=1):
    """Pure bending: end faces rotated by -angle (left) and +angle (right) about their centres,
    y fixed at the bottom node of each face only, so the faces contract freely and the exact
    plane-strain solution of linear elasticity is admissible (both bottom corners have the same
    exact v, so fixing them removes only rigid motions). Positive angle: the top fibre is compressed.
    ``order``: the elements' order along the strip (:func:`jaxfric.strip_mesh`)."""
    mesh = strip_mesh(-length / 2, length / 2, -thickness / 2, thickness, nx, ny, order=order)
    bcs = [end_rotation(mesh, -angle, "left"), end_rotation(mesh, angle, "right"),
           DirichletBC([mesh.left[0], mesh.right[0]], components=(1,))]
    return StripModel(mesh, material, (Phase("bend", bcs, n_steps=n_steps),), formulation=formulation)


def bending_path(length, thickness, nx, ny, path, material, n_steps, formulation, order=1):
    """As :func:`pure_bending`, along a path of phases: phase k turns the end faces from the previous
    (angle, shift) to ``path[k]`` = (angle, shift) (rad, mm; from (0, 0)), the right face by +angle and
    +shift along x, the left by the opposite; ``n_steps`` steps per phase."""
    mesh = strip_mesh(-length / 2, length / 2, -thickness / 2, thickness, nx, ny, order=order)
    pin = DirichletBC([mesh.left[0], mesh.right[0]], components=(1,))

    def face(side, sign, start, end):
        nodes = getattr(mesh, side)
        pivot = (float(mesh.nodes[nodes[0], 0]), float(jnp.mean(mesh.nodes[nodes, 1])))
        return DirichletBC(nodes, components=(0,), motion=RigidMotion(
            pivot=pivot, angle_start=sign * start[0], angle_end=sign * end[0],
            shift_start=(sign * start[1], 0.0), shift_end=(sign * end[1], 0.0)))

    ends = [(0.0, 0.0), *path]
    phases = tuple(Phase(f"path{k}", [face("left", -1.0, a, b), face("right", 1.0, a, b), pin], n_steps=n_steps)
                   for k, (a, b) in enumerate(zip(ends[:-1], ends[1:])))
    return StripModel(mesh, material, phases, formulation=formulation)


def end_moment(result, mesh):
    """Moment (N mm / mm) of the right-face reactions about the face centre (counter-clockwise > 0)."""
    nodes = mesh.right
    y = mesh.nodes[nodes, 1] - jnp.mean(mesh.nodes[nodes, 1])
    f = result.final.f_int[nodes]
    return float(-jnp.sum(y * f[:, 0]))


def end_axial_force(result, mesh):
    """Axial force (N/mm) of the right-face reactions, positive in tension."""
    return float(jnp.sum(result.final.f_int[mesh.right, 0]))


def bending_ratio(ny, formulation, nx=40, length=2.0, order=1):
    """M_FE / M_beam for pure bending of an elastic strip (plane strain, nu = 0.3), with
    M_beam = E/(1-nu^2) t^3/12 kappa, kappa = 2 angle / length."""
    E, nu, t, angle = 200000.0, 0.3, 1.0, 1e-4
    model = pure_bending(length, t, nx=nx, ny=ny, angle=angle, material=J2Material.elastic(E, nu),
                         formulation=formulation, order=order)
    res = run(model, progress=False)
    return abs(end_moment(res, model.mesh)) / (E / (1 - nu**2) * t**3 / 12 * 2 * angle / length)
