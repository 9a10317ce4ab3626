"""``formulation="anst"``: ``ans``'s assumed natural strains with a condensed through-thickness mode.

A bent strip's thickness strain is linear through its thickness; a bilinear element's is constant
through each element. ``ans`` (F-bar) then drops the bending energy that variation carries and bends
too softly with few layers; ``anst`` carries it in one enhanced mode per element
(:mod:`jaxfric.fem.element`). These tests check what that must give: elastic bending exact whatever
the layers and the aspect ratio, plastic bending converged through the thickness at 2 and 3 layers,
no volumetric locking, no hourglassing under strong compression. The patch test, the tangent and
Newton's rate are with the other formulations (``tests/test_solver.py``, ``tests/test_element_ans.py``).
"""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

import jaxfric as jf
from jaxfric.numerics.results import Result
from strips import bending_ratio, end_moment, pure_bending
from test_element_ans import NINE_STEEL, compressed_block, hourglass_amplitude
from test_solver import thick_cylinder_ratio


def test_elastic_bending_is_exact_at_two_and_three_layers():
    """Elastic pure bending against plane-strain beam theory: 2 elements through the thickness as long
    as thick, and 3 elements 4 times as long as thick: exact to 1e-6 (measured 1e-8); ``ans`` gives 0.8375 and
    0.928 (its constant dilatation per element)."""
    ratios = {(ny, a): bending_ratio(ny, "anst", nx=10, length=10 * a / ny) for ny, a in ((2, 1), (3, 4))}
    assert all(abs(r - 1.0) < 1e-6 for r in ratios.values()), ratios


@pytest.mark.parametrize("points", [2, 3, 4, 6])
def test_gauss_rule_integrates_through_the_thickness_exactly(points):
    """The rule with ``points`` through the thickness integrates eta^p exactly up to p = 2 points - 1 (and
    xi^p up to 3), with weights summing to the parent square's area 4; 2 points is the 2 x 2 rule."""
    from jaxfric.fem.element import GAUSS_POINTS, gauss_rule

    def exact(p):   # the integral of xi^p (or eta^p) over the parent square
        return 2.0 * (1.0 - (-1.0) ** (p + 1)) / (p + 1)

    xy, w = gauss_rule(points)
    assert xy.shape == (2 * points, 2) and w.shape == (2 * points,)
    for p in range(2 * points):
        assert abs(float(np.sum(w * xy[:, 1] ** p)) - exact(p)) < 1e-13, p
    for p in range(4):
        assert abs(float(np.sum(w * xy[:, 0] ** p)) - exact(p)) < 1e-13, p
    if points == 2:
        assert np.array_equal(xy, GAUSS_POINTS)


def test_more_points_through_the_thickness_keep_elastic_bending_exact():
    """Elastic pure bending (3 layers, elements as long as thick) with 4 points through each element's
    thickness: exact, as with 2 (the elastic integrand is polynomial in eta), and the point states
    carry the rule's 8 points per element."""
    E, nu, angle, length = 200000.0, 0.3, 1e-4, 10.0 / 3.0
    model = pure_bending(length, 1.0, nx=10, ny=3, angle=angle, material=jf.J2Material.elastic(E, nu),
                         formulation="anst")
    model = dataclasses.replace(model, thickness_points=4)
    res = jf.run(model, progress=False)
    assert res.final.material.eqps.shape == (30, 8)
    ratio = abs(end_moment(res, model.mesh)) / (E / (1 - nu**2) / 12 * 2 * angle / length)
    assert abs(ratio - 1.0) < 1e-6, ratio


@pytest.mark.slow  # three plastic bending runs, about a minute with compilation
def test_plastic_bending_is_converged_through_the_thickness():
    """Plastic pure bending to 4 % surface strain (the Nine's steel, a 2 x 1 mm strip, 6 elements along,
    10 steps): the moment with 2 and 3 layers within 1 % of 12 layers (measured -0.53 % and +0.75 %;
    ``ans`` -3.6 % and -5.0 % of its own 12-layer moment)."""

    def moment(ny):
        model = pure_bending(2.0, 1.0, nx=6, ny=ny, angle=0.08, material=NINE_STEEL, n_steps=10,
                             formulation="anst")
        return end_moment(jf.run(model, progress=False), model.mesh)

    reference = moment(12)
    errors = {ny: moment(ny) / reference - 1.0 for ny in (2, 3)}
    assert all(abs(e) < 0.01 for e in errors.values()), errors


@pytest.mark.slow  # compiles the element's local solve for another mesh
def test_no_volumetric_locking():
    """The thick cylinder of tests/test_solver.py: the limit pressure within 2 % on the coarse 4 x 8 mesh
    (measured 1.0067, F-bar 1.0066): one dilatation constraint per element, as with F-bar."""
    ratio = thick_cylinder_ratio("anst")
    assert abs(ratio - 1.0) < 0.02, f"limit pressure ratio {ratio:.4f}"


@pytest.mark.slow  # two runs of the block, 26 s
def test_strong_compression_without_hourglassing():
    """The 40 % compressed block of tests/test_element_ans.py on 6 x 6 elements: finished without an
    inverted element, press force and hourglass amplitude near F-bar's (measured 0.977 and 1.23; ``ans``
    0.92 and 1.17), where the four-mode enhanced element inverts an element at 20 %."""
    res, mesh = compressed_block("anst", 6)
    ref, _ = compressed_block("fbar", 6)
    assert int(res.code) == Result.SUCCESS
    force, force_fbar = (-float(jnp.sum(r.final.f_int[mesh.top, 1])) for r in (res, ref))
    assert 0.85 < force / force_fbar < 1.15, f"press force {force:.2f} N/mm, F-bar {force_fbar:.2f}"
    ratio = hourglass_amplitude(res, mesh) / hourglass_amplitude(ref, mesh)
    assert ratio < 1.5, f"hourglass amplitude {ratio:.3f} times F-bar's"
