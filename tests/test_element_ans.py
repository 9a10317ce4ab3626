"""The assumed-natural-strain F-bar element (``formulation="ans"``): bending without parasitic shear.

A bilinear element bent along its length turns its through-thickness fibres along the element, a
shear of about kappa dx / 2 that yields in plastic bending; the plastic work it adds is first order in
the element length. ``ans`` samples the through-thickness derivative on the element's centre line
(:mod:`jaxfric.fem.element`). These tests check what that must give: bending that does not depend on
the element's aspect ratio, a plastic moment converged along the strip at aspect ratio 1, no
volumetric locking, no hourglassing under strong compression, a consistent tangent. The patch test and
Newton's rate are in ``tests/test_solver.py`` with the other formulations.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfric as jf
from jaxfric.numerics.results import Result
from models import STEEL
from strips import bending_ratio, end_moment, pure_bending
from test_solver import thick_cylinder_ratio

NINE_STEEL = jf.J2Material(E=200000.0, nu=0.3, sigma_y=171.0, A=121.74485, n=0.23)


def test_elastic_bending_does_not_depend_on_the_aspect_ratio():
    """Elastic pure bending, 3 elements through a 1 mm strip, element length over element thickness 1,
    2 and 4. ``ans`` gives the same moment at every aspect ratio, that of F-bar with short elements
    (F-bar's constant dilatation per element, 7 % soft at 3 layers, tests/test_solver.py); F-bar's
    parasitic shear stiffens it with the aspect ratio (measured 0.967, 1.083, 1.550)."""
    ans = {a: bending_ratio(3, "ans", nx=10, length=10 * a / 3) for a in (1, 2, 4)}
    fbar = {a: bending_ratio(3, "fbar", nx=10, length=10 * a / 3) for a in (1, 4)}
    fbar_short = bending_ratio(3, "fbar", nx=10, length=10 * 0.1 / 3)
    report = f"ans {ans}, F-bar {fbar}, F-bar at aspect 0.1 {fbar_short:.6f}"
    assert all(abs(r / ans[1] - 1) < 1e-6 for r in ans.values()), report
    assert abs(ans[1] / fbar_short - 1) < 2e-3, report
    assert fbar[4] > 1.4 * fbar[1], report


@pytest.mark.parametrize("aspect", [1, 2])
def test_plastic_bending_is_converged_along_the_strip(aspect):
    """Plastic pure bending to 4 % surface strain (the Nine's steel, 3 elements through a 1 mm strip,
    6 elements of length ``aspect`` x thickness / 3 along it, 10 steps): refining 4 times along the strip
    changes the moment by less than 0.2 % with ``ans`` (measured 0.01 % and 0.07 %), by 3.7 % and 10 %
    with F-bar, whose parasitic shear yields and adds plastic work in proportion to the element length."""
    length = 6 * aspect / 3
    angle = 0.08 * length / 2  # curvature 0.08 / mm: surface strains of 4 %

    def moment(formulation, nx):
        model = pure_bending(length, 1.0, nx=nx, ny=3, angle=angle, material=NINE_STEEL, n_steps=10,
                             formulation=formulation)
        return end_moment(jf.run(model, progress=False), model.mesh)

    ans, fbar = moment("ans", 6) / moment("ans", 24), moment("fbar", 6) / moment("fbar", 24)
    assert abs(ans - 1) < 2e-3, f"ans: M(6) / M(24) = {ans:.5f}"
    assert fbar - 1 > 0.03, f"F-bar: M(6) / M(24) = {fbar:.5f} (the parasitic shear this element removes)"


def test_no_volumetric_locking():
    """The thick cylinder of tests/test_solver.py (elements of trapezoidal shape) with ``ans``: its limit
    pressure within 2 % on the coarse 4 x 8 mesh, as F-bar."""
    ratio = thick_cylinder_ratio("ans")
    assert abs(ratio - 1.0) < 0.02, f"limit pressure ratio {ratio:.4f}"


def compressed_block(formulation, n, order=1):
    """A 2 x 2 mm steel block held without slip between two flat platens (u = 0 on the bottom and the top
    faces), compressed by 40 % in 20 steps: the faces barrel, the corners fold; the strong compression
    under which enhanced-strain elements develop hourglass modes. ``order``: the elements' order along x.
    Returns (result, mesh)."""
    mesh = jf.strip_mesh(0.0, 2.0, 0.0, 2.0, n, n, order=order)
    bcs = [jf.DirichletBC(mesh.bottom), jf.DirichletBC(mesh.top, motion=jf.Ramp((0.0, 0.0), (0.0, -0.8)))]
    model = jf.StripModel(mesh, jf.J2Material(**STEEL), (jf.Phase("press", bcs, n_steps=20),),
                          formulation=formulation)
    return jf.run(model, progress=False), mesh


def hourglass_amplitude(result, mesh) -> float:
    """The largest bilinear (hourglass-shaped) part (1, -1, 1, -1) / 4 of an element's nodal displacements."""
    u = np.asarray(result.final.u)[mesh.elements]
    return float(np.abs(np.einsum("a,eai->ei", np.array([1.0, -1.0, 1.0, -1.0]) / 4, u)).max())


def test_strong_compression_without_hourglassing():
    """The block above on 6 x 6 elements: ``ans`` finishes the 40 % compression without an inverted element
    (the enhanced-strain element inverts one at 20 %, measured), and neither its press force nor the
    bilinear part of its element displacements departs far from F-bar's, which has no hourglass mode
    (measured ratios 0.92 and 1.17; an hourglass instability would multiply the second). The folding
    corners make this problem singular: on 24 x 24 the two elements still differ by 9 % in force, so this
    test bounds a failure mode, not an accuracy."""
    res, mesh = compressed_block("ans", 6)
    ref, _ = compressed_block("fbar", 6)
    assert int(res.code) == Result.SUCCESS  # an inverted element stops a run (INVERTED_ELEMENT)
    force, force_fbar = (-float(jnp.sum(r.final.f_int[mesh.top, 1])) for r in (res, ref))
    assert 0.85 < force / force_fbar < 1.15, f"press force {force:.2f} N/mm, F-bar {force_fbar:.2f}"
    ratio = hourglass_amplitude(res, mesh) / hourglass_amplitude(ref, mesh)
    assert ratio < 1.5, f"hourglass amplitude {ratio:.3f} times F-bar's"


@pytest.mark.parametrize("formulation", ["ans", "anst", "fbar"])
def test_element_tangent_is_the_derivative_of_its_force(formulation):
    """At a plastic state of one distorted element, the tangent equals central differences of its force
    (for ``anst`` with its thickness mode condensed)."""
    from jaxfric.fem.assembly import mesh_geometry
    from jaxfric.fem.element import element_force, element_force_and_tangent

    mesh = jf.strip_mesh(0.0, 1.0, 0.0, 0.5, 1, 1)
    mesh = jf.StripMesh(mesh.nodes.at[2].add(jnp.array([0.1, 0.05])), 1, 1)
    geo = jax.tree_util.tree_map(lambda a: a[0], mesh_geometry(mesh))
    dN = geo.gradients(formulation)
    u = jnp.array([[0.0, 0.0], [0.03, 0.004], [0.025, -0.01], [-0.004, -0.012]])  # 3 % stretch, bent
    mat = jf.J2Material(**STEEL)
    init = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (4, *jnp.shape(a))), mat.init_state())

    @jax.jit
    def force(v):
        return element_force(mat, formulation, dN, geo.dN_dX_center, geo.weight, v, init)

    f, (states, _, _) = force(u)
    assert float(jnp.max(states.eqps)) > 1e-3, "the state must be plastic"
    f2, K, _ = jax.jit(element_force_and_tangent, static_argnums=1)(mat, formulation, dN, geo.dN_dX_center,
                                                                    geo.weight, u, init)
    np.testing.assert_allclose(f2, f, rtol=0, atol=1e-10 * float(jnp.max(jnp.abs(f))))
    h = 1e-7
    fd = jnp.stack([(force(u + h * e.reshape(4, 2))[0] - force(u - h * e.reshape(4, 2))[0]).ravel() / (2 * h)
                    for e in jnp.eye(8)], axis=1)
    np.testing.assert_allclose(K, fd, rtol=0, atol=1e-6 * float(jnp.max(jnp.abs(K))))


@pytest.mark.parametrize("formulation", ["fbar", "ans"])
def test_fbar_geometric_term_is_the_hessian_of_the_kinematics(formulation):
    """The closed forms of F-bar's gradient dF_bar/du and of its tangent's geometric term
    (:func:`jaxfric.fem.element._fbar_geometric_term`) equal the forward and the forward-over-reverse
    derivatives of the element's kinematics, on distorted elements under
    large random displacements, and where an inverted point guards the ratio J_0 / J (no term there)."""
    from jaxfric.fem.assembly import mesh_geometry
    from jaxfric.fem.element import _fbar_geometric_term, _fbar_gradient, _fbar_parts, _kinematics

    rng = np.random.default_rng(3)
    mesh = jf.strip_mesh(0.0, 3.0, 0.0, 0.6, 6, 2)
    mesh = jf.StripMesh(mesh.nodes + jnp.asarray(rng.uniform(-0.08, 0.08, mesh.nodes.shape)), 6, 2)
    geo = mesh_geometry(mesh)
    dN, dN0 = geo.gradients(formulation), geo.dN_dX_center
    u = jnp.asarray(rng.normal(scale=0.05, size=mesh.nodes.shape))[mesh.elements]
    u = u.at[0, 1, 0].add(-1.2)                        # element 0: its corner 1 pushed through corner 0
    S = jnp.asarray(rng.normal(scale=100.0, size=(mesh.n_elements, 4, 2, 2)))

    def by_ad(S_e, dN_e, dN0_e, w_e, u_e):
        def term(v):
            return jnp.sum(S_e * _kinematics(formulation, dN_e, dN0_e, w_e, v.reshape(4, 2), jnp.zeros(0))[0])
        return jax.jacfwd(jax.grad(term))(u_e.ravel())

    def closed_form(S_e, dN_e, dN0_e, u_e):
        parts = _fbar_parts(dN_e, dN0_e, u_e)
        return _fbar_geometric_term(S_e, parts, dN_e), parts.Fbar, _fbar_gradient(parts, dN_e)

    def kinematics_by_ad(dN_e, dN0_e, w_e, u_e):
        def Fbar(v):
            return _kinematics(formulation, dN_e, dN0_e, w_e, v.reshape(4, 2), jnp.zeros(0))[0]
        return Fbar(u_e.ravel()), jax.jacfwd(Fbar)(u_e.ravel())

    # Compiled (op by op, the batched derivatives compile hundreds of small programs).
    want = jax.jit(jax.vmap(by_ad))(S, dN, dN0, geo.weight, u)
    got, Fbar, dFbar = jax.jit(jax.vmap(closed_form))(S, dN, dN0, u)
    Fbar_ad, dFbar_ad = jax.jit(jax.vmap(kinematics_by_ad))(dN, dN0, geo.weight, u)
    np.testing.assert_allclose(Fbar, Fbar_ad, rtol=0, atol=1e-14)
    np.testing.assert_allclose(dFbar, dFbar_ad, rtol=0, atol=1e-12 * float(jnp.max(jnp.abs(dFbar_ad))))
    J = jax.vmap(lambda d, v: jnp.linalg.det(jnp.eye(2) + jnp.einsum("ai,gaj->gij", v, d)))(dN, u)
    assert bool(jnp.any(J[0] <= 0)), "element 0 must have an inverted point"
    for e in range(mesh.n_elements):
        np.testing.assert_allclose(got[e], want[e], rtol=0, atol=1e-12 * float(jnp.max(jnp.abs(want[e]))))
