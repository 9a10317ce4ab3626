"""Elements quadratic along the strip (``strip_mesh(..., order=2)``, six nodes, linear through each layer).

A bilinear element's bending strain is constant along it, so a strip whose curvature turns within a few
elements (the Nine's reversals between its rollers) is resolved at first order in the element length. With
a mid-side column of nodes per element the bending strain varies linearly along each element
(:mod:`jaxfric.fem.mesh`, :mod:`jaxfric.fem.element`). These tests check the numbering and the
block-tridiagonal stiffness of two node columns per block (with the padding column), that the tangent is
the force's derivative, elastic bending exact at any aspect ratio with ``anst``, the formulations refused
on this element, and no volumetric locking and no hourglassing.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfric as jf
from jaxfric import scenes
from jaxfric.fem.assembly import internal_force, internal_force_and_tangent, mesh_geometry
from jaxfric.fem.element import enhanced_count
from jaxfric.numerics.results import Result
from models import clamped_pull
from strips import bending_ratio
from test_element_ans import NINE_STEEL, compressed_block
from test_solver import thick_cylinder_ratio


def _virgin_states(mesh, material, formulation, thickness_points=2):
    """The point states before the first step of a model on ``mesh`` (2 x ``thickness_points`` points, alpha by
    the local solve)."""
    phases = (jf.Phase("hold", [jf.DirichletBC(mesh.left)], n_steps=1),)
    model = jf.StripModel(mesh, material, phases, formulation=formulation, enhanced_update="local",
                          thickness_points=thickness_points)
    return jf.initial_state(model).material


def test_numbering_node_sets_and_blocks():
    """2 x 1 elements on [0, 4] x [0, 1]: node columns at x = 0, 1, 2, 3, 4 and the padding column half an
    element further, at 5; elements counter-clockwise through their mid-side nodes; the node sets without
    the padding; blocks of two node columns."""
    mesh = jf.strip_mesh(0.0, 4.0, 0.0, 1.0, 2, 1, order=2)
    assert (mesh.n_columns, mesh.n_nodes, mesh.block_size, mesh.num_blocks) == (5, 12, 8, 3)
    np.testing.assert_array_equal(np.unique(np.asarray(mesh.nodes[:, 0])), [0.0, 1.0, 2.0, 3.0, 4.0, 5.0])
    np.testing.assert_array_equal(mesh.elements, [[0, 2, 4, 5, 3, 1], [4, 6, 8, 9, 7, 5]])
    np.testing.assert_array_equal(mesh.padding, [10, 11])
    np.testing.assert_array_equal(mesh.right, [8, 9])
    np.testing.assert_array_equal(mesh.top, [1, 3, 5, 7, 9])
    assert mesh.node_set("all").size == 10
    blocks, rows = mesh.block_rows(np.array([0, 3, 9, 11]))
    np.testing.assert_array_equal(blocks, [0, 0, 2, 2])
    np.testing.assert_array_equal(rows, [[0, 1], [6, 7], [2, 3], [6, 7]])
    # Shoelace area of every element's six nodes: positive (counter-clockwise) and 2 mm^2.
    x = np.asarray(mesh.nodes)[mesh.elements]
    area = 0.5 * np.sum(x[..., 0] * np.roll(x[..., 1], -1, 1) - np.roll(x[..., 0], -1, 1) * x[..., 1], axis=1)
    np.testing.assert_allclose(area, 2.0)


def test_reduced_rule_leaves_no_zero_energy_mode():
    """2 points along the element (a reduced rule for a quadratic one) and 2 through it: the elastic
    stiffness of three six-node elements in a row has exactly the 3 rigid-body modes as zero eigenvalues,
    with the compatible field and with ``anst``'s condensed mode (measured the same for one element and
    for 4 points through it)."""
    material = jf.J2Material.elastic(200000.0, 0.3)
    mesh = jf.strip_mesh(0.0, 3.0, 0.0, 1.0, 3, 1, order=2)
    geo = mesh_geometry(mesh)
    free = np.setdiff1d(np.arange(mesh.n_dofs), (2 * mesh.padding[:, None] + np.arange(2)).ravel())
    for formulation in ("q4", "anst"):
        states = _virgin_states(mesh, material, formulation)
        K = internal_force_and_tangent(mesh, material, formulation, geo, jnp.zeros((mesh.n_nodes, 2)),
                                       states).tangent.to_dense()
        K = np.asarray(K)[np.ix_(free, free)]
        eig = np.linalg.eigvalsh(0.5 * (K + K.T))
        assert int(np.sum(eig < 1e-8 * eig[-1])) == 3, (formulation, eig[:5])


def test_patch_test_on_distorted_elements_with_the_mode_linear_along():
    """``anst`` on six-node elements carries two thickness parameters per element, constant and linear along
    it (:func:`jaxfric.fem.element._thickness_mode`; the bilinear element one). Taylor's correction makes each
    mode's gradient sum to zero over the rule on any element shape, so a homogeneous deformation of distorted
    elements is reproduced exactly: both parameters zero, no force on the inner nodes, the uniform stress at
    every point."""
    assert enhanced_count("anst", 6) == 2 and enhanced_count("anst", 4) == 1
    material = jf.J2Material.elastic(200000.0, 0.3)
    mesh = jf.strip_mesh(0.0, 3.0, 0.0, 1.0, 3, 2, order=2)
    X = np.asarray(mesh.nodes)
    moved = X + np.stack([0.07 * np.sin(2.1 * X[:, 0]) * X[:, 1] * (1 - X[:, 1]),
                          0.09 * np.cos(1.7 * X[:, 0]) * X[:, 1] * (1 - X[:, 1])], axis=1)
    mesh = eqx.tree_at(lambda m: m.nodes, mesh, jnp.asarray(moved))
    geo = mesh_geometry(mesh, thickness_points=4)
    states = _virgin_states(mesh, material, "anst", thickness_points=4)
    H = np.array([[1e-4, 3e-4], [-2e-4, 5e-4]])
    u = jnp.asarray(moved @ H.T).at[mesh.padding].set(0.0)
    a = internal_force(mesh, material, "anst", geo, u, states)
    assert a.states.enhanced.shape == (mesh.n_elements, 8, 2)
    alpha_scale = np.abs(H).max()
    assert float(jnp.max(jnp.abs(a.states.enhanced))) < 1e-10 * alpha_scale
    boundary = np.unique(np.concatenate([mesh.left, mesh.right, mesh.bottom, mesh.top, mesh.padding]))
    inner = np.setdiff1d(np.arange(mesh.n_nodes), boundary)
    assert inner.size > 0
    f = np.asarray(a.f_int)
    assert np.abs(f[inner]).max() < 1e-10 * np.abs(f).max()


# anst: 14 s of compilation (the derivative through its local solve); the fast suite checks the scatter with
# q4 and the six-node anst force in the elastic bending test.
@pytest.mark.parametrize("formulation", [pytest.param("anst", marks=pytest.mark.slow), "q4"])
def test_tangent_is_the_derivative_of_the_force(formulation):
    """The block-tridiagonal tangent of a 3 x 2 strip, dense, against forward-mode derivatives of the
    internal force, at a displacement that yields part of the strip; the padding column's rows are identity
    rows with no force."""
    mesh = jf.strip_mesh(0.0, 3.0, 0.0, 1.0, 3, 2, order=2)
    geo = mesh_geometry(mesh)
    states = _virgin_states(mesh, NINE_STEEL, formulation)
    X = np.asarray(mesh.nodes)
    u = jnp.asarray(np.stack([0.004 * X[:, 0] * (X[:, 1] - 0.5), -0.002 * X[:, 0] ** 2], axis=1))
    u = u.at[mesh.padding].set(0.0)

    def force(v):
        return internal_force(mesh, NINE_STEEL, formulation, geo, v.reshape(-1, 2), states).f_int.reshape(-1)

    a = internal_force_and_tangent(mesh, NINE_STEEL, formulation, geo, u, states)
    assert float(jnp.max(a.states.eqps)) > 0.0   # plastic somewhere
    dense = np.asarray(jax.jacfwd(force)(u.reshape(-1)))
    np.testing.assert_allclose(np.asarray(a.tangent.to_dense()), dense, atol=1e-6 * np.abs(dense).max())
    pad = (2 * mesh.padding[:, None] + np.arange(2)).ravel()
    np.testing.assert_array_equal(dense[pad][:, pad], np.eye(pad.size))
    assert float(jnp.max(jnp.abs(a.f_int[mesh.padding]))) == 0.0


def test_elastic_bending_is_exact_at_any_aspect_ratio():
    """Elastic pure bending with ``anst``: 2 and 3 layers, elements 1 and 4 times as long as thick, exact
    to 1e-6 (measured 3e-7); the compatible six-node element (``q4``) 1.025 at 3 layers whatever the aspect
    ratio (its thickness strain is constant through each layer), so no shear stiffens it along the strip
    (the bilinear Q4: 1.064 and 1.647, tests/test_solver.py)."""
    ratios = {(ny, a): bending_ratio(ny, "anst", nx=10, length=10 * a / ny, order=2) for ny, a in ((2, 1), (3, 4))}
    assert all(abs(r - 1.0) < 1e-6 for r in ratios.values()), ratios
    compatible = [bending_ratio(3, "q4", nx=10, length=10 * a / 3, order=2) for a in (1, 4)]
    np.testing.assert_allclose(compatible, 1.025, rtol=1e-5)


@pytest.mark.parametrize("formulation", ["fbar", "ans", "eas"])
def test_formulations_refused_on_quadratic_elements(formulation):
    """F-bar's one dilatation per six-node element bends too softly (0.40 of the elastic moment at
    aspect ratio 4), and ``ans`` samples a shear this element does not have: the model names the field."""
    mesh = jf.strip_mesh(0.0, 3.0, 0.0, 1.0, 3, 2, order=2)
    phases = (jf.Phase("hold", [jf.DirichletBC(mesh.left)], n_steps=1),)
    with pytest.raises(ValueError, match="field 'formulation'"):
        jf.StripModel(mesh, NINE_STEEL, phases, formulation=formulation)
    with pytest.raises(ValueError, match="element_order"):
        scenes.make("nine", algorithm="lcp_ssn", overrides={"element": "ans", "element_order": 2})


@pytest.mark.slow  # compiles the cylinder's program
def test_no_volumetric_locking():
    """The thick cylinder of tests/test_solver.py, quadratic along its radius: the limit pressure within
    2 % on the 4 x 8 mesh (measured 1.0014, the bilinear ``anst`` 1.0067)."""
    ratio = thick_cylinder_ratio("anst", order=2)
    assert abs(ratio - 1.0) < 0.02, f"limit pressure ratio {ratio:.4f}"


@pytest.mark.slow  # two runs of the block
def test_strong_compression_without_hourglassing():
    """The 40 % compressed block of tests/test_element_ans.py on 6 x 6 elements, quadratic along x:
    finished without an inverted element, the press force near F-bar's on the bilinear mesh (measured
    0.996 times)."""
    res, mesh = compressed_block("anst", 6, order=2)
    ref, ref_mesh = compressed_block("fbar", 6)
    assert int(res.code) == Result.SUCCESS
    force, force_fbar = (-float(jnp.sum(r.final.f_int[m.top, 1])) for r, m in ((res, mesh), (ref, ref_mesh)))
    assert 0.85 < force / force_fbar < 1.15, f"press force {force:.2f} N/mm, F-bar {force_fbar:.2f}"


def test_run_directory_of_quadratic_elements(tmp_path):
    """A flat-die run on six-node elements (20 x 2, ``anst``, the die pressed with its force, then drawn)
    writes a run directory that passes the output contract (its contact file's elements (n_el, 6),
    numbered through their mid-side nodes). The die's position, the sheet's through-thickness compression
    under it, is that of the bilinear elements (a homogeneous state both represent: measured 4e-5 apart),
    with every surface node under the die in contact, the mid-side ones too."""
    from jaxfric.io import output
    from jaxfric.io.contract import check_run_dir

    last = {}
    for order in (1, 2):
        scene = scenes.make("flat_die", None, "penalty",
                            {"nx": 20, "ny": 2, "element": "anst", "element_order": order})
        result = jf.run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                        snapshot=scene.snapshot, progress=False)
        last[order] = {k: float(result.history[k][-1]) for k in ("tool_position", "n_active")}
    out = tmp_path / "run"
    output.write_run(scene, result, str(out), figures=False)
    assert [p for p in check_run_dir(str(out)) if not p.endswith(".png: missing")] == []
    assert (last[1]["n_active"], last[2]["n_active"]) == (21, 41)
    assert abs(last[2]["tool_position"] / last[1]["tool_position"] - 1.0) < 1e-3, last


@pytest.mark.slow  # compiles simulate and its forward-mode derivative (minutes on the 2-core machine)
def test_path_derivative_matches_central_differences():
    """The load-unload cycle of tests/test_derivatives.py (the right end pulled to 2.5 times the yield
    strain and back; its final reaction is path dependent) on six-node ``anst`` elements: the forward-mode
    derivative of the final reaction along (sigma_y, length) against central differences (the length a
    traced coordinate of the mid-side and padding columns too)."""
    tight = jf.NewtonOptions(rtol=1e-12, atol=1e-10)

    @jax.jit
    def reaction(p):
        model = clamped_pull(length=p[1], sigma_y=p[0], nx=3, ny=2, pull=0.05, n_steps=3, formulation="anst",
                             order=2)
        sim = jf.simulate(model, newton=tight)
        return sim.history.observed["reaction_right"][sim.history.n_rows - 1, 0]

    p0, direction = jnp.array([200.0, 10.0]), jnp.array([1.0, 0.05])
    value, tangent = jax.jvp(reaction, (p0,), (direction,))
    h = 0.02
    fd = (reaction(p0 + h * direction) - reaction(p0 - h * direction)) / (2 * h)
    assert float(value) < -1.0
    np.testing.assert_allclose(float(tangent), float(fd), rtol=1e-5)
