"""Kink-safe tensor helpers: values against eigendecomposition references, derivatives at the kinks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfric.numerics.tensor import safe_norm, sym2_exp, sym2_log, sym2_log_derivative

RNG_SEED = 20240611

# Compiled once per module: eager op-by-op dispatch of derivatives is what makes such tests slow.
VALUE = {fn: jax.jit(fn) for fn in (sym2_log, sym2_exp)}
JAC_FWD = {fn: jax.jit(jax.jacfwd(fn)) for fn in (sym2_log, sym2_exp)}
JAC_REV = {fn: jax.jit(jax.jacrev(fn)) for fn in (sym2_log, sym2_exp)}
JVP = {fn: jax.jit(lambda A, H, fn=fn: jax.jvp(fn, (A,), (H,))[1]) for fn in (sym2_log, sym2_exp)}


def rotation(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s], [s, c]])


def spd_with_eigenvalues(l1, l2, angle):
    R = rotation(angle)
    return R @ np.diag([l1, l2]) @ R.T


def reference_function(A, f):
    """f(A) by numpy's symmetric eigendecomposition."""
    lam, Q = np.linalg.eigh(A)
    return (Q * f(lam)) @ Q.T


def divided_difference_log(l1, l2):
    # (log l1 - log l2) / (l1 - l2) without cancellation
    return 1.0 / l1 if l1 == l2 else np.log1p((l1 - l2) / l2) / (l1 - l2)


def divided_difference_exp(l1, l2):
    return np.exp(l1) if l1 == l2 else np.exp(l2) * np.expm1(l1 - l2) / (l1 - l2)


def reference_derivative(A, H, divided_difference):
    """Daleckii-Krein: df(A)[H] = Q (D o (Q^T H Q)) Q^T with D_ij = f[l_i, l_j]."""
    lam, Q = np.linalg.eigh(A)
    D = np.array([[divided_difference(li, lj) for lj in lam] for li in lam])
    return Q @ (D * (Q.T @ H @ Q)) @ Q.T


def random_spd_matrices(count):
    rng = np.random.default_rng(RNG_SEED)
    mats = []
    for _ in range(count):
        l1, l2 = np.exp(rng.uniform(-1.5, 1.5, size=2))
        mats.append(spd_with_eigenvalues(l1, l2, rng.uniform(0, np.pi)))
    return mats


# Eigenvalue pairs around the series/exact switch (d/m = 1e-2 for log, d = 1e-2 for exp),
# nearly equal, and exactly equal.
NEAR_EQUAL = [(2.0, 2.0 * (1 + r)) for r in (0.0, 1e-15, 1e-13, 1e-9, 1e-6, 1e-3, 1.99e-2, 2.01e-2, 1e-1)] + [
    (0.3, 0.3 + 2e-2 * (1 - 1e-9)),
    (0.3, 0.3 + 2e-2 * (1 + 1e-9)),
    (1.0, 1.0),
]


def symmetric_direction(rng):
    H = rng.standard_normal((2, 2))
    return 0.5 * (H + H.T)


@pytest.mark.parametrize("fn, f_np", [(sym2_log, np.log), (sym2_exp, np.exp)])
def test_values_random_spd(fn, f_np):
    for A in random_spd_matrices(50):
        ref = reference_function(A, f_np)
        got = np.asarray(VALUE[fn](jnp.asarray(A)))
        assert np.linalg.norm(got - ref) <= 1e-13 * np.linalg.norm(ref)
        assert np.array_equal(got, got.T)


@pytest.mark.parametrize("fn, f_np", [(sym2_log, np.log), (sym2_exp, np.exp)])
@pytest.mark.parametrize("l1, l2", NEAR_EQUAL)
def test_values_near_equal_eigenvalues(fn, f_np, l1, l2):
    for angle in (0.0, 0.3, np.pi / 4):
        A = spd_with_eigenvalues(l1, l2, angle)
        ref = reference_function(A, f_np)
        got = np.asarray(VALUE[fn](jnp.asarray(A)))
        assert np.linalg.norm(got - ref) <= 1e-13 * max(np.linalg.norm(ref), 1.0)


def test_log_of_identity_is_zero_and_log_of_diagonal_is_exact():
    assert np.array_equal(np.asarray(sym2_log(jnp.eye(2))), np.zeros((2, 2)))
    got = np.asarray(sym2_log(jnp.diag(jnp.array([3.0, 0.5]))))
    np.testing.assert_allclose(got, np.diag(np.log([3.0, 0.5])), rtol=1e-15, atol=1e-16)


def test_exp_inverts_log():
    for A in random_spd_matrices(20) + [spd_with_eigenvalues(l1, l2, 0.7) for l1, l2 in NEAR_EQUAL]:
        back = np.asarray(VALUE[sym2_exp](VALUE[sym2_log](jnp.asarray(A))))
        assert np.linalg.norm(back - A) <= 1e-13 * np.linalg.norm(A)


@pytest.mark.parametrize(
    "fn, scale", [(sym2_log, lambda a: 1.0 / a), (sym2_exp, np.exp)], ids=["log", "exp"]
)
@pytest.mark.parametrize("a", [2.0, 1.0, 0.37])
def test_derivative_exactly_at_equal_eigenvalues(fn, scale, a):
    # At A = a I: d log(A)[H] = H / a, d exp(A)[H] = e^a H, for every symmetric H.
    rng = np.random.default_rng(RNG_SEED)
    A = a * jnp.eye(2)
    jac_fwd = np.asarray(JAC_FWD[fn](A))
    jac_rev = np.asarray(JAC_REV[fn](A))
    assert np.all(np.isfinite(jac_fwd)) and np.all(np.isfinite(jac_rev))
    for _ in range(3):
        H = symmetric_direction(rng)
        expected = scale(a) * H
        np.testing.assert_allclose(np.einsum("ijkl,kl->ij", jac_fwd, H), expected, rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(np.einsum("ijkl,kl->ij", jac_rev, H), expected, rtol=1e-14, atol=1e-15)
        tangent = JVP[fn](A, jnp.asarray(H))
        np.testing.assert_allclose(np.asarray(tangent), expected, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize(
    "fn, f_np, dd",
    [(sym2_log, np.log, divided_difference_log), (sym2_exp, np.exp, divided_difference_exp)],
    ids=["log", "exp"],
)
@pytest.mark.parametrize("l1, l2", NEAR_EQUAL + [(0.5, 3.0)])
def test_derivative_near_equal_eigenvalues(fn, f_np, dd, l1, l2):
    rng = np.random.default_rng(RNG_SEED + 1)
    A = spd_with_eigenvalues(l1, l2, 0.4)
    jac = np.asarray(JAC_FWD[fn](jnp.asarray(A)))
    assert np.all(np.isfinite(jac))
    for _ in range(3):
        H = symmetric_direction(rng)
        got = np.einsum("ijkl,kl->ij", jac, H)
        exact = reference_derivative(A, H, dd)
        assert np.linalg.norm(got - exact) <= 1e-12 * np.linalg.norm(exact)
        # Independent check: central finite difference (truncation ~h^2, roundoff ~eps/h).
        h = 1e-5
        fd = (reference_function(A + h * H, f_np) - reference_function(A - h * H, f_np)) / (2 * h)
        assert np.linalg.norm(got - fd) <= 1e-8 * np.linalg.norm(exact)


LOG_DERIVATIVE = jax.jit(sym2_log_derivative)


@pytest.mark.parametrize("l1, l2", NEAR_EQUAL + [(0.5, 3.0)])
def test_log_derivative_in_several_directions_is_the_jvp_of_the_log(l1, l2):
    """sym2_log_derivative's directions at once equal the log's jvp in each (both branches and the switch
    between them), and Daleckii-Krein's derivative; directions need not be symmetric (only their
    symmetric part counts, as for the log itself)."""
    rng = np.random.default_rng(RNG_SEED + 2)
    A = jnp.asarray(spd_with_eigenvalues(l1, l2, 0.4))
    H = jnp.asarray(np.stack([symmetric_direction(rng) for _ in range(3)] + [rng.standard_normal((2, 2))]))
    value, derivative = LOG_DERIVATIVE(A, H)
    assert np.array_equal(np.asarray(value), np.asarray(VALUE[sym2_log](A)))
    for H_i, got in zip(H, np.asarray(derivative)):
        jvp = np.asarray(JVP[sym2_log](A, H_i))
        scale = np.linalg.norm(jvp)
        assert np.linalg.norm(got - jvp) <= 1e-13 * scale
        exact = reference_derivative(np.asarray(A), 0.5 * np.asarray(H_i + H_i.T), divided_difference_log)
        assert np.linalg.norm(got - exact) <= 1e-12 * scale


def test_second_derivative_of_log_at_equal_eigenvalues():
    # Second derivatives of the log at A = 2I (d^2 log(A)[H, H] = -H^2 / 4 there): the series branch is a
    # polynomial in t, so every order is finite and exact.
    H = jnp.array([[0.3, -0.7], [-0.7, 1.1]])
    second = jax.jit(lambda A, H: jax.jvp(lambda B: jax.jvp(sym2_log, (B,), (H,))[1], (A,), (H,))[1])
    expected = -np.asarray(H @ H) / 4.0
    np.testing.assert_allclose(np.asarray(second(2.0 * jnp.eye(2), H)), expected, rtol=1e-13, atol=1e-15)


def test_vmap_and_jit():
    mats = jnp.asarray(np.stack(random_spd_matrices(8) + [np.eye(2)]))
    batched = jax.jit(jax.vmap(sym2_log))(mats)
    for A, got in zip(mats, batched):
        np.testing.assert_allclose(np.asarray(got), np.asarray(sym2_log(A)), rtol=1e-15, atol=1e-16)


def test_safe_norm_value_and_gradient():
    x = jnp.array([3.0, -4.0])
    assert float(safe_norm(x)) == 5.0
    np.testing.assert_allclose(np.asarray(jax.grad(safe_norm)(x)), [0.6, -0.8], rtol=1e-15)
    zero = jnp.zeros(3)
    assert float(safe_norm(zero)) == 0.0
    for grad in (jax.jit(jax.grad(safe_norm))(zero), jax.jit(jax.jacfwd(safe_norm))(zero)):
        assert np.array_equal(np.asarray(grad), np.zeros(3))
    assert np.all(np.isfinite(np.asarray(jax.jit(jax.hessian(safe_norm))(zero))))


def test_safe_norm_axis():
    x = jnp.array([[3.0, 4.0], [0.0, 0.0]])
    np.testing.assert_array_equal(np.asarray(safe_norm(x, axis=1)), [5.0, 0.0])
    jac = np.asarray(jax.jacrev(lambda y: safe_norm(y, axis=1))(x))
    assert np.all(np.isfinite(jac))
    np.testing.assert_allclose(jac[0, 0], [0.6, 0.8], rtol=1e-15)
    np.testing.assert_array_equal(jac[1], np.zeros((2, 2)))
