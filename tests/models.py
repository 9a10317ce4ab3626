"""Small strip problems shared by the core tests (built only from the public API)."""

import jax.numpy as jnp
import numpy as np

import jaxfric as jf

# A steel-like hardening material, and its perfectly plastic version.
STEEL = dict(E=200000.0, nu=0.3, sigma_y=200.0, A=100.0, n=0.25)


def clamped_pull(length=10.0, thickness=1.0, nx=10, ny=2, pull=0.15, unload=True, n_steps=4,
                 sigma_y=200.0, material=None, formulation="fbar", order=1):
    """Strip clamped on the left, right end pulled by ``pull`` (mm) in x with v = 0, then returned.

    The load-unload cycle leaves a path-dependent (compressive) residual reaction at the right end.
    ``order``: the elements' order along the strip.
    """
    mesh = jf.strip_mesh(0.0, length, 0.0, thickness, nx, ny, order=order)
    if material is None:
        material = jf.J2Material(**{**STEEL, "sigma_y": sigma_y})
    clamp = jf.DirichletBC(mesh.left)
    phases = [jf.Phase("load", [clamp, jf.DirichletBC(mesh.right, motion=jf.Ramp((0, 0), (pull, 0)))],
                       n_steps=n_steps)]
    if unload:
        phases.append(jf.Phase("unload", [clamp, jf.DirichletBC(mesh.right, motion=jf.Ramp((pull, 0), (0, 0)))],
                               n_steps=n_steps))
    return jf.StripModel(mesh, material, tuple(phases), formulation=formulation)


def flat_die_strip(law, length=6.0, half_thickness=0.395, nx=30, ny=2, force=50.0, mu=0.15,
                   draw=0.03, material=None, clamp_steps=10, increments=((1 / 12, 100), (1.0, 275))):
    """A small version of the benchmark's flat die: a force-driven die (line above the strip) clamps
    it with `force` N/mm frictionlessly, then the right end is drawn by `draw` mm with friction `mu`
    (the spec's increments: 100 steps to draw/12, then 275). v = 0 on the bottom (symmetry plane)."""
    from jaxfric.contact.rigid import Force, RigidTool
    from jaxfric.contact.tools import Tool

    mesh = jf.strip_mesh(0.0, length, 0.0, half_thickness, nx, ny)
    if material is None:
        material = jf.J2Material(E=69004.0, nu=0.3, sigma_y=80.55923, A=10000.0, n=0.216)
    die = Tool.line((-2.0, half_thickness), (length + 2.0, half_thickness), normal_side="right")
    tool = RigidTool("die", die, drive=(0.0, -1.0), candidates=mesh.top,
                     controls=(Force(force, start=0.0), Force(force)), mu=(0.0, mu))
    sym = jf.DirichletBC(mesh.bottom, components=(1,))
    hold = jf.DirichletBC(mesh.right, components=(0,))
    pull = jf.DirichletBC(mesh.right, components=(0,), motion=jf.Ramp((0, 0), (draw, 0)))
    phases = (jf.Phase("clamp", [sym, hold], clamp_steps),
              jf.Phase("draw", [sym, pull], increments=increments))
    return jf.StripModel(mesh, material, phases, tools=(tool,), contact=law)


def wrapped_strip(radius=10.0, thickness=0.1, wrap=np.pi / 2, leg=5.0, h=0.1, ny=2):
    """A thin strip lying stress-free over the top of a roller of centre (0, 0): an arc of `wrap` rad on
    the circle of `radius` (its inner surface, j = 0, on the circle) between two straight tangent legs.
    Returns the mesh and the unit directions of the strip along its incoming and outgoing legs."""
    phi1, phi2 = np.pi / 2 + wrap / 2, np.pi / 2 - wrap / 2
    arc = radius * wrap
    n_leg, n_arc = int(round(leg / h)), int(round(arc / h))
    s = np.concatenate([np.linspace(-leg, 0, n_leg + 1)[:-1], np.linspace(0, arc, n_arc + 1),
                        arc + np.linspace(0, leg, n_leg + 1)[1:]])
    r = radius + thickness * np.arange(ny + 1) / ny
    d1, d2 = np.array([np.sin(phi1), -np.cos(phi1)]), np.array([np.sin(phi2), -np.cos(phi2)])
    nodes = np.zeros((s.size, ny + 1, 2))
    for i, si in enumerate(s):
        if si < 0:
            nodes[i] = r[:, None] * np.array([np.cos(phi1), np.sin(phi1)]) + si * d1
        elif si > arc:
            nodes[i] = r[:, None] * np.array([np.cos(phi2), np.sin(phi2)]) + (si - arc) * d2
        else:
            phi = phi1 - si / radius
            nodes[i] = r[:, None] * np.array([np.cos(phi), np.sin(phi)])
    return jf.StripMesh(jnp.asarray(nodes.reshape(-1, 2)), s.size - 1, ny), d1, d2
