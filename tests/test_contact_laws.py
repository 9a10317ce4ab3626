"""The pair law at its kinks: branch choices, exact values, smoothing."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfric.contact.alart_curnier import OPEN as AC_OPEN
from jaxfric.contact.alart_curnier import STICK as AC_STICK
from jaxfric.contact.alart_curnier import alart_curnier_residual, piece_jacobian
from jaxfric.contact.exact_active_set import Compliance, compliant
from jaxfric.contact.laws import augmented_pair
from jaxfric.contact.status import OPEN, SLIP, STICK, contact_status

EPS_N, EPS_T, MU = 1e5, 1.5e4, 0.2


def penalty_pair(gap, slip, rt_prev, mu, eps_n, eps_t):
    """The penalty law: the augmented-Lagrangian pair law with lambda_N = 0 and lambda_T = R_T,n."""
    return augmented_pair(gap, slip, 0.0, rt_prev, mu, eps_n, eps_t)


def test_penalty_branches():
    open_ = penalty_pair(1e-3, 0.0, 0.0, MU, EPS_N, EPS_T)
    assert float(open_.normal) == 0.0 and int(open_.status) == OPEN
    stick = penalty_pair(-1e-4, 1e-6, 0.0, MU, EPS_N, EPS_T)
    np.testing.assert_allclose([stick.normal, stick.tangential], [10.0, -0.015])
    assert int(stick.status) == STICK
    slip = penalty_pair(-1e-4, 1e-3, 0.0, MU, EPS_N, EPS_T)
    np.testing.assert_allclose([slip.normal, slip.tangential], [10.0, -2.0])
    assert int(slip.status) == SLIP


def test_touching_pair_is_closed_with_normal_stiffness_and_no_spurious_stick():
    """g = 0 exactly: closed (spec 0), dR_N/dg = -eps_n; R_T = 0 with zero tangential stiffness."""
    f = lambda g, s: penalty_pair(g, s, 0.0, MU, EPS_N, EPS_T)  # noqa: E731
    assert int(f(0.0, 0.0).status) != OPEN
    dn = jax.grad(lambda g: f(g, 0.0).normal)(0.0)
    dt = jax.grad(lambda s: f(0.0, s).tangential)(0.0)
    assert float(dn) == -EPS_N and float(dt) == 0.0


def test_frictionless_and_status_thresholds():
    f = penalty_pair(-1e-4, 1e-3, 0.0, 0.0, EPS_N, EPS_T)
    assert float(f.tangential) == 0.0 and int(f.status) == SLIP
    np.testing.assert_array_equal(contact_status(jnp.array([0.0, 1.0, 1.0]), jnp.array([0.0, 0.1, 0.2]), 0.2),
                                  [OPEN, STICK, SLIP])


@pytest.mark.parametrize("s", [1e-2, 1e-4])
def test_smoothing_tends_to_the_exact_law_and_is_differentiable_at_the_kinks(s):
    gaps = jnp.linspace(-2e-4, 2e-4, 41)
    slips = jnp.linspace(-3e-3, 3e-3, 41)
    exact = jax.vmap(lambda g, x: augmented_pair(g, x, 0.0, 0.0, MU, EPS_N, EPS_T))(gaps, slips)
    smooth = jax.vmap(lambda g, x: augmented_pair(g, x, 0.0, 0.0, MU, EPS_N, EPS_T, smoothing=s))(gaps, slips)
    # error at most s log 2 in R_N; the clip adds at most (1 + mu) s log 2 to R_T
    assert float(jnp.max(jnp.abs(smooth.normal - exact.normal))) <= s * np.log(2) * 1.0001
    assert float(jnp.max(jnp.abs(smooth.tangential - exact.tangential))) <= (1 + MU) * s * np.log(2) * 1.0001
    # at the normal kink (g = 0) and at the stick/slip kink (|R_T^tr| = mu R_N): finite derivatives that
    # match central differences
    for g, x in [(0.0, 0.0), (-1e-4, MU * 10.0 / EPS_T)]:
        f = lambda v: jnp.stack(augmented_pair(v[0], v[1], 0.0, 0.0, MU, EPS_N, EPS_T, smoothing=s)[:2])  # noqa: E731
        v0 = jnp.array([g, x])
        J = jax.jacfwd(f)(v0)
        h = jnp.array([1e-3, 1e-3]) * s / EPS_N
        fd = jnp.stack([(f(v0 + h * e) - f(v0 - h * e)) / (2 * h[i]) for i, e in enumerate(jnp.eye(2))], 1)
        assert bool(jnp.all(jnp.isfinite(J)))
        np.testing.assert_allclose(J, fd, rtol=1e-5, atol=1e-6 * EPS_N)


def test_smoothed_law_has_finite_tangents_on_invalid_pairs_with_a_traced_scale():
    """A pair that projects on no primitive, with the force scale s traced (a model leaf, as in every
    scene): zero forces and zero, not NaN, tangents in forward and reverse mode (an -inf trial force
    once made the forward tangent inf * 0 = NaN, which spread through the bead test's whole step)."""
    def f(v, valid):
        return jnp.stack(augmented_pair(v[0], v[1], 0.0, 1.0, MU, EPS_N, EPS_T, valid, smoothing=v[2])[:2])

    v0 = jnp.array([1e-3, 1e-4, 10.0])
    for valid in (False, True):
        value, tangent = jax.jvp(lambda v: f(v, valid), (v0,), (jnp.array([1.0, 1.0, 0.0]),))
        assert bool(jnp.all(jnp.isfinite(tangent))) and bool(jnp.all(jnp.isfinite(jax.jacrev(f)(v0, valid))))
    np.testing.assert_array_equal(np.asarray(f(v0, False)), 0.0)
    np.testing.assert_array_equal(np.asarray(jax.jvp(lambda v: f(v, False), (v0,), (jnp.ones(3),))[1]), 0.0)


def test_static_flags_follow_the_given_values_inside_jit():
    """Built inside jit from plain numbers, a penalty is not smoothed and a mu = 0 tool is frictionless."""
    from jaxfric.contact.formulations import Penalty
    from jaxfric.contact.rigid import Move, RigidTool
    from jaxfric.contact.tools import Tool

    @jax.jit
    def flags(eps):
        law = Penalty(eps, 0.0)
        tool = RigidTool("t", Tool.line((0.0, 0.0), (1.0, 0.0)), (0.0, -1.0), [0], (Move(),), 0.0)
        assert not law.smooth and not tool.frictional
        return eps

    flags(1e5)


def test_penalty_law_is_the_alart_curnier_law_of_the_compliant_gap_and_slip():
    """The compliant semismooth solve (Complementarity(compliant=True), exact_start's start) rests on this:
    the penalty law's forces make the Alart-Curnier residual of g~ = g + R_N / eps_N, s~ = s + (R_T - R_T,n)
    / eps_T vanish (open, stick and slip pairs, any c_N, c_T > 0), with the active set the penalty law
    took, and on that piece the residual's derivative in the forces is W_F + W_K diag(1 / eps_N, 1 / eps_T),
    the matrix piece_system assembles."""
    rng = np.random.default_rng(3)
    n = 400
    gap = rng.uniform(-3e-4, 1e-4, n)
    slip = rng.uniform(-2e-3, 2e-3, n) * rng.choice([1e-3, 1.0], n)    # sticking and slipping pairs
    lam_t = rng.uniform(-5.0, 5.0, n)
    c_n, c_t = rng.uniform(1e2, 1e6, n), rng.uniform(1e2, 1e6, n)
    f = jax.vmap(lambda g, s, lt: penalty_pair(g, s, lt, MU, EPS_N, EPS_T))(gap, slip, lam_t)
    mu = jnp.full(n, MU)
    cp = Compliance(jnp.asarray(1.0 / EPS_N), jnp.asarray(1.0 / EPS_T), jnp.asarray(lam_t))
    pairs = jnp.arange(n)

    def residual(R_N, R_T):
        g, s = compliant(cp, pairs, mu, R_N, R_T, gap, slip)
        return alart_curnier_residual(R_N, R_T, g, s, mu, c_n, c_t)

    state, C, _ = residual(f.normal, f.tangential)
    kinds = {int(k) for k in np.asarray(f.status)}
    assert kinds == {OPEN, STICK, SLIP}
    np.testing.assert_allclose(np.asarray(C), 0.0, atol=1e-12 * float(jnp.max(f.normal)))
    expected = np.where(f.status == OPEN, AC_OPEN, np.where(f.status == STICK, AC_STICK, -1))
    took = np.asarray(state)
    assert np.all((took == expected) | ((expected == -1) & (took > AC_STICK)))
    # The piece's Jacobian in the forces (away from the kinks, where the piece is the penalty law's).
    J = jax.vmap(jax.jacfwd(lambda p, g, s, lt, cn, ct: alart_curnier_residual(
        p[0], p[1], *compliant(cp._replace(lam_t=lt), 0, MU, p[0], p[1], g, s), MU, cn, ct)[1]))(
        jnp.stack([f.normal, f.tangential], -1), gap, slip, lam_t[:, None], c_n, c_t)
    w_f, w_k = piece_jacobian(state, mu, c_n, c_t)
    np.testing.assert_allclose(np.asarray(J), np.asarray(w_f + w_k * jnp.array([1.0 / EPS_N, 1.0 / EPS_T])),
                               rtol=1e-12, atol=1e-12)
