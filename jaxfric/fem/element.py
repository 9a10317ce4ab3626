"""Plane-strain quadrilaterals: F-bar against volumetric locking, assumed natural strain against parasitic shear,
and elements quadratic along the strip (below).

Formulation (de Souza Neto, Peric, Dutko, Owen, Int. J. Solids Struct. 33, 1996; de Souza Neto et al.,
*Computational Methods for Plasticity*, 2008, sec. 15.2). At each of the 2x2 Gauss points the in-plane
deformation gradient is replaced by

    F_bar = (J_0 / J)^(1/2) F,        F_bar_zz = 1,

with J = det F at the point and J_0 = det F at the element centroid. The volume change is therefore
constant over the element (one volumetric constraint per element, as in a Q1/P0 mixed element), which
removes the locking of full-integration Q4 under isochoric plastic flow, while the deviatoric
deformation keeps its full 2x2 integration (no hourglass modes). F-bar is chosen over a mixed Q1/P0
element because it keeps the displacement-only data structure (same unknowns, same block-tridiagonal
stiffness) and works with any material law written as ``update(F, state)``.

Internal force: the virtual work ``sum_gp w_gp P_bar : dF_bar/du`` with P_bar = tau F_bar^-T (the forces
alone, :func:`element_force`, by pulling P_bar back through the map u -> F_bar with a JAX VJP). The element
tangent is the exact derivative of that force (:func:`element_force_and_tangent`), with the material's
part the point law's consistent tangent (:func:`~jaxfric.fem.material.piola_and_tangent`: the radial
return's in closed form, equal to the forward-mode derivative of the return mapping to round-off).

``formulation="ans"``: F-bar on assumed natural strains through the thickness. A bilinear element
x(xi, eta) = x_0 + a_1 xi + a_2 eta + h xi eta bent along xi (the strip's length) has
dx/deta = a_2 + h xi: its through-thickness fibres turn along the element, a shear that a bent strip
does not have (Q4's parasitic shear, about kappa dx / 2 at the element's ends). In plastic bending that
shear yields, so the element dissipates more than the strip it models by an amount first order in the
element length dx. Here dx/deta at each Gauss point is sampled at the element's centre line xi = 0,
as the assumed-natural-strain elements of shells do with their transverse shear (Dvorkin & Bathe,
Eng. Comput. 1, 1984), in the deformed and the reference configuration alike:

    F_ans = [dx/dxi (g), dx/deta (0)] [dX/dxi (g), dX/deta (0)]^-1,

which is I + sum_a u_a (x) B_a with constant gradients B_a (``ElementGeometry.dN_dX_assumed``), so a
homogeneous deformation stays exact (patch test) and the element stays displacement-only; the
covariant components C_xixi, C_etaeta and C_xieta at the points are those of the bilinear field sampled
on the centre line, so the element is objective. The hourglass vector h still strains it at the two
Gauss rows (bending through C_xixi, the other component through C_xieta), so no zero-energy mode
appears. F-bar is then applied as above (one volumetric constraint per element). The second parent axis
eta must be the strip's thickness direction, as in :func:`jaxfric.fem.mesh.strip_mesh`. Its cost is
F-bar's (the same operations on other constant gradients). Measured (``tests/test_element_ans.py``,
``experiments/nine_error_sources.py``, docs/results.md): elastic bending independent of the aspect ratio
(F-bar's moment grows 1.6 times from aspect ratio 1 to 4); plastic bending at aspect ratio 1 within
0.01 % of a 4 times finer mesh along the strip (F-bar 3.7 %); the Nine's steady force on its 300 x 3
mesh 1.4 % (``mu000``) and 3.5 % (``mu017``) above the mesh limit, against 6.9 % and 9.3 % with F-bar.
It keeps F-bar's through-thickness error (below), which no longer cancels part of the parasitic shear's:
with 2 layers it bends too softly (the blankholder's spec mesh: 149.03 N/mm against 166.14 with 4
layers, where F-bar gives 164.61). So ``ans`` is the default of the scenes whose strips have 3 layers or
more (Nine, bead), F-bar that of the others and of :class:`~jaxfric.loadpath.model.StripModel`, which
knows nothing of the mesh's orientation.

``formulation="anst"``: ``ans``'s assumed natural strains without F-bar, plus one enhanced mode that
lets the thickness strain vary through each element. A bent strip's thickness strain is linear
through its thickness (Poisson's effect in the elastic core, the plastic flow's incompressibility in the
yielded fibres); a bilinear element's is constant through each element, so with few layers the element
either resists that variation (plain Q4: too stiff, and volumetric locking in plastic flow) or, with
F-bar, makes the dilatation constant per element and loses the bending energy it carries (``ans``: 7 %
soft in elastic bending at 3 layers, 16 % at 2). The mode is the incompatible displacement
(1 - eta^2) alpha dx/deta(0), a stretch of the element's current thickness fibre quadratic through its
thickness, with Taylor's correction so that the patch test holds; alpha is condensed in the element
exactly as ``eas``'s parameters (below). Because the mode stretches the fibre only and follows it
through rotations, it cannot pair with the hourglass vector into a zero-energy mode, as ``eas``'s
in-plane mode of the same fibre does once the shear is sampled on the centre line; with one mode per
element the dilatation carries one constraint per element, as with F-bar, so plastic flow does not
lock. Measured (``tests/test_element_anst.py``): elastic
pure bending exact to 1e-8 at 2, 3 and 6 layers; plastic bending to 4 % surface strain within 0.5 %
and 0.75 % of 12 layers at 2 and 3 layers (``ans`` -3.6 % and -5.0 %); the thick cylinder's limit
pressure within 0.7 %; the 40 % compressed block finished without an inverted element. On the scenes
(docs/results.md, the through-thickness mode) it removes the layer error: the blankholder moves 0.5 %
from 2 to 4 layers (``ans`` 11 %, F-bar 8 %); on the Nine 12 layers give 2.9 % more than 3 (mu000),
which is the quadrature through the thickness of its reversed bends (below: 4 points per layer).
Within a Newton loop alpha is carried with the iterate (``enhanced_update="iterate"``, the default; the
enhanced-strain update of Simo and Armero, Int. J. Numer. Meth. Engng 33, 1992): each linearisation of
the element's own equation R_a(u, alpha) = 0 predicts the next iterate's alpha from its displacements
(:func:`element_force_and_tangent`'s ``predictor``, kept in the point states from one step to the
next), so an element evaluation is one material pass, and the loop is Newton's on (u, alpha), alpha
condensed out of each direction. The other way, ``enhanced_update="local"``, condenses alpha by a local
Newton in every evaluation, where a batch of elements iterates as long as its slowest one. Both converge
to the same answer (to the Newton tolerance); derivatives condense exactly in both. Measured on the Nine
(mu017, 300 x 3, U_draw 3 mm; docs/results.md, the through-thickness mode): the carried alpha costs
about what ``ans`` costs per Newton iteration, with 2 and with 4 points through each element, for
4 % fewer iterations than ``ans`` and 2 to 3 % more than the local solve, which costs 1.7 to 2.3 times
(2 points) and 2.5 times (4 points) as much per iteration.

Through its thickness each element is integrated by ``thickness_points`` Gauss-Legendre points
(:func:`gauss_rule`: 2 along xi times that many along eta; :class:`~jaxfric.loadpath.model.StripModel`'s
field and the scenes' of that name, 2 by default: the 2 x 2 rule). A strip bent plastically carries
a stress that jumps across its neutral axis, and the plastic work and stretch of bending under tension
follow from integrating it; with 2 points per layer and few layers that integral is coarse. Measured
on the Nine without friction (``experiments/nine_plastic_work.py``, docs/results.md, where the layers'
error comes from): ``anst`` on 3 layers gives a steady force 2.2 % below 12 layers with 2 points and
0.5 % below with 4, the plastic work of the two reversed bends (A to B, B to C) being the part that
moves. ``ans`` gains 1.0 % only: its error with few layers is its constant dilatation per element, which
more points do not change (on 3 layers it stretches the strip 4.4 % over the tools, 12 layers 8.1 %).

``formulation="q4"`` (plain displacement Q4, F_bar = F) is kept for the elastic verification checks.

**Elements quadratic along the strip** (six nodes; :func:`jaxfric.fem.mesh.strip_mesh` with ``order=2``).
The shape functions are the quadratic Lagrange polynomials on xi = -1, 0, 1 times the linear ones on
eta = -1, 1, integrated by the same rule (2 points along xi, ``thickness_points`` along eta: along xi
the rule is reduced, which a quadratic element takes without a zero-energy mode, checked on its
stiffness in ``tests/test_element_quadratic.py``). Each layer's displacement along the strip is
quadratic, so the bending strain varies linearly along the element where a bilinear element's is
constant, and the deflection's quadratic part is in the field, so bending turns no fibre into a
parasitic shear (``ans``' sampling has nothing to remove: its gradients are the compatible ones here).
``anst``'s thickness mode (the same construction, its centre and fibre from the six-node field) varies
linearly along the element (two parameters, :func:`_thickness_mode`), as the bending strain it goes with
does, and makes elastic pure bending exact at 2 and 3 layers and aspect ratios 1 to 4. With one parameter,
constant along the element as on the bilinear one, the element converged at second order along the strip
without friction but not with it: on the Nine with friction the constant mode held the thickness strain of
the reversed bends, where the curvature changes sign within a few elements (docs/results.md, elements
quadratic along the strip). F-bar is not offered on this
element: one dilatation per six-node element leaves a softness that grows with the aspect ratio
(elastic pure bending at 3 layers: 0.85 of the beam moment at aspect ratio 1, 0.40 at 4), so
:data:`QUADRATIC_FORMULATIONS` are ``anst`` and the compatible ``q4``.

``formulation="eas"``: the enhanced-assumed-strain element Q1/E4 at finite strain (Simo & Armero,
Int. J. Numer. Meth. Engng 33, 1992). The compatible gradient gets four enhanced parameters alpha per
element, those of the incompatible modes (1 - xi^2), (1 - eta^2) of each displacement component,

    F = I + Grad u + (j_0 / j) A(xi, eta; alpha) J_0^-1,    A = [[xi a_1, eta a_2], [xi a_3, eta a_4]],

with J_0 = dX/dxi at the centroid (Taylor's correction: the enhancement integrates to zero over the
element, so the patch test holds). alpha is condensed inside the element: it solves
``sum_g w_g P_g : dF_g/dalpha = 0`` (with the Newton iterate as ``anst``'s, above, or by a local Newton
from the last converged step's alpha, differentiable by the implicit function theorem through
``jax.lax.custom_root``), and the tangent is the condensed ``K_uu - K_ua K_aa^-1 K_au``. The modes carry
the quadratic through-thickness Poisson displacement of a bent strip that F-bar and Q4 miss (pure
bending is exact with three elements through the thickness, where F-bar is 7 % too soft and Q4 2.6 % too
stiff), and relax the incompressibility constraint as well. It is not the default: the finite-strain
enhanced elements are known to develop hourglass modes under strong compression, which the clamped
sheets of the benchmarks see (it inverts an element
at 20 % compression of the block of ``tests/test_element_ans.py``, and during the Nine's clamping).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..numerics.tensor import det2, inv2
from .material import piola, piola_and_tangent

__all__ = ["FORMULATIONS", "QUADRATIC_FORMULATIONS", "ElementGeometry", "gauss_rule", "element_geometry",
           "deformation_gradients", "initial_point_state", "element_force", "element_force_and_tangent",
           "enhanced_predictor", "enhanced_count", "ENHANCED_UPDATES"]

FORMULATIONS = ("fbar", "ans", "anst", "q4", "eas")
QUADRATIC_FORMULATIONS = ("anst", "q4")   # those of the elements quadratic along the strip (module docstring)
ENHANCED_UPDATES = ("iterate", "local")   # alpha with the Newton iterate, or by a local solve per evaluation
EAS_MAX_ITER = 25      # local Newton iterations for the enhanced parameters (while_loop bound)
EAS_RTOL = 1e-12       # relative to sum_g w_g |P_g| |dF_g/dalpha|
EAS_STEP_TOL = 1e-12   # a Newton step of the enhanced parameters this small ends the local solve

_G = 1.0 / np.sqrt(3.0)
# Corner coordinates of the parent square, counter-clockwise from (-1, -1).
_XI = np.array([-1.0, 1.0, 1.0, -1.0])
_ETA = np.array([-1.0, -1.0, 1.0, 1.0])
GAUSS_POINTS = np.array([[-_G, -_G], [_G, -_G], [_G, _G], [-_G, _G]])
GAUSS_WEIGHTS = np.ones(4)


def _parent_gradients(xi: float, eta: float, n_nodes: int = 4) -> np.ndarray:
    """dN_a/d(xi, eta) at one parent point, (n_nodes, 2): the 4 bilinear shape functions, or the 6 of the
    element quadratic along xi and linear along eta (nodes at xi = -1, 0, 1 on eta = -1, then back at
    xi = 1, 0, -1 on eta = 1: :attr:`jaxfric.fem.mesh.StripMesh.elements`)."""
    if n_nodes == 4:
        return 0.25 * np.stack([_XI * (1.0 + _ETA * eta), _ETA * (1.0 + _XI * xi)], axis=1)
    # Lagrange polynomials on xi = -1, 0, 1 and their derivatives; linear ones along eta.
    lag = np.array([0.5 * xi * (xi - 1.0), 1.0 - xi * xi, 0.5 * xi * (xi + 1.0)])
    dlag = np.array([xi - 0.5, -2.0 * xi, xi + 0.5])
    along, side = np.array([0, 1, 2, 2, 1, 0]), np.array([-1.0, -1.0, -1.0, 1.0, 1.0, 1.0])
    lin = 0.5 * (1.0 + side * eta)
    return np.stack([dlag[along] * lin, lag[along] * 0.5 * side], axis=1)


@functools.cache
def _dn_center(n_nodes: int) -> np.ndarray:
    """dN/dxi at the element's centre, (n_nodes, 2)."""
    return _parent_gradients(0.0, 0.0, n_nodes)


@functools.cache
def gauss_rule(thickness_points: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """The element's quadrature: parent points (n, 2) and weights (n,), 2 Gauss points along xi (the
    strip's length) times ``thickness_points`` Gauss-Legendre points along eta (its thickness). With 2
    it is the 2 x 2 rule, :data:`GAUSS_POINTS` (counter-clockwise); with more, the rows of eta in
    ascending order. A rule's size n = 2 ``thickness_points`` is the leading axis of the point arrays
    (:class:`ElementGeometry`, the material states), from which the element functions recover it."""
    if thickness_points == 2:
        return GAUSS_POINTS, GAUSS_WEIGHTS
    eta, w = np.polynomial.legendre.leggauss(int(thickness_points))
    points = np.array([[xi, e] for e in eta for xi in (-_G, _G)])
    return points, np.repeat(w, 2)


@functools.cache
def _parent_tables(n_points: int, n_nodes: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For the rule of ``n_points`` points: its weights (n,), the parent gradients at its points
    (n, n_nodes, 2), the assumed ones (d/dxi at the point, d/deta at the centre line xi = 0), and the
    Q1/E4 modes A_ik = alpha_(2i+k) (xi, eta)_k at its points, (n, 2, 2, 4)."""
    points, weights = gauss_rule(n_points // 2)
    dn = np.stack([_parent_gradients(p[0], p[1], n_nodes) for p in points])
    # Quadratic along xi (6 nodes): no parasitic shear in bending, nothing to sample (module docstring).
    assumed = dn if n_nodes == 6 else np.stack(
        [np.stack([dn[g, :, 0], _parent_gradients(0.0, p[1], n_nodes)[:, 1]], axis=1) for g, p in enumerate(points)])
    modes = np.zeros((len(points), 2, 2, 4))
    for i in range(2):
        for k in range(2):
            modes[:, i, k, 2 * i + k] = points[:, k]
    return weights, dn, assumed, modes


class ElementGeometry(eqx.Module):
    """Reference-configuration data of every element, computed once per simulation (gp: the points of
    the element's rule, :func:`gauss_rule`; 4 with the default 2 x 2).

    Attributes:
        dN_dX: (n_el, gp, 4 nodes, 2) shape-function gradients at the Gauss points (1/mm).
        dN_dX_center: (n_el, 4 nodes, 2) shape-function gradients at the centroid (1/mm).
        dN_dX_assumed: (n_el, gp, 4 nodes, 2) the gradients of ``formulation="ans"`` at the Gauss
            points: the eta-derivatives taken at the element's centre line xi = 0 (1/mm).
        weight: (n_el, gp) Gauss weight times det(dX/dxi): reference area per point (mm^2,
            per unit out-of-plane width).
    """

    dN_dX: jax.Array
    dN_dX_center: jax.Array
    dN_dX_assumed: jax.Array
    weight: jax.Array

    def gradients(self, formulation: str) -> jax.Array:
        """The Gauss-point gradients ``formulation`` builds its deformation gradients from."""
        return self.dN_dX_assumed if formulation in ("ans", "anst") else self.dN_dX


def element_geometry(X_el: jax.Array, thickness_points: int = 2) -> ElementGeometry:
    """Element geometry from the reference node coordinates ``X_el`` (n_el, 4 or 6, 2), in mm, for the rule
    of :func:`gauss_rule` with ``thickness_points`` points through the thickness."""
    n_nodes = X_el.shape[1]
    weights, dn_gauss, dn_assumed, _ = _parent_tables(2 * int(thickness_points), n_nodes)

    def gradients(dN_dxi, X):
        jac = X.T @ dN_dxi  # dX/dxi, (2, 2)
        return dN_dxi @ inv2(jac), det2(jac)

    def one(X):
        dN, det = jax.vmap(gradients, (0, None))(jnp.asarray(dn_gauss), X)
        dN0, _ = gradients(jnp.asarray(_dn_center(n_nodes)), X)
        dN_ans, _ = jax.vmap(gradients, (0, None))(jnp.asarray(dn_assumed), X)
        return dN, dN0, dN_ans, det * weights

    dN, dN0, dN_ans, w = jax.vmap(one)(X_el)
    return ElementGeometry(dN_dX=dN, dN_dX_center=dN0, dN_dX_assumed=dN_ans, weight=w)


def deformation_gradients(dN_dX, dN_dX_center, u_e, formulation: str):
    """In-plane deformation gradients at the Gauss points, (gp, 2, 2), and det F there and at the centroid.

    F = I + sum_a u_a (x) dN_a/dX (``dN_dX``: :meth:`ElementGeometry.gradients` of the formulation). With
    ``formulation="fbar"`` or ``"ans"`` the returned gradients are F_bar = (J_0/J)^(1/2) F. Also returns
    the smallest of det F at the Gauss points and the centroid, which is <= 0 for an inverted element.
    """
    F, F0, J, J0 = _compatible(dN_dX, dN_dX_center, u_e)
    det_min = jnp.minimum(jnp.min(J), J0)
    if formulation in ("q4", "eas", "anst"):  # eas, anst: the compatible part; see _kinematics
        return F, det_min
    return _fbar_ratio(J, J0)[3][:, None, None] * F, det_min


def _compatible(dN_dX, dN_dX_center, u_e):
    """F = I + sum_a u_a (x) dN_a at the points (g, 2, 2) and at the centroid (2, 2), and their
    determinants."""
    eye = jnp.eye(2)
    F = eye + jnp.einsum("ai,gaj->gij", u_e, dN_dX)
    F0 = eye + u_e.T @ dN_dX_center
    return F, F0, det2(F), det2(F0)


def _fbar_ratio(J, J0):
    """F-bar's factor r = (J_0 / J)^(1/2) per point, guarded so that an inverted element gives a finite
    (flagged) value, not NaN: ``(ok, J_safe, J0_safe, r)`` with r = 1 where not ``ok`` (J or J_0 <= 0) and
    the determinants replaced by 1 where they cannot divide."""
    ok = (J > 0) & (J0 > 0)
    J_safe, J0_safe = jnp.where(ok, J, 1.0), jnp.where(J0 > 0, J0, 1.0)
    return ok, J_safe, J0_safe, jnp.where(ok, jnp.sqrt(J0_safe / J_safe), 1.0)


def _centroid_jacobian_inverse(dN_dX_center) -> jax.Array:
    """J_0^-1 = dxi/dX at the centroid, (2, 2), recovered from dN/dX = (dN/dxi) J_0^-1 there (dN/dxi at the
    centroid has orthogonal columns: their squared norms 1/4, and 1/4 and 1/2 for the quadratic element,
    so the left inverse below is exact in floating point)."""
    dn = _dn_center(dN_dX_center.shape[0])
    return jnp.asarray(np.linalg.inv(dn.T @ dn) @ dn.T) @ dN_dX_center


def _enhanced_basis(dN_dX_center, weight) -> jax.Array:
    """dF_g/dalpha of the Q1/E4 enhancement, (gp, 2, 2, 4): (j_0 / j_g) A_g J_0^-1, with
    j_g = weight_g / (the rule's weight at g)."""
    rule_weights, _, _, modes = _parent_tables(weight.shape[0])
    J0_inv = _centroid_jacobian_inverse(dN_dX_center)
    ratio = jnp.asarray(rule_weights) / (det2(J0_inv) * weight)
    return ratio[:, None, None, None] * jnp.einsum("gikm,kj->gijm", jnp.asarray(modes), J0_inv)


def _thickness_mode(dN_dX_center, weight, u_e) -> jax.Array:
    """dF_g/dalpha of the ``anst`` enhancement, (gp, 2, 2, m): the incompatible displacement
    (1 - eta^2) alpha dx/deta(0) (a stretch of the element's current thickness fibre, quadratic through
    its thickness), whose gradient with Taylor's correction is

        eta_g (j_0 / j_g) F_0 (J_0 e_eta) (x) (e_eta J_0^-1),

    F_0 = I + Grad u at the centroid. It follows the fibre through rigid rotations (objective), and it
    stretches that fibre only, so it cannot pair with the hourglass vector into a zero-energy mode as the
    in-plane incompatible modes of a fibre would. On the element quadratic along the strip (six nodes)
    alpha varies linearly along it, alpha_0 + xi alpha_1 (m = 2; the second mode's gradient is the first's
    times xi_g, whose weighted sum over the rule vanishes too, so the patch test holds): its bending strain
    varies linearly along the element, and so must the thickness strain that goes with it (module
    docstring). The bilinear element's bending strain is constant along it, and so is its mode (m = 1)."""
    J0_inv = _centroid_jacobian_inverse(dN_dX_center)
    projector = jnp.outer(inv2(J0_inv)[:, 1], J0_inv[1, :])
    F0 = jnp.eye(2) + u_e.T @ dN_dX_center
    points, rule_weights = gauss_rule(weight.shape[0] // 2)
    ratio = jnp.asarray(points[:, 1] * rule_weights) / (det2(J0_inv) * weight)
    mode = ratio[:, None, None] * (F0 @ projector)[None, :, :]
    if enhanced_count("anst", u_e.shape[0]) == 1:
        return mode[..., None]
    return jnp.stack([mode, mode * jnp.asarray(points[:, 0])[:, None, None]], axis=-1)


def enhanced_count(formulation: str, n_nodes: int = 4) -> int:
    """Enhanced parameters per element of ``formulation`` on elements of ``n_nodes`` nodes: ``eas`` 4,
    ``anst`` 1 (bilinear) or 2 (quadratic along the strip: :func:`_thickness_mode`), 0 for the others."""
    return {"eas": 4, "anst": 1 if n_nodes == 4 else 2}.get(formulation, 0)


def initial_point_state(material, formulation: str, enhanced_update: str = "local", n_nodes: int = 4):
    """A virgin state of one point of ``material`` with room for the formulation's enhanced parameters
    (zero: the undeformed element of ``n_nodes`` nodes): alpha (n,) for the local solve, the predictor
    (n, 1 + 2 n_nodes) of :func:`element_force_and_tangent` for ``enhanced_update="iterate"``."""
    n = enhanced_count(formulation, n_nodes)
    state = material.init_state()
    if not n:
        return state
    kept = jnp.zeros((n, 1 + 2 * n_nodes) if enhanced_update == "iterate" else (n,), jnp.float64)
    return eqx.tree_at(lambda s: s.enhanced, state, kept, is_leaf=lambda x: x is None)


def _kept(states, n: int):
    """The enhanced data the point states keep: ("alpha", (n,)), ("predictor", (n, 1 + element dofs)) or
    (None, None)."""
    kept = getattr(states, "enhanced", None)
    if kept is None or n == 0:
        return None, None
    if kept.shape[-1:] == (n,):
        return "alpha", kept[0]
    if kept.ndim >= 3 and kept.shape[-2] == n:
        return "predictor", kept[0]
    return None, None


def _start(states, n: int, u_e, dtype):
    """The enhanced parameters the point states give at ``u_e``: the kept alpha, or the kept predictor's."""
    form, kept = _kept(states, n)
    if form == "alpha":
        return kept
    if form == "predictor":
        return kept[:, 0] + kept[:, 1:] @ u_e.ravel()
    return jnp.zeros(n, dtype)


def _with_enhanced(states, alpha, predictor=None):
    """``states`` (batched over the element's points) keeping ``alpha`` in their form: alpha itself, or
    a predictor (``predictor``, or alpha held: :func:`enhanced_predictor`)."""
    if alpha.size == 0:
        return states
    form, kept = _kept(states, alpha.size)
    if form == "predictor":
        value = enhanced_predictor(alpha, n_dofs=kept.shape[-1] - 1) if predictor is None else predictor
    else:
        value = alpha
    n_points = jax.tree_util.tree_leaves(states)[0].shape[0]
    return eqx.tree_at(lambda s: s.enhanced, states, jnp.broadcast_to(value, (n_points,) + value.shape),
                       is_leaf=lambda x: x is None)


def _kinematics(formulation, dN_dX, dN_dX_center, weight, u_e, alpha):
    """Gradients (gp, 2, 2) at the Gauss points for displacements ``u_e`` (4, 2) and enhanced parameters
    ``alpha`` (:func:`enhanced_count` entries), and the smallest det F of the compatible part (see
    :func:`deformation_gradients`) and of the enhanced gradients."""
    F, det_min = deformation_gradients(dN_dX, dN_dX_center, u_e, formulation)
    if formulation == "eas":
        F = F + _enhanced_basis(dN_dX_center, weight) @ alpha
    elif formulation == "anst":
        F = F + _thickness_mode(dN_dX_center, weight, u_e) @ alpha
    if alpha.size:
        det_min = jnp.minimum(det_min, jnp.min(det2(F)))
    return F, det_min


_EPS2 = np.array([[0.0, 1.0], [-1.0, 0.0]])  # the 2D permutation symbol: det F = 1/2 eps_ik eps_jl F_ij F_kl


def _det_derivatives(F, dN):
    """Gradient (..., 2 n) of J = det F over the element dofs (node-major, n nodes) for
    F = I + sum_a u_a (x) dN_a, linear in the dofs: dJ/du_bk = sum_j cof(F)_kj dN_bj; and the (..., n, n)
    matrix M = dN eps dN^T of its constant Hessian d2J/du_bk du_cl = M_bc eps_kl (eps: the 2D permutation
    symbol)."""
    cof = jnp.einsum("ki,...ij,jl->...kl", _EPS2, F, _EPS2.T)  # J F^-T
    grad = jnp.einsum("...bj,...kj->...bk", dN, cof)
    return grad.reshape(*grad.shape[:-2], -1), jnp.einsum("...bj,jn,...cn->...bc", dN, _EPS2, dN)


class _FbarParts(NamedTuple):
    """F-bar's kinematics at the Gauss points of one element with their derivatives over the dofs."""

    F: jax.Array        # (g, 2, 2) compatible gradients, linear in the dofs
    Fbar: jax.Array     # (g, 2, 2) r F
    r: jax.Array        # (g,) (J_0 / J)^(1/2), 1 where guarded
    dl: jax.Array       # (g, 2n) d ln r over the element's 2n dofs (n nodes), 0 where guarded
    ok: jax.Array       # (g,) not guarded (J > 0 and J_0 > 0)
    J: jax.Array        # (g,) det F (1 where guarded)
    dJ: jax.Array       # (g, 2n)
    M: jax.Array        # (g, n, n) of d2J (:func:`_det_derivatives`)
    J0: jax.Array       # () det F at the centroid (1 where not positive)
    dJ0: jax.Array      # (2n,)
    M0: jax.Array       # (n, n)
    det_min: jax.Array  # () smallest det F at the points and the centroid


def _fbar_parts(dN_dX, dN_dX_center, u_e) -> _FbarParts:
    """:func:`deformation_gradients` of ``fbar``/``ans`` with the determinants' derivatives: F is linear in
    the dofs, F_bar = r F with r = (J_0 / J)^(1/2) and ln r = (ln J_0 - ln J) / 2."""
    F, F0, J, J0 = _compatible(dN_dX, dN_dX_center, u_e)
    ok, J_safe, J0_safe, r = _fbar_ratio(J, J0)
    dJ, M = _det_derivatives(F, dN_dX)                    # (g, 2n), (g, n, n)
    dJ0, M0 = _det_derivatives(F0, dN_dX_center)          # (2n,), (n, n)
    dl = jnp.where(ok[:, None], 0.5 * (dJ0[None, :] / J0_safe - dJ / J_safe[:, None]), 0.0)
    return _FbarParts(F, r[:, None, None] * F, r, dl, ok, J_safe, dJ, M, J0_safe, dJ0, M0,
                      jnp.minimum(jnp.min(J), J0))


def _fbar_gradient(parts: _FbarParts, dN_dX) -> jax.Array:
    """dF_bar / du, (g, 2, 2, 2n): r dF/du + F (x) r dl, with dF_ij/du_bk = delta_ik dN_bj."""
    dF = jnp.einsum("ik,gbj->gijbk", jnp.eye(2), dN_dX).reshape(*parts.F.shape, -1)
    return parts.r[:, None, None, None] * dF + parts.Fbar[..., None] * parts.dl[:, None, None, :]


def _fbar_geometric_term(S, parts: _FbarParts, dN_dX) -> jax.Array:
    """The (2n, 2n) Hessian over the element dofs of sum_g S_g : F_bar_g(u) with the S_g held fixed: the
    geometric part of the F-bar tangent (``fbar``, ``ans``).

    With s_g = S_g : F_g (linear, gradient a_g), dr = r dl and d2r = r (dl (x) dl + d2l) for
    l = ln r = (ln J_0 - ln J_g) / 2, the Hessian is

        sum_g c_g (dl_g (x) dl_g + d2l_g) + r_g (dl_g (x) a_g + a_g (x) dl_g),    c_g = s_g r_g,

    with d2l_g = (d2J_0 / J_0 - dJ_0 (x) dJ_0 / J_0^2 - d2J_g / J_g + dJ_g (x) dJ_g / J_g^2) / 2 from the
    determinants' derivatives (:func:`_det_derivatives`), summed over the points before the outer products
    are formed. A point where the ratio is guarded (an inverted element) has F_bar = F, linear, and no such
    term. The same matrix as the forward-over-reverse derivative of the F-bar kinematics
    (``tests/test_element_ans.py``) at less cost."""
    r = jnp.where(parts.ok, parts.r, 0.0)
    dl, dJ, J, J0 = parts.dl, parts.dJ, parts.J, parts.J0
    c = jnp.einsum("gij,gij->g", S, parts.F) * r
    ra = r[:, None] * jnp.einsum("gkj,gbj->gbk", S, dN_dX).reshape(S.shape[0], -1)
    c0 = jnp.sum(c) / J0
    M_sum = jnp.kron(c0 * parts.M0 - jnp.einsum("g,gbc->bc", c / J, parts.M), _EPS2)
    return (dl.T @ (c[:, None] * dl) + dl.T @ ra + ra.T @ dl
            + 0.5 * (M_sum - c0 / J0 * jnp.outer(parts.dJ0, parts.dJ0) + dJ.T @ ((c / J ** 2)[:, None] * dJ)))


def _value_and_jacfwd(fn, x):
    """``fn(x) = (value, aux)``: (value, aux, d value / dx) from one forward-mode pass, the value riding
    along as auxiliary output instead of a second evaluation."""

    def with_value(y):
        value, aux = fn(y)
        return value, (value, aux)

    jac, (value, aux) = jax.jacfwd(with_value, has_aux=True)(x)
    return value, aux, jac


def _condensed(material, formulation, dN_dX, dN_dX_center, weight, u_e, states):
    """The enhanced parameters at displacements ``u_e``: alpha solves R(alpha) = sum_g w_g P_g : G_g = 0,
    G = dF/dalpha (F is affine in alpha); a local Newton from the last converged step's alpha (kept in
    the point states; zero when they hold none), differentiable by the implicit function
    theorem (``jax.lax.custom_root``)."""
    n = enhanced_count(formulation, u_e.shape[0])
    if n == 0:
        return jnp.zeros(0, u_e.dtype)
    F_c, _, G = _value_and_jacfwd(lambda a: _kinematics(formulation, dN_dX, dN_dX_center, weight, u_e, a),
                                  jnp.zeros(n, u_e.dtype))
    point = jax.vmap(lambda F, state: piola(material, F, state))
    norm_g = jnp.sqrt(jnp.sum(G**2, axis=(1, 2, 3)))

    def residual_and_tolerance(alpha):
        P = point(F_c + G @ alpha, states)[0]
        tol = EAS_RTOL * jnp.sum(weight * jnp.linalg.norm(P, axis=(1, 2)) * norm_g) + 1e-300
        return jnp.einsum("g,gij,gijm->m", weight, P, G), tol

    def residual(alpha):
        return residual_and_tolerance(alpha)[0]

    def linearized(alpha):
        """(dR/dalpha, R, tolerance) at alpha from one forward pass of the material."""
        r, tol, jac = _value_and_jacfwd(residual_and_tolerance, alpha)
        return jac, r, tol

    def newton(fn, alpha0):
        """Newton with backtracking on |R| (halving, at most 10 times): from alpha = 0 the first full
        steps can overshoot where the points pass from elastic to plastic. Each trial point is evaluated
        with its derivative, which the next iteration's step uses. It stops when |R| is within
        EAS_RTOL of its scale, or when the step falls below EAS_STEP_TOL or no halving decreases |R|:
        the return mapping's own tolerance can set |R|'s rounding floor above EAS_RTOL, and an element
        left iterating there holds its whole batch of elements in the loop. (``fn`` is ``residual``.)"""
        del fn

        def size(r):
            return jnp.max(jnp.abs(r))

        def body(c):
            k, alpha, jac, r, _ = c
            step = -jnp.linalg.solve(jac, r)

            def shorter(d):
                t = 0.5 * d[0]
                a = alpha + t * step
                return (t, a, *linearized(a))

            tiny = jnp.max(jnp.abs(step)) <= EAS_STEP_TOL

            def too_long(d):
                t, r_new = d[0], d[3]
                return (t > 1e-3) & ~tiny & ~(size(r_new) < (1.0 - 1e-4 * t) * size(r))

            t, alpha, jac, r_new, tol = jax.lax.while_loop(too_long, shorter,
                                                           (1.0, alpha + step, *linearized(alpha + step)))
            stalled = tiny | ~(size(r_new) < size(r))
            return k + 1, alpha, jac, r_new, (size(r_new) <= tol) | stalled

        jac0, r0, tol0 = linearized(alpha0)
        return jax.lax.while_loop(lambda c: (c[0] < EAS_MAX_ITER) & ~c[4], body,
                                  (jnp.array(0), alpha0, jac0, r0, size(r0) <= tol0))[1]

    start = _start(states, n, u_e, F_c.dtype)
    return jax.lax.custom_root(residual, jax.lax.stop_gradient(start), newton,
                               lambda g, y: jnp.linalg.solve(jax.jacfwd(g)(y), y))


def element_force(material, formulation, dN_dX, dN_dX_center, weight, u_e, states):
    """Internal force of one element and its updated material states.

    Args:
        material: the material law, ``material.update(F (2,2), state) -> (tau (3,3), state)``.
        formulation: one of :data:`FORMULATIONS` (static).
        dN_dX, dN_dX_center, weight: this element's rows of :class:`ElementGeometry` (``dN_dX``: those of
            :meth:`ElementGeometry.gradients`).
        u_e: (4, 2) nodal displacements (mm).
        states: material states at the Gauss points (batched pytree, leading axis gp).

    Returns:
        f_e: (4, 2) nodal internal forces (N/mm).
        aux: (new_states, tau (gp, 3, 3), det_min).
    """

    alpha = _condensed(material, formulation, dN_dX, dN_dX_center, weight, u_e, states)

    def kinematics(u):
        return _kinematics(formulation, dN_dX, dN_dX_center, weight, u, alpha)

    Fb, pull_back, det_min = jax.vjp(kinematics, u_e, has_aux=True)
    tau, new_states = jax.vmap(material.update)(Fb, states)
    new_states = _with_enhanced(new_states, alpha)
    # Plane strain: tau and F_bar are block-diagonal, so the in-plane block of P_bar = tau F_bar^-T
    # is tau_2D F_bar_2D^-T; the zz entry does no virtual work (dF_bar_zz = 0).
    P = jnp.einsum("gik,gjk->gij", tau[:, :2, :2], inv2(Fb))
    (f_e,) = pull_back(weight[:, None, None] * P)
    return f_e, (new_states, tau, det_min)


def element_force_and_tangent(material, formulation, dN_dX, dN_dX_center, weight, u_e, states, predictor=None):
    """As :func:`element_force`, plus the (8, 8) element tangent d f_e / d u_e (dofs node-major).

    The tangent is the exact derivative of f_e = sum_g w_g (dF_g/du)^T P_g, assembled by the chain rule,
    so that the material is pushed forward along 4 directions (the components of F_bar) instead of 8
    (the element dofs):

        K_e = sum_g w_g [ (dF_g/du)^T (dP_g/dF_g) (dF_g/du) + P_g : d2F_g/du2 ]

    dP/dF the point law's consistent tangent (:func:`~jaxfric.fem.material.piola_and_tangent`: in closed
    form for the radial return, else ``jacfwd``). For ``fbar`` and ``ans``,
    dF/du and the geometric term (the Hessian of u -> sum_g w_g P_g : F_g(u) with P held fixed) in
    closed form from the determinants' derivatives (:func:`_fbar_geometric_term`: about 0.7 times the
    element cost of differentiating the kinematics, ``experiments/bench_element_tangent.py``); for the
    others by ``jacfwd`` of the kinematics and, for ``anst``, ``jacfwd`` over ``grad`` (zero for plain
    Q4 and ``eas``, whose F is affine in (u, alpha)). With enhanced parameters the tangent is the
    condensed ``K_uu - K_ua K_aa^-1 K_au``.

    ``predictor`` (enhanced formulations only): None, alpha is condensed by the local solve (exact at
    every call); or (n_alpha, 9), the enhanced-strain update of Simo and Armero, which carries alpha
    with the Newton iterate: alpha = predictor[:, 0] + predictor[:, 1:] u_e (the previous iterate's
    alpha corrected by its linearised equation, :func:`enhanced_predictor`), one material pass and no
    local solve. The force is then the condensed residual ``R_u - K_ua K_aa^-1 R_a``, whose Newton step
    with the condensed tangent is Newton's on (u, alpha), and the aux gains the next iterate's
    predictor and ``K_ua K_aa^-1 R_a`` (8,), what the element's own equation still moves in the force
    (zero once alpha is condensed).
    """

    alpha = (_condensed(material, formulation, dN_dX, dN_dX_center, weight, u_e, states) if predictor is None
             else predictor[:, 0] + predictor[:, 1:] @ u_e.ravel())

    nd = u_e.size   # the element's dofs, node-major

    def kinematics(v):  # v: the element dofs, then alpha
        return _kinematics(formulation, dN_dX, dN_dX_center, weight, v[:nd].reshape(u_e.shape), v[nd:])

    if formulation in ("fbar", "ans"):
        parts = _fbar_parts(dN_dX, dN_dX_center, u_e)
        Fb, det_min, dF_dv = parts.Fbar, parts.det_min, _fbar_gradient(parts, dN_dX)
    else:
        v = jnp.concatenate([u_e.ravel(), alpha])
        Fb, det_min, dF_dv = _value_and_jacfwd(kinematics, v)  # dF_dv: (gp, 2, 2, nd + n_alpha)
    dP_dF, (P, tau, new_states) = jax.vmap(lambda F, state: piola_and_tangent(material, F, state))(Fb, states)
    wP = weight[:, None, None] * P
    K_e = jnp.einsum("g,gija,gijkl,gklb->ab", weight, dF_dv, dP_dF, dF_dv)
    if formulation in ("fbar", "ans"):
        K_e = K_e + _fbar_geometric_term(wP, parts, dN_dX)
    elif formulation == "anst":  # F depends on alpha through the fibre F_0: differentiate the kinematics
        # Forward over grad (not jax.hessian, i.e. forward over jacrev): same matrix, measured 2.3x faster.
        K_e = K_e + jax.jacfwd(jax.grad(lambda w: jnp.sum(jax.lax.stop_gradient(wP) * kinematics(w)[0])))(v)
    if predictor is None:
        new_states = _with_enhanced(new_states, alpha)
        f_e = jnp.einsum("gij,gija->a", wP, dF_dv[..., :nd])
        if alpha.size:
            K_e = K_e[:nd, :nd] - K_e[:nd, nd:] @ jnp.linalg.solve(K_e[nd:, nd:], K_e[nd:, :nd])
        return f_e.reshape(u_e.shape), K_e, (new_states, tau, det_min)
    r = jnp.einsum("gij,gija->a", wP, dF_dv)      # (R_u, R_a)
    h = jnp.linalg.solve(K_e[nd:, nd:], jnp.concatenate([r[nd:, None], K_e[nd:, :nd]], axis=1))  # K_aa^-1 [R_a K_au]
    gap = K_e[:nd, nd:] @ h[:, 0]
    f_e = r[:nd] - gap
    K_c = K_e[:nd, :nd] - K_e[:nd, nd:] @ h[:, 1:]
    next_predictor = enhanced_predictor(alpha - h[:, 0] + h[:, 1:] @ u_e.ravel(), -h[:, 1:])
    new_states = _with_enhanced(new_states, alpha, next_predictor)
    return f_e.reshape(u_e.shape), K_c, (new_states, tau, det_min, next_predictor, gap.reshape(u_e.shape))


def enhanced_predictor(alpha0, slope=None, n_dofs: int = 8) -> jax.Array:
    """(n_alpha, 1 + n_dofs) the predictor of :func:`element_force_and_tangent`: alpha(u_e) = alpha0 + slope u_e
    (``slope`` (n_alpha, n_dofs), the element's dofs; zero by default: alpha held at ``alpha0``, as at the
    start of a step)."""
    n_dofs = n_dofs if slope is None else slope.shape[-1]
    slope = jnp.zeros((alpha0.shape[-1], n_dofs), alpha0.dtype) if slope is None else slope
    return jnp.concatenate([alpha0[..., None], jnp.broadcast_to(slope, alpha0.shape + (n_dofs,))], axis=-1)
