"""Kink-safe tensor helpers, written once and tested at their kinks.

- `safe_norm`: Euclidean norm whose value and gradient are 0 at x = 0.
- `sym2_log`, `sym2_exp`: matrix logarithm and exponential of a symmetric 2x2 matrix, in closed form,
  differentiable (forward and reverse mode, to any order the Taylor branch allows) at equal
  eigenvalues without `eigh` and without random perturbation; `sym2_log_derivative`: the logarithm's
  directional derivatives, several at once.

The isotropic function of a symmetric 2x2 matrix A with eigenvalues l1,2 = m +/- d, where
m = tr(A)/2 and d^2 = ((A11 - A22)/2)^2 + A12^2, is (Cayley-Hamilton)

    f(A) = a0 I + a1 A,   a1 = (f(l1) - f(l2)) / (l1 - l2),   a0 = (f(l1) + f(l2))/2 - a1 m,

evaluated here as f(A) = s0 I + a1 (A - m I) with s0 = (f(l1) + f(l2))/2, so the traceless part
A - m I is never formed from a difference of large numbers. Both s0 and a1 are even in d, hence
analytic functions of t = d^2; when d is tiny relative to the function's scale they are evaluated by
their Taylor series in t (no sqrt, so no kink), otherwise exactly. The two branches are joined by the
double-`where` trick, so the untaken branch never sees an argument that makes its derivative NaN.
"""

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp

__all__ = ["safe_norm", "sym2_log", "sym2_log_derivative", "sym2_exp", "det2", "inv2"]

# Series branch when d < _SERIES_RATIO * scale. The series below keeps terms up to t^3, so its
# truncation error is ~ ratio^8 = 1e-16; the exact branch loses ~ eps / ratio = 2e-14 to cancellation
# in the derivative of a1 just above the switch. Values are accurate to eps either way.
_SERIES_RATIO = 1e-2
_N_TAYLOR = 8  # Taylor coefficients c_0 .. c_7 of f about the mean


def safe_norm(x: jax.Array, axis: int | tuple[int, ...] | None = None) -> jax.Array:
    """Euclidean norm sqrt(sum x^2) over `axis` (all axes if None), with value 0 and gradient 0 at x = 0.

    The plain norm has gradient x / |x|, which is 0/0 = NaN at the origin. The inner `where` feeds
    sqrt a positive dummy where the sum is 0, so the untaken branch has a finite derivative; the outer
    `where` returns 0 there (a subgradient, the natural choice for the kinks of contact and plasticity).
    """
    squared = jnp.sum(x * x, axis=axis)
    nonzero = squared > 0
    squared_safe = jnp.where(nonzero, squared, jnp.ones_like(squared))
    return jnp.where(nonzero, jnp.sqrt(squared_safe), jnp.zeros_like(squared))


def _sym2_branches(t: jax.Array, scale: jax.Array):
    """(use_series, t_series, t_exact, d): which branch of :func:`_sym2_coefficients` each matrix takes (the
    series where d = sqrt(t) is below _SERIES_RATIO * ``scale``), and each branch's arguments. Double where on
    both branches: each sees only arguments where it and its derivative are finite. The series sees t = 0
    outside its region (a large t^3 could overflow); the exact branch sees d = 2 * threshold inside it, which
    keeps m - d in f's domain (log) and 1/d finite."""
    threshold = _SERIES_RATIO * scale
    use_series = t < threshold * threshold
    t_series = jnp.where(use_series, t, jnp.zeros_like(t))
    t_exact = jnp.where(use_series, 4.0 * threshold * threshold, t)
    return use_series, t_series, t_exact, jnp.sqrt(t_exact)


def _sym2_coefficients(
    mean: jax.Array,
    t: jax.Array,
    f: Callable[[jax.Array], jax.Array],
    taylor: Callable[[jax.Array], list[jax.Array]],
    scale: Callable[[jax.Array], jax.Array],
) -> tuple[jax.Array, jax.Array]:
    """(s0, a1) of f(A) = s0 I + a1 (A - m I) from the mean m of A's eigenvalues and t = d^2.

    Args:
        mean, t: m = tr(A) / 2 and t = ((A11 - A22)/2)^2 + A12^2.
        f: scalar function applied to the eigenvalues.
        taylor: m -> [c_0, ..., c_7], the Taylor coefficients c_j = f^(j)(m) / j! about the mean.
        scale: m -> length over which f varies near m (m for log, 1 for exp); the series branch is
            taken when d < _SERIES_RATIO * scale.

    With t = d^2: s0 = sum_k c_2k t^k and a1 = sum_k c_(2k+1) t^k (series), or
    s0 = (f(m+d) + f(m-d)) / 2 and a1 = (f(m+d) - f(m-d)) / (2d) (exact).
    """
    use_series, t_series, t_exact, d = _sym2_branches(t, scale(mean))
    coeffs = taylor(mean)
    s0_series = coeffs[0] + t_series * (coeffs[2] + t_series * (coeffs[4] + t_series * coeffs[6]))
    a1_series = coeffs[1] + t_series * (coeffs[3] + t_series * (coeffs[5] + t_series * coeffs[7]))

    f_plus, f_minus = f(mean + d), f(mean - d)
    s0_exact = 0.5 * (f_plus + f_minus)
    a1_exact = (f_plus - f_minus) / (2.0 * d)

    return jnp.where(use_series, s0_series, s0_exact), jnp.where(use_series, a1_series, a1_exact)


def _sym2_invariants(A: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """(m, (A11 - A22)/2, the symmetric off-diagonal entry, t = d^2) of the 2x2 matrices A (..., 2, 2)."""
    mean = 0.5 * (A[..., 0, 0] + A[..., 1, 1])
    half_diff = 0.5 * (A[..., 0, 0] - A[..., 1, 1])
    off = 0.5 * (A[..., 0, 1] + A[..., 1, 0])
    return mean, half_diff, off, half_diff * half_diff + off * off  # t: no sqrt, so smooth at equal eigenvalues


def _sym2_from(s0: jax.Array, a1: jax.Array, half_diff: jax.Array, off: jax.Array) -> jax.Array:
    """The symmetric (..., 2, 2) matrix s0 I + a1 [[h, o], [o, -h]]."""
    diagonal = a1 * half_diff
    return jnp.stack([jnp.stack([s0 + diagonal, a1 * off], axis=-1),
                      jnp.stack([a1 * off, s0 - diagonal], axis=-1)], axis=-2)


def _sym2_isotropic(
    A: jax.Array,
    f: Callable[[jax.Array], jax.Array],
    taylor: Callable[[jax.Array], list[jax.Array]],
    scale: Callable[[jax.Array], jax.Array],
) -> jax.Array:
    """Isotropic matrix function f(A) of a symmetric 2x2 matrix A, shape (2, 2) (only its symmetric part
    is used; f, taylor and scale as :func:`_sym2_coefficients`)."""
    mean, half_diff, off, t = _sym2_invariants(A)
    s0, a1 = _sym2_coefficients(mean, t, f, taylor, scale)
    return _sym2_from(s0, a1, half_diff, off)


def _log_taylor(m: jax.Array) -> list[jax.Array]:
    # log(m + x) = log m + sum_{j>=1} (-1)^(j-1) x^j / (j m^j)
    inv_m = 1.0 / m
    return [jnp.log(m)] + [((-1.0) ** (j - 1) / j) * inv_m**j for j in range(1, _N_TAYLOR)]


def _exp_taylor(m: jax.Array) -> list[jax.Array]:
    # exp(m + x) = e^m sum_j x^j / j!
    em = jnp.exp(m)
    return [em / math.factorial(j) for j in range(_N_TAYLOR)]


def sym2_log(A: jax.Array) -> jax.Array:
    """Principal matrix logarithm of a symmetric positive-definite 2x2 matrix.

    Args:
        A: (2, 2) SPD matrix (e.g. the in-plane block of the elastic left Cauchy-Green tensor b^e).

    Returns:
        (2, 2) symmetric log(A) = sum_i log(l_i) n_i n_i^T, in closed form; exact derivatives at
        equal eigenvalues (at A = l I, d log(A)[H] = H / l).
    """
    return _sym2_isotropic(A, jnp.log, _log_taylor, lambda m: m)


def sym2_log_derivative(A: jax.Array, H: jax.Array) -> tuple[jax.Array, jax.Array]:
    """log(A) and its directional derivatives d log(A)[H] for a batch of directions H (k, 2, 2).

    Differentiating f(A) = s0 I + a1 (A - m I) gives
    d f[H] = ds0 I + da1 (A - m I) + a1 (H - dm I), with dm = tr(H) / 2, dt = 2 (h dh + o do), and
    (ds0, da1) from the four partial derivatives of (s0, a1) in (m, t), in closed form on either branch
    (:func:`_log_coefficient_partials`) and taken once for all the directions: what
    ``jax.jvp(sym2_log, (A,), (H_i,))`` gives in each direction (to round-off, ``tests/test_tensor.py``).
    """
    mean, half_diff, off, t = _sym2_invariants(A)
    s0, a1 = _sym2_coefficients(mean, t, jnp.log, _log_taylor, lambda x: x)
    (s0_m, a1_m), (s0_t, a1_t) = _log_coefficient_partials(mean, t, a1)
    h_mean, h_half_diff, h_off, _ = _sym2_invariants(H)
    h_t = 2.0 * (half_diff * h_half_diff + off * h_off)
    ds0 = s0_m * h_mean + s0_t * h_t
    da1 = a1_m * h_mean + a1_t * h_t
    derivative = _sym2_from(ds0, da1, half_diff, off) + _sym2_from(jnp.zeros_like(ds0), a1, h_half_diff, h_off)
    return _sym2_from(s0, a1, half_diff, off), derivative


def _log_coefficient_partials(mean: jax.Array, t: jax.Array, a1: jax.Array):
    """((ds0/dm, da1/dm), (ds0/dt, da1/dt)) of the log's coefficients (:func:`_sym2_coefficients`, whose
    a1 is given), on the same branches. Series: the Taylor coefficients about the mean obey
    dc_j/dm = (j + 1) c_(j+1). Exact, with p, q = m +- d: ds0/dm = (1/p + 1/q)/2, da1/dm = (1/p - 1/q)/(2d),
    ds0/dt = da1/dm / 2 and da1/dt = (ds0/dm - a1) / (2t)."""
    use_series, t_series, t_exact, d = _sym2_branches(t, mean)
    c = _log_taylor(mean)
    c.append(-(1.0 / mean) ** _N_TAYLOR / _N_TAYLOR)   # c_8: the derivative of c_7's term
    series = ((c[1] + t_series * (3.0 * c[3] + t_series * (5.0 * c[5] + t_series * 7.0 * c[7]))),
              (2.0 * c[2] + t_series * (4.0 * c[4] + t_series * (6.0 * c[6] + t_series * 8.0 * c[8])))), \
             ((c[2] + t_series * (2.0 * c[4] + t_series * 3.0 * c[6])),
              (c[3] + t_series * (2.0 * c[5] + t_series * 3.0 * c[7])))
    inv_p, inv_q = 1.0 / (mean + d), 1.0 / (mean - d)
    s0_m = 0.5 * (inv_p + inv_q)
    a1_m = (inv_p - inv_q) / (2.0 * d)
    # Off its branch, a1 is the series' value and t_exact a dummy: finite, and not selected.
    exact = (s0_m, a1_m), (0.5 * a1_m, (s0_m - a1) / (2.0 * t_exact))
    return jax.tree_util.tree_map(lambda a, b: jnp.where(use_series, a, b), series, exact)


def sym2_exp(A: jax.Array) -> jax.Array:
    """Matrix exponential of a symmetric 2x2 matrix.

    Args:
        A: (2, 2) symmetric matrix (e.g. twice the in-plane logarithmic elastic strain).

    Returns:
        (2, 2) symmetric exp(A) = sum_i exp(l_i) n_i n_i^T, in closed form; exact derivatives at
        equal eigenvalues (at A = a I, d exp(A)[H] = e^a H).
    """
    return _sym2_isotropic(A, jnp.exp, _exp_taylor, jnp.ones_like)


def det2(F: jax.Array) -> jax.Array:
    """Determinant of 2x2 matrices (..., 2, 2) in closed form (no batched LU for tiny matrices)."""
    return F[..., 0, 0] * F[..., 1, 1] - F[..., 0, 1] * F[..., 1, 0]


def inv2(F: jax.Array) -> jax.Array:
    """Inverse of 2x2 matrices (..., 2, 2) in closed form (the adjugate over the determinant)."""
    adj = jnp.stack([jnp.stack([F[..., 1, 1], -F[..., 0, 1]], axis=-1),
                     jnp.stack([-F[..., 1, 0], F[..., 0, 0]], axis=-1)], axis=-2)
    return adj / det2(F)[..., None, None]
