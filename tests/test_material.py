"""Finite-strain J2 law at a point: yield surface along a path, unloading, consistent tangent, small-strain
limit, objectivity, parameter sensitivities, degenerate laws (perfectly plastic, elastic), validation."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfric.fem.material import (
    INTEGRATIONS,
    J2Material,
    MaterialState,
    piola_and_tangent,
    piola_and_tangent_ad,
    von_mises,
)

# Sheet materials of the benchmark scenes (spec tables 1 and 2): a very steep initial hardening
# (A = 1e4) and a moderate one.
FLAT_DIE = dict(E=69004.0, nu=0.3, sigma_y=80.55923, A=10000.0, n=0.216)
BEAD = dict(E=200000.0, nu=0.3, sigma_y=169.0, A=127.42425, n=0.225)
PERFECT_N0 = dict(E=200000.0, nu=0.3, sigma_y=169.0, A=127.42425, n=0.0)
PERFECT_A0 = dict(E=200000.0, nu=0.3, sigma_y=169.0, A=0.0, n=0.225)
MATERIALS = {"flat_die": FLAT_DIE, "bead": BEAD}
PERFECT = {"n0": PERFECT_N0, "A0": PERFECT_A0}
ALL_LAWS, ALL_LAW_IDS = [FLAT_DIE, BEAD, PERFECT_N0, PERFECT_A0], ["flat_die", "bead", "n0", "A0"]

# A general (sheared, non-diagonal) plastic step from the virgin state, and a further step along it.
F_FIRST = np.array([[1.01, 0.004], [0.002, 0.993]])
F_SECOND = np.eye(2) + 1.5 * (F_FIRST - np.eye(2))


N_INCREMENTS = 50

# ---------------------------------------------------------------------------------------------------
# Compiled helpers (the material is an argument: new parameter values reuse the compiled code).


@jax.jit
def update(material, F, state):
    return material.update(F, state)


def first_piola_2d(material, F, state):
    """In-plane P = tau F^-T, flattened to (P11, P12, P21, P22)."""
    tau, _ = material.update(F, state)
    return (tau[:2, :2] @ jnp.linalg.inv(F).T).ravel()


@jax.jit
def tangents(material, F, state):
    """dP/dF (4, 4) by forward mode (as the element code does) and by reverse mode."""
    fwd = jax.jacfwd(first_piola_2d, argnums=1)(material, F, state).reshape(4, 4)
    rev = jax.jacrev(first_piola_2d, argnums=1)(material, F, state).reshape(4, 4)
    return fwd, rev


@jax.jit
def uniaxial_path(material, stretches):
    """Plane-strain uniaxial tension F = diag(lam, lam2), lam2 solved each increment so tau_yy = 0.

    Returns per increment: tau (3, 3), state, lam2.
    """

    def increment(carry, lam):
        state, lam2 = carry

        def tau_yy(l2):
            return material.update(jnp.diag(jnp.stack([lam, l2])), state)[0][1, 1]

        def newton(_, l2):
            value, slope = jax.jvp(tau_yy, (l2,), (jnp.ones_like(l2),))
            return l2 - value / slope

        lam2 = jax.lax.fori_loop(0, 20, newton, lam2)
        tau, new_state = material.update(jnp.diag(jnp.stack([lam, lam2])), state)
        return (new_state, lam2), (tau, new_state, lam2)

    _, out = jax.lax.scan(increment, (material.init_state(), jnp.ones_like(stretches[0])), stretches)
    return out


def stretch_path(final):
    """Stretches 1 -> final in N_INCREMENTS equal increments (one length: uniaxial_path compiles once)."""
    return jnp.linspace(1.0, final, N_INCREMENTS + 1)[1:]


def take(tree, k):
    return jax.tree.map(lambda leaf: leaf[k], tree)


def hencky_reference(material, F, state):
    """tau from b^e = F C_p^-1 F^T by numpy's eigendecomposition (independent of jaxfric.numerics.tensor)."""
    kappa, G = float(material.bulk_modulus), float(material.shear_modulus)
    be = F @ np.asarray(state.cp_inv) @ F.T
    lam, Q = np.linalg.eigh(be)
    eps = np.zeros((3, 3))
    eps[:2, :2] = (Q * (0.5 * np.log(lam))) @ Q.T
    eps[2, 2] = 0.5 * np.log(float(state.cp_inv_zz))
    trace = np.trace(eps)
    return kappa * trace * np.eye(3) + 2.0 * G * (eps - trace / 3.0 * np.eye(3))


def all_finite(tree):
    return all(bool(np.all(np.isfinite(np.asarray(leaf)))) for leaf in jax.tree.leaves(tree))


def plastic_state(material):
    _, state = update(material, jnp.asarray(F_FIRST), material.init_state())
    assert float(state.eqps) > 0
    return state


# ---------------------------------------------------------------------------------------------------
# Yield surface, unloading, state consistency.


@pytest.mark.parametrize("name", MATERIALS)
def test_uniaxial_path_stays_on_yield_surface(name):
    material = J2Material(**MATERIALS[name])
    stretches = stretch_path(1.05)
    taus, states, lam2s = uniaxial_path(material, stretches)
    eqps = np.asarray(states.eqps)
    q = np.asarray(jax.vmap(von_mises)(taus))
    sigma_Y = np.asarray(material.yield_stress(states.eqps))
    np.testing.assert_allclose(np.asarray(taus[:, 1, 1]), 0.0, atol=1e-9 * float(material.sigma_y))

    plastic = np.diff(np.concatenate([[0.0], eqps])) > 0
    assert plastic.sum() >= 45 and np.all(np.diff(eqps) >= 0)
    np.testing.assert_allclose(q[plastic], sigma_Y[plastic], rtol=1e-8)
    assert np.all(q[~plastic] <= sigma_Y[~plastic])
    # Uniaxial tension: sigma_xx is the largest stress and the material hardens along the path.
    assert np.all(np.diff(q[plastic]) > 0)

    # The stored C_p^-1 reproduces the returned stress: tau = Hencky(1/2 ln(F C_p^-1 F^T)).
    for k in (0, 10, 49):
        F = np.diag([float(stretches[k]), float(lam2s[k])])
        ref = hencky_reference(material, F, take(states, k))
        np.testing.assert_allclose(np.asarray(taus[k]), ref, rtol=0, atol=1e-9 * np.abs(ref).max())


@pytest.mark.parametrize("name", MATERIALS)
def test_unloading_is_elastic(name):
    material = J2Material(**MATERIALS[name])
    taus, states, lam2s = uniaxial_path(material, stretch_path(1.03))
    state_n, tau_n = take(states, -1), np.asarray(taus[-1])
    F_n = np.diag([1.03, float(lam2s[-1])])
    # Unload part of the way back: far less than the 2 sigma_Y stress reversal needed to re-yield.
    F = F_n + np.diag([-1.5e-3, 0.5e-3])
    tau, state = update(material, jnp.asarray(F), state_n)
    assert float(state.eqps) == float(state_n.eqps)
    np.testing.assert_array_equal(np.asarray(state.cp_inv), np.asarray(state_n.cp_inv))
    assert float(state.cp_inv_zz) == float(state_n.cp_inv_zz)
    assert float(von_mises(tau)) < 0.9 * float(material.yield_stress(state_n.eqps))
    # Stress change = elastic law change with the plastic metric frozen.
    expected_change = hencky_reference(material, F, state_n) - hencky_reference(material, F_n, state_n)
    atol = 1e-8 * np.abs(expected_change).max()
    np.testing.assert_allclose(np.asarray(tau) - tau_n, expected_change, rtol=0, atol=atol)
    assert np.abs(expected_change).max() > 10.0  # a real unloading, not a no-op


@pytest.mark.parametrize("name", MATERIALS)
def test_single_large_step_converges(name):
    material = J2Material(**MATERIALS[name])
    tau, state = update(material, jnp.array([[1.3, 0.1], [-0.05, 0.8]]), material.init_state())
    assert float(state.eqps) > 0.1
    np.testing.assert_allclose(float(von_mises(tau)), float(material.yield_stress(state.eqps)), rtol=1e-12)


# ---------------------------------------------------------------------------------------------------
# Tangents.


def central_difference_tangent(material, F, state, h=1e-7):
    def P(F):
        tau, _ = update(material, jnp.asarray(F), state)
        return (np.asarray(tau)[:2, :2] @ np.linalg.inv(F).T).ravel()

    columns = []
    for k in range(4):
        dF = np.zeros(4)
        dF[k] = h
        columns.append((P(F + dF.reshape(2, 2)) - P(F - dF.reshape(2, 2))) / (2 * h))
    return np.stack(columns, axis=1)


@pytest.mark.parametrize("integration", INTEGRATIONS)
@pytest.mark.parametrize("name", MATERIALS)
def test_consistent_tangent_matches_finite_differences(name, integration):
    material = J2Material(**MATERIALS[name], integration=integration)
    state_n = plastic_state(material)
    F = jnp.asarray(F_SECOND)
    _, state = update(material, F, state_n)
    assert float(state.eqps) > float(state_n.eqps)  # trial plastic

    tangent, tangent_rev = (np.asarray(t) for t in tangents(material, F, state_n))
    fd = central_difference_tangent(material, F_SECOND, state_n)
    assert np.linalg.norm(tangent - fd) <= 1e-6 * np.linalg.norm(fd)
    np.testing.assert_allclose(tangent_rev, tangent, rtol=0, atol=1e-10 * np.abs(tangent).max())
    # The test can fail: the elastic tangent at the same point is far from the consistent one.
    elastic = J2Material.elastic(material.E, material.nu)
    elastic_tangent = np.asarray(tangents(elastic, F, state_n)[0])
    assert np.linalg.norm(elastic_tangent - tangent) > 0.1 * np.linalg.norm(tangent)


@pytest.mark.parametrize("params", ALL_LAWS, ids=ALL_LAW_IDS)
def test_tangent_at_identity_is_small_strain_elasticity(params):
    for material in (J2Material(**params), J2Material.elastic(params["E"], params["nu"])):
        state = material.init_state()
        F = jnp.eye(2)
        G = float(material.shear_modulus)
        lame = float(material.bulk_modulus) - 2.0 * G / 3.0
        # Rows and columns ordered (11, 12, 21, 22).
        expected = np.array(
            [[lame + 2 * G, 0, 0, lame], [0, G, G, 0], [0, G, G, 0], [lame, 0, 0, lame + 2 * G]]
        )
        for tangent in tangents(material, F, state):
            tangent = np.asarray(tangent)
            assert np.all(np.isfinite(tangent))
            np.testing.assert_allclose(tangent, expected, rtol=1e-13, atol=1e-9 * G)


# ---------------------------------------------------------------------------------------------------
# Degenerate laws: perfectly plastic, purely elastic. No NaN in values or derivatives.


PARAM_NAMES = ("E", "nu", "sigma_y", "A", "n")


def two_step_response(params_vector, F1, F2):
    """(tau (9), eqps, C_p^-1 (4)) after two steps F1, F2 from the virgin state, as a function of the
    parameters (E, nu, sigma_y, A, n): the derivative follows the history through both returns."""
    material = J2Material(**dict(zip(PARAM_NAMES, params_vector)))
    _, state = material.update(F1, material.init_state())
    tau, state = material.update(F2, state)
    return jnp.concatenate([tau.ravel(), state.eqps[None], state.cp_inv.ravel()])


two_step_value = jax.jit(two_step_response)


@jax.jit
def two_step_jvp_vjp(p, v, w, F1, F2):
    value, jvp = jax.jvp(lambda q: two_step_response(q, F1, F2), (p,), (v,))
    _, pullback = jax.vjp(lambda q: two_step_response(q, F1, F2), p)
    return value, jvp, pullback(w)[0]


def parameter_derivatives(params, direction, w, F1=F_FIRST, F2=F_SECOND):
    """Forward (J v), reverse (J^T w) and central-difference (h = 1e-6) derivatives along `direction`."""
    p0 = np.array([params[k] for k in PARAM_NAMES])
    F1, F2 = jnp.asarray(F1), jnp.asarray(F2)
    derivatives = two_step_jvp_vjp(jnp.asarray(p0), jnp.asarray(direction), jnp.asarray(w), F1, F2)
    value, jvp, vjp = (np.asarray(x) for x in derivatives)
    h = 1e-6
    plus = np.asarray(two_step_value(jnp.asarray(p0 + h * direction), F1, F2))
    minus = np.asarray(two_step_value(jnp.asarray(p0 - h * direction), F1, F2))
    return value, jvp, vjp, (plus - minus) / (2 * h)


def assert_derivatives_finite(params):
    """Forward and reverse derivatives w.r.t. F (tangent) and the parameters (two-step history) are finite,
    at F = I (zero stress, |dev tau| = 0) and along a plastic path."""
    material = J2Material(**params)
    w = np.random.default_rng(3).standard_normal(14)
    for F1, F2 in ((np.eye(2), np.eye(2)), (F_FIRST, F_SECOND)):
        _, state = update(material, jnp.asarray(F1), material.init_state())
        F2 = jnp.asarray(F2)
        assert all_finite((state, update(material, F2, state), tangents(material, F2, state)))
        value, jvp, vjp, _ = parameter_derivatives(params, np.ones(5), w, F1, F2)
        assert all_finite((value, jvp, vjp))


@pytest.mark.parametrize("name", PERFECT)
def test_perfectly_plastic(name):
    material = J2Material(**PERFECT[name])
    assert float(material.hardening_slope(0.0)) == 0.0 and float(material.hardening_slope(0.3)) == 0.0
    taus, states, _ = uniaxial_path(material, stretch_path(1.02))
    eqps = np.asarray(states.eqps)
    assert eqps[-1] > 0.01
    plastic = np.diff(np.concatenate([[0.0], eqps])) > 0
    q = np.asarray(jax.vmap(von_mises)(taus))
    np.testing.assert_allclose(q[plastic], float(material.sigma_y), rtol=1e-12)
    assert_derivatives_finite(PERFECT[name])


def test_elastic_never_yields():
    material = J2Material.elastic(200000.0, 0.3)
    assert float(material.yield_stress(0.0)) == np.inf and float(material.hardening_slope(0.0)) == 0.0
    state0 = material.init_state()
    for F in (np.eye(2), np.diag([1.5, 0.6]), np.array([[1.2, 0.7], [-0.3, 0.9]])):
        tau, state = update(material, jnp.asarray(F), state0)
        assert float(state.eqps) == 0.0
        np.testing.assert_array_equal(np.asarray(state.cp_inv), np.eye(2))
        ref = hencky_reference(material, F, state0)
        np.testing.assert_allclose(np.asarray(tau), ref, rtol=0, atol=1e-10 * max(np.abs(ref).max(), 1.0))
    assert_derivatives_finite(dict(E=200000.0, nu=0.3, sigma_y=np.inf, A=0.0, n=0.0))
    taus, states, _ = uniaxial_path(material, stretch_path(1.2))
    assert np.all(np.asarray(states.eqps) == 0.0)
    assert float(jax.vmap(von_mises)(taus)[-1]) > 10 * 169.0


# ---------------------------------------------------------------------------------------------------
# Objectivity, batching, compilation.


@pytest.mark.parametrize("name", MATERIALS)
@pytest.mark.parametrize("integration", INTEGRATIONS)
def test_objectivity(name, integration):
    material = J2Material(**MATERIALS[name], integration=integration)
    state_n = plastic_state(material)
    angle = 0.7
    Q = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    tau, state = update(material, jnp.asarray(F_SECOND), state_n)
    tau_rot, state_rot = update(material, jnp.asarray(Q @ F_SECOND), state_n)
    tau, tau_rot = np.asarray(tau), np.asarray(tau_rot)
    scale = np.abs(tau).max()
    np.testing.assert_allclose(tau_rot[:2, :2], Q @ tau[:2, :2] @ Q.T, rtol=0, atol=1e-11 * scale)
    np.testing.assert_allclose(tau_rot[2, 2], tau[2, 2], rtol=1e-12)
    np.testing.assert_allclose(tau_rot[:2, 2], 0.0, atol=0)
    np.testing.assert_allclose(float(state_rot.eqps), float(state.eqps), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(state_rot.cp_inv), np.asarray(state.cp_inv), rtol=0, atol=1e-13)
    assert float(state.eqps) > float(state_n.eqps)


@jax.jit
@eqx.debug.assert_max_traces(max_traces=1)
def batched_update_and_tangent(material, Fs, states):
    """The element code's use: vmap over points of the update and of its jacfwd tangent."""
    taus, new_states = jax.vmap(material.update)(Fs, states)
    tangents = jax.vmap(jax.jacfwd(first_piola_2d, argnums=1), in_axes=(None, 0, 0))(material, Fs, states)
    return taus, new_states, tangents


def test_vmap_jit_and_no_retrace():
    Fs = jnp.asarray(np.stack([np.eye(2), F_FIRST, F_SECOND, np.array([[0.999, 0.0], [0.0, 1.0005]])]))
    # New parameter values (including the elastic law) reuse the one trace.
    for material in (J2Material(**BEAD), J2Material(**FLAT_DIE), J2Material.elastic(1.0e5, 0.25)):
        states = jax.tree.map(lambda leaf: jnp.stack([leaf] * 4), material.init_state())
        taus, new_states, batch_tangents = batched_update_and_tangent(material, Fs, states)
        assert np.all(np.isfinite(np.asarray(batch_tangents)))  # elastic F = I next to plastic points
        for k in range(4):
            tau, state = update(material, Fs[k], take(states, k))
            np.testing.assert_allclose(np.asarray(taus[k]), np.asarray(tau), rtol=1e-14, atol=1e-12)
            np.testing.assert_allclose(float(new_states.eqps[k]), float(state.eqps), rtol=1e-14, atol=0)
            np.testing.assert_allclose(
                np.asarray(batch_tangents[k]).reshape(4, 4),
                np.asarray(tangents(material, Fs[k], take(states, k))[0]),
                rtol=1e-13,
                atol=1e-9,
            )
        assert float(new_states.eqps[0]) == 0.0
        assert (float(new_states.eqps[2]) > 0.0) == bool(np.isfinite(float(material.sigma_y)))


# ---------------------------------------------------------------------------------------------------
# Parameter sensitivities through the return map (implicit function theorem at the converged Newton).
# Helpers are defined above, with the degenerate laws that also use them.


@pytest.mark.parametrize("name", MATERIALS)
def test_yield_stress_sensitivity_matches_finite_differences(name):
    params = MATERIALS[name]
    direction = params["sigma_y"] * np.array([0.0, 0.0, 1.0, 0.0, 0.0])  # relative change of sigma_y
    value, jvp, _, fd = parameter_derivatives(params, direction, np.zeros(14))
    assert value[9] > 0  # both steps plastic (checked in plastic_state / the tangent test)
    assert np.linalg.norm(jvp[:9] - fd[:9]) <= 1e-6 * np.linalg.norm(fd[:9])
    assert abs(jvp[9] - fd[9]) <= 1e-6 * abs(fd[9])
    assert np.linalg.norm(fd[:9]) > 1.0  # the stress really depends on sigma_y: the steps are plastic


@pytest.mark.parametrize("name", MATERIALS)
def test_parameter_sensitivities_all_modes(name):
    """Random direction in (E, nu, sigma_y, A, n): jvp = central differences; <w, J v> = <J^T w, v>."""
    params = MATERIALS[name]
    rng = np.random.default_rng(7)
    p0 = np.array([params[k] for k in PARAM_NAMES])
    direction = rng.standard_normal(5) * p0 * np.array([1, 0.1, 1, 1, 1])  # keeps nu well inside (-1, 0.5)
    w = rng.standard_normal(14)
    _, jvp, vjp, fd = parameter_derivatives(params, direction, w)
    np.testing.assert_allclose(w @ jvp, vjp @ direction, rtol=1e-11)
    assert np.linalg.norm(jvp - fd) <= 1e-6 * np.linalg.norm(fd)


def test_elastic_parameter_derivatives():
    # Purely elastic response: tau is linear in E at fixed nu, and nothing yields, so no NaN from inf.
    params = dict(E=200000.0, nu=0.3, sigma_y=np.inf, A=0.0, n=0.0)
    direction, w = np.array([1.0, 0, 0, 0, 0]), np.r_[np.ones(9), np.zeros(5)]
    value, jvp, vjp, _ = parameter_derivatives(params, direction, w)
    np.testing.assert_allclose(jvp[:9], value[:9] / params["E"], rtol=1e-12, atol=1e-20)
    np.testing.assert_allclose(vjp[0], value[:9].sum() / params["E"], rtol=1e-12)
    assert np.all(np.isfinite(vjp)) and value[9] == 0.0 and vjp[2] == 0.0


# ---------------------------------------------------------------------------------------------------
# Laws: yield stress, hardening slope.


@pytest.mark.parametrize("params", ALL_LAWS, ids=ALL_LAW_IDS)
def test_hardening_slope_is_derivative_of_yield_stress(params):
    material = J2Material(**params)
    for eqps in (0.0, 1e-6, 0.01, 0.5):
        slope = jax.grad(material.yield_stress)(jnp.asarray(eqps))
        np.testing.assert_allclose(float(material.hardening_slope(eqps)), float(slope), rtol=1e-13)
        assert np.isfinite(float(slope))
    np.testing.assert_allclose(float(material.yield_stress(0.0)), params["sigma_y"], rtol=1e-15)


def test_moduli():
    material = J2Material(E=260.0, nu=0.3, sigma_y=1.0, A=0.0, n=0.0)
    np.testing.assert_allclose(float(material.shear_modulus), 100.0, rtol=1e-15)
    np.testing.assert_allclose(float(material.bulk_modulus), 260.0 / 1.2, rtol=1e-15)
    assert material.E.dtype == jnp.float64 and material.init_state().eqps.dtype == jnp.float64
    assert isinstance(material.init_state(), MaterialState)


# ---------------------------------------------------------------------------------------------------
# Validation at construction.

BAD_VALUES = (
    [("E", v) for v in (0.0, -1.0, np.nan, np.inf, -np.inf)]
    + [("nu", v) for v in (-1.0, 0.5, 0.7, np.nan, np.inf, -np.inf)]
    + [("sigma_y", v) for v in (0.0, -5.0, np.nan, -np.inf)]
    + [("A", v) for v in (-1.0, np.nan, -np.inf, np.inf)]
    + [("n", v) for v in (-0.1, np.nan, -np.inf, np.inf)]
)


@pytest.mark.parametrize("field, value", BAD_VALUES)
def test_bad_values_raise(field, value):
    params = dict(BEAD, **{field: value})
    with pytest.raises(ValueError, match=f"J2Material: {field} = "):
        J2Material(**params)


def test_good_edge_values_and_tracers_accepted():
    J2Material(E=1.0, nu=-0.99, sigma_y=np.inf, A=0.0, n=0.0)
    J2Material(E=1.0, nu=0.4999, sigma_y=1e-3, A=1e6, n=3.0)
    # Inside jit the leaves are tracers: no check, no error, values flow through.
    built = jax.jit(lambda E: J2Material(E=E, nu=0.3, sigma_y=1.0, A=0.0, n=0.0).shear_modulus)(260.0)
    np.testing.assert_allclose(float(built), 100.0, rtol=1e-15)


# ---------------------------------------------------------------------------------------------------
# Integration of a step's flow: the radial return against the midpoint rule.


def turning_path(t):
    """A strain path whose direction turns: a stretch up and back, a growing shear, a rigid rotation."""
    a, g, th = 0.02 * jnp.sin(jnp.pi * t), 0.03 * t * t, 0.5 * t
    rot = jnp.array([[jnp.cos(th), -jnp.sin(th)], [jnp.sin(th), jnp.cos(th)]])
    return rot @ jnp.array([[1.0 + a, g], [0.0, 1.0 / (1.0 + a)]])


def proportional_path(t):
    """An isochoric stretch whose principal axes turn with the material: proportional in the rotated
    frame (a constant direction of the deviatoric log strain there)."""
    th = 0.8 * t
    rot = jnp.array([[jnp.cos(th), -jnp.sin(th)], [jnp.sin(th), jnp.cos(th)]])
    lam = 1.0 + 0.03 * t
    return rot @ jnp.diag(jnp.stack([lam, 1.0 / lam]))


@eqx.filter_jit
def integrate(material, path, n):
    """tau (3, 3) and eqps at the end of ``path`` (t from 0 to 1) in ``n`` equal steps."""
    def step(state, k):
        tau, new = material.update(path(k / n), state)
        return new, tau

    state, taus = jax.lax.scan(step, material.init_state(), jnp.arange(1, n + 1, dtype=jnp.float64))
    return taus[-1], state.eqps


def test_midpoint_return_is_second_order_where_the_path_turns_and_the_radial_return_first():
    errors = {}
    for integration in INTEGRATIONS:
        material = J2Material(**BEAD, integration=integration)
        tau_ref, eqps_ref = integrate(material, turning_path, 1280)
        errors[integration] = [abs(float(integrate(material, turning_path, n)[1] - eqps_ref)) for n in (20, 40, 80)]
        assert float(eqps_ref) > 0.02
    radial, midpoint = (np.array(errors[k]) for k in INTEGRATIONS)
    assert np.all((radial[:-1] / radial[1:] > 1.7) & (radial[:-1] / radial[1:] < 2.3))   # first order
    assert np.all(midpoint[:-1] / midpoint[1:] > 3.4)                                    # second order
    assert np.all(midpoint < radial / 5)


def test_midpoint_return_is_the_radial_return_on_a_proportional_path():
    radial, midpoint = (integrate(J2Material(**BEAD, integration=k), proportional_path, 40) for k in INTEGRATIONS)
    assert float(radial[1]) > 0.02
    np.testing.assert_allclose(np.asarray(midpoint[0]), np.asarray(radial[0]), rtol=0,
                               atol=1e-9 * float(np.abs(radial[0]).max()))
    assert float(midpoint[1]) == pytest.approx(float(radial[1]), rel=1e-10)


def test_unknown_integration_is_named():
    with pytest.raises(ValueError, match="integration = 'trapezoid'"):
        J2Material(**BEAD, integration="trapezoid")


@jax.jit
def closed_and_ad_tangents(material, Fs, states):
    """The radial return's closed-form dP/dF (what the element code takes) and jacfwd's, over points,
    with each one's derivative along a change of F and of the material's parameters."""
    def both(mat, F):
        return (jax.vmap(lambda f, s: piola_and_tangent(mat, f, s)[0])(F, states),
                jax.vmap(lambda f, s: piola_and_tangent_ad(mat, f, s)[0])(F, states))
    dmat = jax.tree.map(lambda leaf: 1e-3 * leaf, material)
    dF = 0.01 * jnp.ones_like(Fs).at[..., 0, 1].set(-0.02)
    values, derivatives = jax.jvp(both, (material, Fs), (dmat, dF))
    pieces = jax.vmap(lambda f, s: piola_and_tangent(material, f, s)[1])(Fs, states)
    pieces_ad = jax.vmap(lambda f, s: piola_and_tangent_ad(material, f, s)[1])(Fs, states)
    return values, derivatives, pieces, pieces_ad


@pytest.mark.parametrize("law", ALL_LAWS + [dict(E=1.0e5, nu=0.25, sigma_y=np.inf, A=0.0, n=0.0)],
                         ids=ALL_LAW_IDS + ["elastic"])
def test_closed_form_tangent_is_the_jacfwd_tangent(law):
    """At the virgin state (F = I, equal eigenvalues: the log's series branch), after a plastic step, on a
    further plastic step, on elastic unloading and on a near-identity trial from a plastic state, the
    closed-form consistent tangent equals ``jacfwd`` of P = tau F^-T to round-off, the stress and the
    updated history are the same bit for bit, and its own derivative (along F and the law's parameters,
    what a derivative of the whole path takes through the tangent) is jacfwd's to round-off and finite."""
    material = J2Material(**law)
    virgin = material.init_state()
    _, after_first = update(material, jnp.asarray(F_FIRST), virgin)
    F_unload = np.eye(2) + 0.5 * (F_FIRST - np.eye(2))
    cases = [(np.eye(2), virgin), (F_FIRST, virgin), (F_SECOND, after_first), (F_unload, after_first),
             (F_FIRST + 1e-9, after_first), (np.array([[1.3, 0.2], [-0.1, 0.8]]), virgin)]
    Fs = jnp.asarray(np.stack([F for F, _ in cases]))
    states = jax.tree.map(lambda *leaves: jnp.stack(leaves), *[s for _, s in cases])
    (closed, ad), (d_closed, d_ad), pieces, pieces_ad = closed_and_ad_tangents(material, Fs, states)
    for got, want in ((closed, ad), (d_closed, d_ad)):
        got, want = np.asarray(got), np.asarray(want)
        assert np.all(np.isfinite(got))
        scale = np.max(np.abs(want), axis=(1, 2, 3, 4), keepdims=True)
        assert np.all(np.abs(got - want) <= 1e-13 * scale), np.max(np.abs(got - want) / scale)
    for a, b in zip(jax.tree.leaves(pieces), jax.tree.leaves(pieces_ad)):
        assert np.array_equal(np.asarray(a), np.asarray(b))
    if np.isfinite(law["sigma_y"]):   # the cases cover both branches of the return
        plastic = np.asarray(pieces[2].eqps) > np.asarray(states.eqps)
        assert plastic.any() and not plastic.all()
