"""Exact complementarity for node-to-rigid contact: the contact LCP, Lemke, and semismooth Newton.

Benchmarks spec sections 1.7 (LCP of the linearised problem) and 1.8 (force-driven tools).

The problem. At a Newton iterate the bulk operators, condensed on the ``n_c`` candidate nodes and
rotated into their local (n, t) frames, give

    K* du_c = r* + p,        du_c, p: (2 n_c,), per candidate (normal, tangential)

with ``p = (R_N, R_T)`` the contact forces on the sheet (N/mm) and ``du_c`` the displacement
increments (mm). The linearised kinematics are ``g_N = g_N^i + du_N`` and ``s = s^i + du_T``
(gap and step slip, mm). The contact law is Signorini and 2D Coulomb (spec 1.4):

    g_N >= 0,  R_N >= 0,  g_N R_N = 0,
    |R_T| <= mu R_N,   |R_T| < mu R_N => s = 0,   s != 0 => R_T = -mu R_N sign(s).

Two solvers of the same problem, which must agree (spec 1.7: "(a) and (b) give the same contact
forces and displacements to solver tolerance"):

* :func:`lemke` on the LCP of :func:`contact_lcp` (NumPy, host side; the reference). Lemke's
  complementary pivoting (Lemke 1965; Cottle, Pang & Stone, *The Linear Complementarity Problem*,
  1992, sections 4.4 and 4.9) with covering vector e = 1 and the lexicographic minimum ratio test.
* :func:`ssn_contact`: Alart-Curnier nonsmooth equations (Alart & Curnier 1991) solved by the
  primal-dual active-set form of semismooth Newton (Hintermueller, Ito & Kunisch 2002), in JAX
  (``jit``, ``vmap``, one ``lax.while_loop``).

What is unique. For two solutions, ``du . K* du = sum dg dR_N + ds dR_T <= mu sum |dR_N| |ds|``
(differences marked d). So for K* positive definite (not necessarily symmetric) and mu small
against the normal-tangential coupling of K*, ``du_c``, ``p`` and the tool increments ``dq`` are
unique; for large mu they need not be (Klarbring 1990): on a clamped strip with mu = 0.99 Lemke
and SSN return different valid solutions. The LCP multipliers are never unique: on an open
candidate R_N = 0 forces R_T = 0, so phi+ = phi- = 0 and only ``s = lambda- - lambda+`` is fixed;
on a closed frictionless candidate the same holds. Compare solutions through
:func:`contact_solution`, never through ``z``.

Force-driven tools (spec 1.8). ``n_q`` tools whose positions q_k are unknown get one extra LCP row
and column each; see :class:`ForceDrive` for the equations.

Units: lengths mm, forces N/mm (per unit width), stiffness N/mm per mm.
"""

from __future__ import annotations

import enum
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from scipy.linalg import lapack
from scipy.linalg.blas import dger

from ._checks import is_concrete
from .status import OPEN, STICK, contact_status

__all__ = [
    "ForceDrive",
    "LemkeStatus",
    "LemkeResult",
    "LemkeContactResult",
    "SSNResult",
    "lemke",
    "lemke_callback",
    "lemke_contact_callback",
    "lemke_start",
    "polish",
    "contact_lcp",
    "contact_solution",
    "lemke_contact",
    "ssn_contact",
    "ssn_start",
    "diagonal_parameters",
]

DEFAULT_SHIFT = 1e3    # mm: alpha of spec 1.8, larger than any tool increment |dq|
_NOISE = 1e-11         # relative round-off scale of the basic values in Lemke (ties within it)
_MEMORY = 5            # semismooth Newton: iterates in the non-monotone line search reference
_ARMIJO = 1e-4         # sufficient decrease factor
_MIN_STEP = 2.0**-30   # smallest step before the line search gives up


# --------------------------------------------------------------------------------------------
# Force-driven tools
# --------------------------------------------------------------------------------------------


class ForceDrive(eqx.Module):
    """Force-driven tools of the condensed contact problem (spec 1.8).

    Tool k moves by ``dq_k`` (mm) along its closing direction e_q,k. The candidates it touches
    see it in their kinematics, and its equilibrium along e_q,k is one extra equation:

        g_N,a = g_N,a^i + du_N,a - sum_k (e_q,k . n_a) dq_k
        s_a   = s_a^i   + du_T,a - sum_k (e_q,k . t_a) dq_k
        r_q,k = sum_a [(e_q,k . n_a) R_N,a + (e_q,k . t_a) R_T,a] - P_k = 0

    In matrix form, with ``C = coupling`` (2 n_c, n_q): ``(g_N, s) = (g^i, s^i) + du_c - C dq``
    and ``C^T p = P``. The same matrix is the kinematic column and the equilibrium row, because
    both are projections on e_q (the tool's virtual work ``dq . C^T p``); the bordered system
    stays symmetric whenever K* is.

    Attributes:
        coupling: (2 n_c, n_q), ordered like K* (normal, tangential per candidate):
            ``coupling[2a, k] = e_q,k . n_a`` and ``coupling[2a + 1, k] = e_q,k . t_a`` when
            candidate a belongs to tool k, 0 otherwise. Dimensionless.
        force: (n_q,) prescribed closing forces P_k >= 0, N/mm.
        shift: alpha, mm. The LCP pairs the tool row with ``z_q = dq + alpha``, which must stay
            > 0 so that complementarity forces the equality ``r_q = 0``; alpha must exceed any
            |dq| (default 1e3 mm, spec 1.8). Not used by :func:`ssn_contact`.
    """

    coupling: jax.Array
    force: jax.Array
    shift: float = DEFAULT_SHIFT

    def __check_init__(self):
        if jnp.ndim(self.coupling) != 2 or jnp.shape(self.coupling)[0] % 2:
            raise ValueError(f"ForceDrive field 'coupling' must have shape (2 n_c, n_q), "
                             f"got {jnp.shape(self.coupling)}")
        if jnp.shape(self.force) != (jnp.shape(self.coupling)[1],):
            raise ValueError(f"ForceDrive field 'force' must have shape (n_q,) = "
                             f"({jnp.shape(self.coupling)[1]},), got {jnp.shape(self.force)}")
        if is_concrete(self.shift) and not float(self.shift) > 0.0:
            raise ValueError(f"ForceDrive field 'shift' must be > 0 mm, got {self.shift}")

    @classmethod
    def single(cls, e_dot_n, e_dot_t, force, shift: float = DEFAULT_SHIFT) -> ForceDrive:
        """One tool: ``e_dot_n``, ``e_dot_t`` (n_c,) are e_q . n_a and e_q . t_a (0 for the
        candidates of other tools), ``force`` the scalar P (N/mm)."""
        e_dot_n, e_dot_t = jnp.asarray(e_dot_n), jnp.asarray(e_dot_t)
        coupling = jnp.stack([e_dot_n, e_dot_t], axis=-1).reshape(-1, 1)
        return cls(coupling=coupling, force=jnp.reshape(jnp.asarray(force, coupling.dtype), (1,)),
                   shift=shift)

    @property
    def num_tools(self) -> int:
        """n_q (static)."""
        return self.coupling.shape[1]

    def increment(self, z: jax.Array) -> jax.Array:
        """Tool increments ``dq = z_q - alpha`` (n_q,) from an LCP solution of size 3 n_c + n_q."""
        return z[z.shape[0] - self.num_tools:] - self.shift


def _coupling(drive: ForceDrive | None, n_c: int, dtype):
    """(C, P): the coupling matrix (2 n_c, n_q) and forces (n_q,); empty when no tool is force-driven."""
    if drive is None:
        return jnp.zeros((2 * n_c, 0), dtype), jnp.zeros((0,), dtype)
    if drive.coupling.shape[0] != 2 * n_c:
        raise ValueError(f"ForceDrive.coupling has {drive.coupling.shape[0]} rows, expected 2 n_c = {2 * n_c}")
    return jnp.asarray(drive.coupling, dtype), jnp.asarray(drive.force, dtype)


# --------------------------------------------------------------------------------------------
# The contact LCP (spec 1.7 steps 2-6, 1.8)
# --------------------------------------------------------------------------------------------


def _interleave(normal: jax.Array, tangential: jax.Array) -> jax.Array:
    """(n_c,), (n_c,) -> (2 n_c,) in K* order (normal, tangential per candidate)."""
    return jnp.stack([normal, tangential], axis=-1).reshape(-1)


def _check_shapes(K_star, r_star, gap, slip, mu=None):
    n_c = jnp.shape(gap)[0]
    want = {"K_star": (2 * n_c, 2 * n_c), "r_star": (2 * n_c,), "slip": (n_c,)}
    if mu is not None:
        want["mu"] = (n_c,)
    got = {"K_star": jnp.shape(K_star), "r_star": jnp.shape(r_star), "slip": jnp.shape(slip)}
    if mu is not None:
        got["mu"] = jnp.shape(mu)
    for name, shape in want.items():
        if got[name] != shape:
            raise ValueError(f"'{name}' must have shape {shape} for n_c = {n_c} candidates, got {got[name]}")
    if mu is not None and is_concrete(mu) and np.any(np.asarray(mu) < 0):
        raise ValueError("friction coefficients 'mu' must be >= 0")
    return n_c


def _facet_matrix(mu: jax.Array) -> jax.Array:
    """A per candidate, (n_c, 3, 2): rows (R_N, phi+, phi-) = [[1, 0], [mu, -1], [mu, 1]] (R_N, R_T)."""
    one, zero = jnp.ones_like(mu), jnp.zeros_like(mu)
    return jnp.stack([jnp.stack([one, zero], -1), jnp.stack([mu, -one], -1), jnp.stack([mu, one], -1)], -2)


# B per candidate: du = (g_N, lambda-  - lambda+) + d0, i.e. (du_N, du_T) = B (g_N, lambda+, lambda-) + d0.
_B = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 1.0]])


def contact_lcp(K_star, r_star, gap, slip, mu, drive: ForceDrive | None = None):
    """The LCP ``w = M z + q, z >= 0, w >= 0, z.w = 0`` of the linearised contact problem.

    Per candidate (spec 1.7), ``z = (g_N, lambda+, lambda-)`` and ``w = (R_N, phi+, phi-)`` with
    ``phi+- = mu R_N -+ R_T`` and ``s = lambda- - lambda+``, so that

        du_c = B z + d0,    p = K* du_c - r*,    w = A p,
        M = A K* B,         q = A (K* d0 - r*),

    ``A = [[1, 0], [mu, -1], [mu, 1]]``, ``B = [[1, 0, 0], [0, -1, 1]]``, ``d0 = (-g_N^i, -s^i)``.

    With a :class:`ForceDrive` (spec 1.8) the unknowns gain ``z_q = dq + alpha`` (n_q,) and the
    rows gain ``w_q = C^T p - P``; with ``d0' = d0 - alpha C 1``:

        du_c = B z + C z_q + d0',
        M = [[A K* B, A K* C], [C^T K* B, C^T K* C]],
        q = [A (K* d0' - r*), C^T (K* d0' - r*) - P].

    Args:
        K_star: (2 n_c, 2 n_c) condensed stiffness in the (n, t) frames, N/mm per mm.
        r_star: (2 n_c,) condensed residual, N/mm.
        gap: (n_c,) normal gaps g_N^i at the iterate (negative: penetration), mm.
        slip: (n_c,) step slips s^i at the iterate, mm.
        mu: (n_c,) friction coefficients >= 0.
        drive: force-driven tools, or None.

    Returns:
        (M, q): shapes (3 n_c + n_q, 3 n_c + n_q) and (3 n_c + n_q,).
    """
    n_c = _check_shapes(K_star, r_star, gap, slip, mu)
    K_star, r_star = jnp.asarray(K_star), jnp.asarray(r_star)
    dtype = K_star.dtype
    C, P = _coupling(drive, n_c, dtype)
    A = _facet_matrix(jnp.asarray(mu, dtype))                         # (n_c, 3, 2)
    B = jnp.asarray(_B, dtype)
    d0 = -_interleave(jnp.asarray(gap, dtype), jnp.asarray(slip, dtype))
    if drive is not None:
        d0 = d0 - drive.shift * jnp.sum(C, axis=1)

    K4 = K_star.reshape(n_c, 2, n_c, 2)
    AK = jnp.einsum("iab,ibjc->iajc", A, K4)                          # A K*, (n_c, 3, n_c, 2)
    M = jnp.einsum("iajc,cd->iajd", AK, B).reshape(3 * n_c, 3 * n_c)
    f0 = K_star @ d0 - r_star                                         # p at z = 0
    q = jnp.einsum("iab,ib->ia", A, f0.reshape(n_c, 2)).reshape(-1)
    if drive is None:
        return M, q
    AKC = AK.reshape(3 * n_c, 2 * n_c) @ C                            # (3 n_c, n_q)
    KB = jnp.einsum("iajc,cd->iajd", K4, B).reshape(2 * n_c, 3 * n_c)  # K* B
    M = jnp.block([[M, AKC], [C.T @ KB, C.T @ K_star @ C]])
    q = jnp.concatenate([q, C.T @ f0 - P])
    return M, q


def contact_solution(K_star, r_star, gap, slip, z, drive: ForceDrive | None = None):
    """Displacements and forces from an LCP solution (spec 1.7 step 6): the unique parts.

    ``du_c = B z + d0 (+ C dq)``, ``p = K* du_c - r*``.

    Args:
        K_star, r_star, gap, slip, drive: as for :func:`contact_lcp`.
        z: (3 n_c + n_q,) LCP solution.

    Returns:
        (du_c, p): (2 n_c,) displacement increments (mm) and contact forces (R_N, R_T) on the
        sheet (N/mm). The tool increments are ``drive.increment(z)``.
    """
    n_c = _check_shapes(K_star, r_star, gap, slip)
    K_star = jnp.asarray(K_star)
    z = jnp.asarray(z, K_star.dtype)
    C, _ = _coupling(drive, n_c, K_star.dtype)
    dq = drive.increment(z) if drive is not None else jnp.zeros((0,), K_star.dtype)
    return _recover(K_star, r_star, gap, slip, z[: 3 * n_c], dq, C)


def _recover(K_star, r_star, gap, slip, z_c, dq, C):
    """``du_c = B z_c + d0 + C dq``, ``p = K* du_c - r*``."""
    dtype = K_star.dtype
    du = jnp.einsum("ab,ib->ia", jnp.asarray(_B, dtype), z_c.reshape(-1, 3)).reshape(-1)
    du = du - _interleave(jnp.asarray(gap, dtype), jnp.asarray(slip, dtype)) + C @ dq
    return du, K_star @ du - jnp.asarray(r_star, dtype)


# --------------------------------------------------------------------------------------------
# Lemke's algorithm (NumPy reference)
# --------------------------------------------------------------------------------------------


class LemkeStatus(enum.IntEnum):
    SOLVED = 0
    RAY = 1               # ray termination: no blocking variable (infeasible, or not processable)
    MAX_PIVOTS = 2        # pivot budget exhausted
    SHIFT_TOO_SMALL = 3   # lemke_contact only: z_q = 0, the tool shift alpha is smaller than |dq|
    INACCURATE = 4        # pivoting ended (z0 left), but the point fails the check on the original data


class LemkeResult(NamedTuple):
    z: np.ndarray       # (n,) z >= 0
    w: np.ndarray       # (n,) M z + q, recomputed from z
    pivots: int         # pivots performed, the initial z0 pivot included
    status: int         # LemkeStatus
    basis: np.ndarray   # (n,) basic variable of each row: i < n is w_i, n + j is z_j, 2n is z0


def _tie_tolerance(ratio: np.ndarray) -> float:
    # Ties are judged with a relative tolerance: the exact ties of a degenerate problem (zero
    # gaps, frictionless rows phi+ = -phi-, mu = 1) arrive with round-off differences.
    return 1e-12 * max(float(np.max(np.abs(ratio))), np.finfo(float).tiny)


def _min_ratio_rows(T: np.ndarray, col: int, column: np.ndarray, q: np.ndarray, pivot_tol: float,
                    work: np.ndarray | None = None) -> np.ndarray:
    """Rows that block first when the variable of tableau column ``col`` enters.

    ``d = B^-1 a`` is the entering column (``a = column`` in the original data) and ``x = B^-1 q``
    the basic values. Their round-off is estimated from the size of the terms that cancel in the
    products, ``dx = eps (|B^-1| |q| + |x|)`` and ``dd = eps (|B^-1| |a| + |d|)``. Admissible
    pivots are ``d_i > max(pivot_tol max|d|, dd_i)``: an entry within its own round-off of 0 is
    no pivot. With ``t = min x_i / d_i``, the rows returned are those that the step t brings to 0
    within round-off, ``x_i - t d_i <= dx_i + t dd_i``.

    The contact LCP has exact ties that must be seen as such: an open candidate has
    ``w = z0 (1, 1, 1)``, so its three rows reach 0 together with z0. K* scales spread over
    decades, and the shift alpha of a force-driven tool (entries alpha K* C in q), make these
    round-off differences far larger than the last digit of x.

    ``work``: an optional (n, n) column-major buffer. When most rows may pivot, ``|B^-1|`` is then
    written into it in one pass over the contiguous first n columns of the column-major T, instead
    of gathered row by row into a new array (on the bead's n = 1536: 15 ms a pivot before, three
    times the pivot itself).
    """
    n = q.size
    d = T[:, col]
    rows = np.flatnonzero(d > pivot_tol * np.max(np.abs(d)))
    if rows.size == 0:
        return rows
    if work is not None and 2 * rows.size > n:
        B_inv = np.abs(T[:, :n], out=work)  # a contiguous block of the column-major T
        terms = np.stack([B_inv @ np.abs(column), B_inv @ np.abs(q)], axis=1)[rows]
    else:
        B_inv = np.abs(T[rows, :n])  # only the rows that may pivot
        terms = np.stack([B_inv @ np.abs(column), B_inv @ np.abs(q)], axis=1)
    noise_d = _NOISE * (terms[:, 0] + np.abs(d[rows]))
    keep = d[rows] > noise_d
    rows, terms, noise_d = rows[keep], terms[keep], noise_d[keep]
    if rows.size == 0:
        return rows
    x = T[rows, -1]
    noise_x = _NOISE * (terms[:, 1] + np.abs(x))
    t = np.min(np.maximum(x, 0.0) / d[rows])
    return rows[x - t * d[rows] <= noise_x + t * noise_d]


def _lexmin(T: np.ndarray, col: int, rows: np.ndarray, n: int) -> int:
    """The lexicographic minimum among tied ``rows``: ``(B^-1)_{i, j} / d_i`` for j = 1..n in turn.

    The first n tableau columns hold B^-1. The rows of ``[x, B^-1]`` then stay lexicographically
    positive, every pivot decreases them strictly, and cycling is excluded (Cottle-Pang-Stone 4.9).
    """
    ratios = T[rows, :n] / T[rows, col][:, None]
    j = 0
    while rows.size > 1 and j < n:
        # Columns where the tied rows agree (within the tie tolerance) decide nothing: skip to the
        # first one where they differ, in one vectorised pass instead of one Python step per column.
        rest = ratios[:, j:]
        tol = 1e-12 * np.maximum(np.max(np.abs(rest), axis=0), np.finfo(float).tiny)
        differ = np.flatnonzero(np.max(rest, axis=0) - np.min(rest, axis=0) > tol)
        if differ.size == 0:
            break
        j += int(differ[0])
        ratio = ratios[:, j]
        keep = ratio <= np.min(ratio) + _tie_tolerance(ratio)
        rows, ratios = rows[keep], ratios[keep]
        j += 1
    return int(rows[0])


def _leads_to_ray(T: np.ndarray, row: int, col: int, next_col: int, pivot_tol: float) -> bool:
    """Whether, after pivoting on (row, col), the column ``next_col`` has no admissible pivot."""
    a = T[:, next_col]
    new = a - T[:, col] * (a[row] / T[row, col])
    new[row] = a[row] / T[row, col]
    return not np.any(new > pivot_tol * np.max(np.abs(new)))


def lemke(M, q, *, max_pivots: int | None = None, pivot_tol: float = 1e-12, start=None) -> LemkeResult:
    """Solve the LCP ``w = M z + q, z >= 0, w >= 0, z.w = 0`` by Lemke's complementary pivoting.

    Lemke (1965), "Bimatrix equilibrium points and mathematical programming"; Cottle, Pang &
    Stone (1992), Algorithm 4.4.5 with the lexicographic rule of section 4.9. The augmented
    system ``w = M z + q + e z0`` (covering vector e = 1) starts from the basis of all w with
    ``z0 = -min q``; each pivot brings in the complement of the variable that just left, until
    z0 leaves (solution), no variable blocks (ray termination) or ``max_pivots`` is reached.

    Processability. Lemke solves any feasible LCP with a copositive-plus M (e.g. positive
    semidefinite). The frictional contact LCP is not copositive, but for K* positive definite and
    mu < 1 a secondary ray is impossible: a ray (z_r, t) would give ``du_r = B z_r`` with
    ``du_r . K* du_r <= 0`` (each pair contributes ``-t g_r`` or ``-(l+ + l-)(mu R_N + t) <= 0``),
    hence ``du_r = 0``, and the only remaining direction ``lambda+ = lambda-`` needs
    ``phi+ = phi- = 0`` with z0 > 0, i.e. ``mu R_N + z0 = 0`` and ``R_N + z0 >= 0``, which
    requires mu >= 1. (With force-driven tools the same holds if every tool has a candidate with
    e_q . n > 0.) So for K* positive definite and mu < 1 Lemke always ends with a solution; ray
    termination signals an indefinite K* or mu >= 1, where it does occur (a clamped strip with
    mu = 1 ends on the ray lambda+ = lambda- in every trial; SSN solves those problems).

    Degeneracy is the rule here, not the exception: an open candidate has R_N = R_T = 0, so its
    three rows reach 0 together with z0; mu = 0 makes the rows phi+ and phi- opposite; zero gaps
    and slips put zeros in q. It is handled by the lexicographic ratio test, with ties judged
    against an estimate of the round-off of each basic value (``_min_ratio_rows``). The final
    basic values are recomputed by one LU solve of the basis against the original data, so the
    round-off of the Gauss-Jordan pivots does not accumulate into the answer.

    Warm start. ``start`` names a complementary basis to begin from (True: z_i basic, False:
    w_i basic), e.g. the active set of the previous Newton iterate. If its basic solution
    ``B^-1 q`` is feasible it is the answer, after one LU solve and no pivot. Otherwise Lemke runs
    with the covering vector ``d = B 1`` in place of e: then ``B^-1 (q + d z0) = B^-1 q + z0 1``, so
    z0 enters at ``-min B^-1 q`` on the guessed basis, as the cold start does on the identity (all
    False is the cold start exactly). The processability argument above is made for d = e, and the
    rows of ``[x, B^-1]`` need not start lexicographically positive: a warm run that ends on a ray
    is restarted from the basis it reached (a few times, see ``_lemke_warm``; the slip directions of
    open candidates are first corrected from the guess's own solution), and one that does not
    end on a solution verified on the original data within ``n`` pivots per run is dropped for the
    cold start.

    Scaling. Every answer is checked on the original data (:func:`_is_solution`). One that fails it
    (a ray, the pivot budget, or an end on a basis that is not feasible) is computed again on the
    symmetrically scaled problem ``M' = D M D, q' = D q`` with ``D = |diag M|^(-1/2)`` (z = D z',
    w = D^-1 w': the same complementarity), warm then cold as before; if that fails too, the first
    run's status is returned (``INACCURATE`` where it had ended as a solution). The tableau's
    round-off follows the spread of M's scales: on the blankholder's lock (band of 256 nodes, the
    force-driven tool eliminated, diagonal of K* from 1e4 to 4e6 N/mm) an unscaled run ended after
    658 pivots on a basis whose R_N came out at -3.6e-3 N/mm and whose frictional rows were violated
    by as much, and the Newton loop cycled on it; the scaled warm start solved it in 19 pivots.
    Problems that the unscaled pivoting solves are not touched.

    Pure function of arrays (NumPy, float64), suitable for ``jax.pure_callback``
    (see :func:`lemke_callback`).

    Args:
        M: (n, n) matrix.
        q: (n,) vector.
        max_pivots: pivot budget; default 50 n.
        pivot_tol: relative pivot tolerance: a pivot must exceed ``pivot_tol`` times the largest
            entry of the entering column.
        start: optional (n,) bools, the complementary basis to start from (see "Warm start").

    Returns:
        :class:`LemkeResult` ``(z, w, pivots, status, basis)``. On failure z is the last basic
        point with z0 dropped (not a solution); ``INACCURATE`` where that point ended the pivoting
        as a solution but fails the check.
    """
    M = np.asarray(M, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64).reshape(-1)
    n = q.size
    if M.shape != (n, n):
        raise ValueError(f"M must have shape ({n}, {n}), got {M.shape}")
    if max_pivots is None:
        max_pivots = 50 * n
    if np.all(q >= 0.0):
        return LemkeResult(np.zeros(n), q.copy(), 0, int(LemkeStatus.SOLVED), np.arange(n))
    res = _lemke_path(M, q, max_pivots, pivot_tol, start)
    if res.status == LemkeStatus.SOLVED and _is_solution(M, q, res.z):
        return res
    # Not a verified solution: pivot again on the diagonally scaled problem (see "Scaling").
    scale = np.abs(np.diagonal(M))
    scale = 1.0 / np.sqrt(np.where(scale > 0.0, scale, 1.0))
    scaled = _lemke_path(scale[:, None] * M * scale[None, :], scale * q, max_pivots, pivot_tol, start)
    z = scale * scaled.z
    pivots = res.pivots + scaled.pivots
    if scaled.status == LemkeStatus.SOLVED and _is_solution(M, q, z):
        return LemkeResult(z, M @ z + q, pivots, int(LemkeStatus.SOLVED), scaled.basis)
    status = res.status if res.status != LemkeStatus.SOLVED else LemkeStatus.INACCURATE
    return res._replace(pivots=pivots, status=int(status))


def _lemke_path(M, q, max_pivots, pivot_tol, start) -> LemkeResult:
    """One run of :func:`lemke` on (M, q) as given: warm start if ``start`` guesses a basis, then cold."""
    n = q.size
    if start is not None and np.any(start):
        warm = _lemke_warm(M, q, np.asarray(start, bool).reshape(n), min(max_pivots, n), pivot_tol)
        if warm is not None:
            return warm
    # Tableau of  I w - M z - e z0 = q  ; columns: w (0..n-1), z (n..2n-1), z0 (2n), rhs (2n+1).
    # The w columns hold B^-1 of the current basis: the initial basis is the identity.
    T = np.asfortranarray(np.hstack([np.eye(n), -M, -np.ones((n, 1)), q[:, None]]))
    return _pivot(T, np.arange(n), M, q, np.ones(n), max_pivots, pivot_tol)


def _basis_columns(M, basis, d) -> np.ndarray:
    """The basis matrix: the original columns ``(I, -M, -d)`` of the basic variables."""
    n = M.shape[0]
    basis = np.asarray(basis)
    cols = np.zeros((n, n))
    w, z = np.flatnonzero(basis < n), np.flatnonzero((basis >= n) & (basis < 2 * n))
    cols[basis[w], w] = 1.0
    cols[:, z] = -M[:, basis[z] - n]
    cols[:, basis == 2 * n] = -np.asarray(d)[:, None]
    return cols


def _lemke_warm(M, q, start, max_pivots, pivot_tol, restarts: int = 3) -> LemkeResult | None:
    """Lemke from the complementary basis ``start`` (see :func:`lemke`); None if it does not end on
    a verified solution.

    A run that ends on a ray (or on a point that fails the check on the original data) is restarted
    from the complementary basis it reached, at most ``restarts`` times: the variables basic there,
    with z0 exchanged for a variable of the pair whose two variables are both non-basic. On the
    bead's clamp, where a guess from the last iterate has 40 to 60 slip directions wrong, the first
    run ends on a ray after about a hundred pivots and the restart solves in two (cold start: 1200
    pivots).

    Before pivoting, the slip direction of every open candidate is read off the guessed basis's own
    solution (:func:`_flip_opposite`): a guessed lambda that comes out negative there is exchanged for
    its opposite, which leaves the point unchanged.
    """
    n = q.size
    pivots = 0
    opposite = _opposite_columns(M)
    for _ in range(restarts + 1):
        factors = _factor_basis(M, q, start)
        if factors is None:
            return None
        flipped = _flip_opposite(M, q, start, factors.x, opposite)
        if flipped is not None:
            # Same point, other sign of a free slip: the basis changed, so factor it again.
            start = flipped
            factors = _factor_basis(M, q, start)
            if factors is None:
                return None
        basis, x = factors.basis, factors.x
        z = np.zeros(n)
        z[basis[start] - n] = np.maximum(x[start], 0.0)
        if _is_solution(M, q, z):  # the guessed basis is feasible (to round-off): no pivot
            return LemkeResult(z, M @ z + q, pivots, int(LemkeStatus.SOLVED), basis)
        T, d = _tableau(M, factors)
        res = _pivot(T, basis, M, q, d, max_pivots, pivot_tol)
        pivots += res.pivots
        if res.status == LemkeStatus.SOLVED and _is_solution(M, q, res.z):
            return res._replace(pivots=pivots)
        reached = np.isin(n + np.arange(n), res.basis)
        row = np.flatnonzero(res.basis == 2 * n)
        if row.size:
            # z0 is still basic: swap it for a variable of the pair with neither basic, the one with
            # the larger tableau entry in z0's row, so that the new basis stays nonsingular.
            k = int(np.flatnonzero(~reached & ~np.isin(np.arange(n), res.basis))[0])
            reached[k] = abs(T[row[0], n + k]) > abs(T[row[0], k])
        if np.array_equal(reached, start):
            return None
        start = reached
    return None


def _pivot(T, basis, M, q, d, max_pivots, pivot_tol) -> LemkeResult:
    """Lemke's pivoting on the tableau ``T = B^-1 [I, -M, -d, q]`` of the complementary basis
    ``basis`` (covering vector d): z0 enters first; then the complement of each leaving variable."""
    n = q.size
    z0 = 2 * n

    def original_column(var):
        """Column of ``var`` in the original system ``[I, -M, -d]``."""
        if var < n:
            return np.eye(1, n, var).ravel()
        return -M[:, var - n] if var < 2 * n else -d

    def pivot(row, col):
        T[row] /= T[row, col]
        factor = T[:, col].copy()
        factor[row] = 0.0
        # T -= factor (x) T[row], in place (BLAS rank-1 update of the column-major T): a third of
        # the time of the outer product and subtraction for n = 1536.
        out = dger(-1.0, factor, T[row].copy(), a=T, overwrite_a=True)
        if not np.shares_memory(out, T):
            T[...] = out
        basis[row] = col

    work = np.empty((n, n), order="F")
    # First pivot: z0 enters at -min x, and a row of the most negative basic value leaves.
    row = _first_leaving_row(T[:, -1])
    leaving = basis[row]
    pivot(row, z0)
    pivots = 1
    entering = _complement(int(leaving), n)
    status = LemkeStatus.MAX_PIVOTS
    while pivots < max_pivots:
        ties = _min_ratio_rows(T, entering, original_column(entering), q, pivot_tol, work)
        if ties.size == 0:
            status = LemkeStatus.RAY
            # z0 may have reached 0 within round-off together with rows judged just below it;
            # then the point is a solution, not a ray. Verified on the original data.
            z = _z_from_basis(M, q, basis, T[:, -1], d)
            if _is_solution(M, q, np.maximum(z, 0.0)):
                status = LemkeStatus.SOLVED
            break
        row = _choose_row(T, basis, entering, ties, n, pivot_tol)
        leaving = basis[row]
        pivot(row, entering)
        pivots += 1
        if leaving == z0:
            status = LemkeStatus.SOLVED
            break
        entering = _complement(int(leaving), n)

    z = _z_from_basis(M, q, basis, T[:, -1], d)
    if status == LemkeStatus.SOLVED:
        # Basic values that should be >= 0 can come back as -1e-17 after the refinement.
        z = np.maximum(z, 0.0)
    return LemkeResult(z, M @ z + q, pivots, int(status), basis.copy())


def _complement(var: int, n: int) -> int:
    return var + n if var < n else var - n


def _choose_row(T, basis, entering, ties, n, pivot_tol) -> int:
    """Leaving row among the rows ``ties`` that block first.

    z0 leaves if it is among them (that ends the algorithm). Otherwise the lexicographic rule,
    with one look-ahead on degenerate ties: a tied row whose leaving variable's complement would
    find no pivot (a ray at the next pivot) is passed over for the next row in lexicographic order.
    This matters for the contact LCP, whose columns of lambda+ and lambda- are opposite: at
    mu = 1, once phi+ = 0 with lambda+ basic, phi- = 2 (R_N + z0) reaches 0 together with the row
    of R_N; letting phi- leave brings in lambda- along the null direction lambda+ = lambda- (a
    ray), letting R_N leave continues the path. Random problems with mu = 1 go from ray
    terminations to solutions with this rule.
    """
    z0 = 2 * n
    if ties.size == 1:
        return int(ties[0])
    in_ties = basis[ties] == z0
    if np.any(in_ties):
        return int(ties[in_ties][0])
    remaining = ties
    first = None
    while remaining.size:
        row = _lexmin(T, entering, remaining, n)
        first = row if first is None else first
        if not _leads_to_ray(T, row, entering, _complement(int(basis[row]), n), pivot_tol):
            return row
        remaining = remaining[remaining != row]
    assert first is not None   # ``ties`` is never empty
    return first


def _first_leaving_row(q: np.ndarray) -> int:
    """Row leaving when z0 enters (the z0 column is -e): one of argmin q.

    After pivoting on row r, a tied row i becomes ``(q_i - q_r, e_i - e_r) = (0, e_i - e_r)``
    in ``[x, B^-1]``; it is lexicographically positive iff i < r. So the lexicographic rule takes
    the largest index among the (round-off) ties.
    """
    rows = np.flatnonzero(q <= np.min(q) + 1e-12 * np.max(np.abs(q)))
    return int(rows[-1])


def _is_solution(M, q, z) -> bool:
    """Whether ``z >= 0`` solves the LCP to round-off: ``w = M z + q >= -tol`` and, wherever
    z_i > 0, ``|w_i| <= tol``; tol is relative to the terms that cancel in each row of w."""
    w = M @ z + q
    tol = 1e3 * _NOISE * (np.abs(M) @ z + np.abs(q))
    return bool(np.all(w >= -tol) and np.all((z == 0.0) | (np.abs(w) <= tol)))


def _z_from_basis(M, q, basis, fallback, d=None):
    """z from the basis: ``B x_B = q`` solved with the original columns (I, -M, -d) by one LU
    (d = e unless given).

    Solving once with the original data, instead of reading the Gauss-Jordan tableau, keeps the
    round-off of the pivots out of the answer. ``fallback`` (the tableau's x) serves if B is
    numerically singular.
    """
    n = q.size
    cols = _basis_columns(M, basis, np.ones(n) if d is None else d)
    try:
        values = np.linalg.solve(cols, q)
    except np.linalg.LinAlgError:
        values = fallback.copy()
    z = np.zeros(n)
    in_z = (basis >= n) & (basis < 2 * n)
    z[basis[in_z] - n] = values[in_z]
    return z


def lemke_callback(M: jax.Array, q: jax.Array, *, max_pivots: int | None = None,
                   pivot_tol: float = 1e-12) -> LemkeResult:
    """:func:`lemke` called from inside ``jit`` through ``jax.pure_callback`` (``vmap`` runs it
    once per batch element). Not differentiable; returns a :class:`LemkeResult` of arrays."""
    n = q.shape[-1]

    def host(M, q):
        res = lemke(M, q, max_pivots=max_pivots, pivot_tol=pivot_tol)
        return (res.z.astype(q.dtype), res.w.astype(q.dtype), np.int32(res.pivots), np.int32(res.status),
                res.basis.astype(np.int32))

    shapes = (jax.ShapeDtypeStruct((n,), q.dtype), jax.ShapeDtypeStruct((n,), q.dtype),
              jax.ShapeDtypeStruct((), jnp.int32), jax.ShapeDtypeStruct((), jnp.int32),
              jax.ShapeDtypeStruct((n,), jnp.int32))
    return LemkeResult(*jax.pure_callback(host, shapes, M, q, vmap_method="sequential"))


class LemkeContactResult(NamedTuple):
    du_c: np.ndarray   # (2 n_c,) displacement increments of the candidates (n, t frames), mm
    p: np.ndarray      # (2 n_c,) contact forces (R_N, R_T) on the sheet, N/mm
    dq: np.ndarray     # (n_q,) increments of the force-driven tools, mm (empty without tools)
    z: np.ndarray      # (3 n_c + n_q,) LCP solution (multipliers not unique; see module doc)
    pivots: int
    status: int        # LemkeStatus


def lemke_contact(K_star, r_star, gap, slip, mu, *, drive: ForceDrive | None = None,
                  max_pivots: int | None = None, pivot_tol: float = 1e-12) -> LemkeContactResult:
    """Solve the linearised contact problem by Lemke (``lcp_lemke`` of spec 1.7), on the host.

    Builds the LCP with :func:`contact_lcp`, solves it with :func:`lemke` and recovers
    ``(du_c, p)`` as :func:`contact_solution` does. Arguments as for :func:`contact_lcp`; the
    default pivot budget is 50 (3 n_c + n_q).

    With force-driven tools the final basis is solved once more against the unshifted data:
    in ``w = M z + q`` the shift enters only through ``q = q_free - alpha M[:, tools]``, so the
    same basis with ``dq`` in place of ``z_q`` and ``q_free`` as right-hand side gives dq, du_c
    and p without the cancellation of alpha (1e3 mm) against dq (typically 1e-3 mm).
    """
    M, q = contact_lcp(K_star, r_star, gap, slip, mu, drive)
    n_q = 0 if drive is None else drive.num_tools
    shift = 0.0 if drive is None else float(drive.shift)
    z_c, dq, pivots, status, z = _lemke_unshifted(np.asarray(M), np.asarray(q), n_q, shift, max_pivots,
                                                  pivot_tol)
    K = jnp.asarray(K_star)
    C, _ = _coupling(drive, np.shape(gap)[0], K.dtype)
    du_c, p = _recover(K, r_star, gap, slip, jnp.asarray(z_c), jnp.asarray(dq), C)
    return LemkeContactResult(np.asarray(du_c), np.asarray(p), np.asarray(dq), z, pivots, status)


def _lemke_unshifted(M, q, n_q: int, shift: float, max_pivots=None, pivot_tol: float = 1e-12):
    """Lemke on (M, q) (NumPy); returns ``(z_c, dq, pivots, status, z)``: the candidates' part of z
    and the tool increments re-solved from the final basis without the shift (see
    :func:`lemke_contact`)."""
    res = lemke(M, q, max_pivots=max_pivots, pivot_tol=pivot_tol)
    n_c3 = q.size - n_q
    if n_q == 0:
        return res.z[:n_c3], np.zeros(0), res.pivots, res.status, res.z
    tools = n_c3 + np.arange(n_q)
    z_free = _z_from_basis(M, q + shift * M[:, tools].sum(axis=1), res.basis, res.z)
    # A tool whose z_q is non-basic sits at z_q = 0, i.e. dq = -alpha.
    basic = np.isin(q.size + tools, res.basis)     # z_j is basic variable n + j
    dq = np.where(basic, z_free[tools], -shift)
    z_c, status = z_free[:n_c3], res.status
    if status == LemkeStatus.SOLVED:
        z_c = np.maximum(z_c, 0.0)
    if status == LemkeStatus.SOLVED and np.any(dq + shift <= 0.0):
        status = int(LemkeStatus.SHIFT_TOO_SMALL)
    return z_c, dq, res.pivots, status, res.z


class _Basis(NamedTuple):
    """A complementary basis factored through its principal submatrix (see :func:`_factor_basis`)."""
    basis: np.ndarray   # (n,) basic variable of each row
    x: np.ndarray       # (n,) basic values B^-1 q
    Z: np.ndarray       # rows whose z is basic
    W: np.ndarray       # rows whose w is basic
    lu: np.ndarray      # LU of M_ZZ (dgetrf)
    piv: np.ndarray


def _factor_basis(M, q, start):
    """The complementary basis ``start`` (True: z basic) and its basic values ``x = B^-1 q``, as a
    :class:`_Basis`; None if it is numerically singular.

    B holds e_i for each basic w_i and -M[:, j] for each basic z_j. With Z the rows whose z is basic
    and W the others, ``B x = q`` splits into ``M_ZZ x_Z = -q_Z`` and ``x_W = q_W + M_WZ x_Z``: one LU
    of the principal submatrix M_ZZ (det B = +-det M_ZZ), a third of B's size or less on the Nine's
    band. Its condition is judged on M_ZZ alone, which the identity columns of B, of another scale
    than M, would otherwise blur."""
    n = start.size
    basis = np.where(start, n + np.arange(n), np.arange(n))
    Z, W = np.flatnonzero(start), np.flatnonzero(~start)
    x = np.array(q, dtype=float)
    lu, piv = np.zeros((0, 0)), np.zeros(0, np.int32)
    if Z.size:
        A = M[np.ix_(Z, Z)]
        lu, piv, info = lapack.dgetrf(A)
        # A guess can be singular (lambda+ and lambda- of one pair basic: opposite columns); its
        # "solution" is then round-off of any size.
        rcond = lapack.dgecon(lu, np.max(np.sum(np.abs(A), axis=0)), norm="1")[0] if info == 0 else 0.0
        if not rcond > 1e-14:
            return None
        x[Z] = lapack.dgetrs(lu, piv, -q[Z])[0]
        x[W] = q[W] + M[np.ix_(W, Z)] @ x[Z]
    return _Basis(basis, x, Z, W, lu, piv)


def _tableau(M, f: _Basis) -> tuple[np.ndarray, np.ndarray]:
    """The tableau ``B^-1 [I, -M, -d, q]`` of the factored basis with covering vector ``d = B 1`` (so
    its z0 column is -1 and its last column x), and d.

    From the split of :func:`_factor_basis`: ``B^-1 b`` has rows ``Z: -M_ZZ^-1 b_Z`` and
    ``W: b_W - M_WZ M_ZZ^-1 b_Z``, so B^-1 and B^-1 M need solves with M_ZZ only."""
    n = M.shape[0]
    Z, W = f.Z, f.W
    B_inv = np.zeros((n, n))
    B_inv[W, W] = 1.0
    BM = np.empty((n, n))
    BM[W] = M[W]
    if Z.size:
        # Y = M_ZZ^-1 [I_Z | M_Z:]: the Z rows of -B^-1 and of -B^-1 M at once.
        Y = lapack.dgetrs(f.lu, f.piv, np.hstack([np.eye(Z.size), M[Z]]))[0]
        coupling = M[np.ix_(W, Z)]
        B_inv[np.ix_(Z, Z)] = -Y[:, :Z.size]
        B_inv[np.ix_(W, Z)] = -coupling @ Y[:, :Z.size]
        BM[Z] = -Y[:, Z.size:]
        BM[W] -= coupling @ Y[:, Z.size:]
    d = np.zeros(n)
    d[W] = 1.0
    d -= M[:, Z].sum(axis=1)
    return np.asfortranarray(np.hstack([B_inv, -BM, -np.ones((n, 1)), f.x[:, None]])), d


def _opposite_columns(M) -> np.ndarray:
    """(n,) bools: column j of M is exactly the negative of column j + 1 (lambda+ and lambda- of a
    contact candidate: ``s = lambda- - lambda+`` enters M through B's columns (0, -1) and (0, 1))."""
    n = M.shape[0]
    out = np.zeros(n, bool)
    if n > 1:
        out[:-1] = np.all(M[:, :-1] == -M[:, 1:], axis=0)
    return out


def _flip_opposite(M, q, start, x, opposite):
    """The basis ``start`` with the sign of each free slip corrected, or None if none needs it.

    Where z_j and z_j+1 have opposite columns and only one of them is basic, the basic one with a
    negative value v can be exchanged for the other at -v when the other's complement w is zero
    there: M z + q is unchanged, so every other basic value stays. That is an open candidate (R_N =
    R_T = 0, so phi+ = phi- = 0) whose guessed slip direction was wrong; the warm start cannot know
    it, since the forces of the last iterate say nothing about a pair that is open."""
    value = np.where(start, x, 0.0)                   # z of the basic point
    w = np.where(start, 0.0, x)                       # w of the basic point
    # Round-off of w (forces); a z of either sign at round-off may flip, which changes nothing.
    tol = 1e3 * _NOISE * (np.abs(M) @ np.abs(value) + np.abs(q))
    j = np.flatnonzero(opposite)
    lo = start[j] & ~start[j + 1] & (x[j] < 0.0) & (np.abs(w[j + 1]) <= tol[j + 1])
    hi = start[j + 1] & ~start[j] & (x[j + 1] < 0.0) & (np.abs(w[j]) <= tol[j])
    if not (np.any(lo) or np.any(hi)):
        return None
    out = start.copy()
    for a, b in ((j[lo], j[lo] + 1), (j[hi] + 1, j[hi])):
        out[a], out[b] = False, True
    return out


def lemke_start(p, slip, mu) -> jax.Array:
    """A complementary basis guessed from contact forces ``p`` (2 n_c,), e.g. those of the previous
    Newton iterate, for :func:`lemke`'s warm start: (3 n_c,) bools, True where z is basic.

    Per candidate (z = (g_N, lambda+, lambda-), w = (R_N, phi+, phi-)): closed (R_N above the open
    threshold) makes R_N basic, open makes g_N basic. A sticking pair has phi+ and phi- basic; a
    slipping one the lambda of its slip direction (R_T = +mu R_N: phi+ = 0, lambda+ basic, s < 0).
    Where R_T says nothing (open, or mu = 0) the sign of the step slip ``slip`` picks the lambda.
    """
    p = jnp.asarray(p).reshape(-1, 2)
    R_N, R_T = p[:, 0], p[:, 1]
    mu = jnp.asarray(mu, p.dtype)
    status = contact_status(R_N, R_T, mu)
    closed, stick = status != OPEN, status == STICK
    by_force = closed & (mu > 0.0)
    plus = ~stick & jnp.where(by_force, R_T > 0.0, jnp.asarray(slip) < 0.0)
    minus = ~stick & ~plus
    return jnp.stack([~closed, plus, minus], -1).reshape(-1)


def lemke_contact_callback(K_star, r_star, gap, slip, mu, drive: ForceDrive | None = None, *,
                           max_pivots: int | None = None, pivot_tol: float = 1e-12, start=None):
    """:func:`lemke_contact` from inside ``jit``: the LCP is built and the solution recovered in JAX,
    the pivoting runs on the host through ``jax.pure_callback``. Not differentiable.

    With force-driven tools the tool rows are equalities with a free unknown dq (a mixed LCP). Here
    they are eliminated before pivoting instead of being shifted by alpha (spec 1.8): from
    ``w_q = M_qz z + M_qq dq + q_q = 0``, ``dq = -M_qq^-1 (M_qz z + q_q)`` and the LCP in z alone is

        M' = M_zz - M_zq M_qq^-1 M_qz,      q' = q_z - M_zq M_qq^-1 q_q      (unshifted q).

    The solutions are the same (z_q = dq + alpha > 0 makes w_q = 0 in the shifted form), but the
    shifted data carry alpha K* (1e8 N/mm for alpha = 1e3 mm) next to forces of 1e-2 N/mm, which
    leaves Lemke's relative pivot and feasibility tests blind to tangential forces below 1e-4 N/mm:
    on a frictionless clamp it returned a stuck (s = 0) solution with R_T of that size. M_qq =
    C^T K* C > 0 as long as the tool touches a candidate of the band, which a force-driven phase
    requires (spec 1.8).

    ``start``: optional (3 n_c,) bools, the starting basis of :func:`lemke` (see :func:`lemke_start`).

    Returns ``(du_c, p, dq, pivots, status)`` as arrays.
    """
    M, q = contact_lcp(K_star, r_star, gap, slip, mu, drive)
    n_q = 0 if drive is None else drive.num_tools
    n_c3 = q.shape[-1] - n_q
    if drive is not None and n_q:
        tools = slice(n_c3, None)
        q = q + drive.shift * jnp.sum(M[:, tools], axis=1)           # unshifted: z_q = dq
        coupling = jnp.linalg.solve(M[tools, tools], jnp.concatenate([M[tools, :n_c3], q[tools, None]], 1))
        M_red = M[:n_c3, :n_c3] - M[:n_c3, tools] @ coupling[:, :n_c3]
        q_red = q[:n_c3] - M[:n_c3, tools] @ coupling[:, n_c3]
    else:
        M_red, q_red = M, q

    def host(M, q, start):
        res = lemke(np.asarray(M), np.asarray(q), max_pivots=max_pivots, pivot_tol=pivot_tol,
                    start=np.asarray(start))
        return res.z.astype(q.dtype), np.int32(res.pivots), np.int32(res.status)

    shapes = (jax.ShapeDtypeStruct((n_c3,), q.dtype), jax.ShapeDtypeStruct((), jnp.int32),
              jax.ShapeDtypeStruct((), jnp.int32))
    start = jnp.zeros(n_c3, bool) if start is None else jnp.asarray(start, bool)
    z_c, pivots, status = jax.pure_callback(host, shapes, M_red, q_red, start, vmap_method="sequential")
    dq = -(coupling[:, :n_c3] @ z_c + coupling[:, n_c3]) if n_q else jnp.zeros(0, q.dtype)
    K = jnp.asarray(K_star)
    C, _ = _coupling(drive, jnp.shape(gap)[0], K.dtype)
    du_c, p = _recover(K, r_star, gap, slip, z_c, dq, C)
    return du_c, p, dq, pivots, status


# --------------------------------------------------------------------------------------------
# Semismooth Newton on the Alart-Curnier equations
# --------------------------------------------------------------------------------------------


class SSNResult(NamedTuple):
    du_c: jax.Array        # (2 n_c,) displacement increments of the candidates, mm
    p: jax.Array           # (2 n_c,) contact forces (R_N, R_T) on the sheet, N/mm
    iterations: jax.Array  # () int32: linear solves performed
    converged: jax.Array   # () bool
    dq: jax.Array          # (n_q,) increments of the force-driven tools, mm (empty without tools)


# Active-set labels of one candidate inside the Newton iteration. The slip direction is part of
# the label: a change of sign is a change of the linear piece.
_OPEN, _STICK, _SLIP_POS, _SLIP_NEG = 0, 1, 2, 3


def _alart_curnier(R_N, R_T, g, s, mu, c_n, c_t):
    """Active set and residual ``(C_N, C_T)`` of the Alart-Curnier equations, per candidate."""
    sig_n = R_N - c_n * g
    sig_t = R_T - c_t * s
    bound = mu * jnp.maximum(sig_n, 0.0)
    C_N = R_N - jnp.maximum(sig_n, 0.0)
    C_T = R_T - jnp.clip(sig_t, -bound, bound)
    state = jnp.where(sig_n <= 0.0, _OPEN,
                      jnp.where(jnp.abs(sig_t) < bound, _STICK,
                                # Without friction the slip direction plays no part.
                                jnp.where((sig_t >= 0.0) | (mu == 0.0), _SLIP_POS, _SLIP_NEG)))
    return state.astype(jnp.int32), jnp.stack([C_N, C_T], axis=-1), sig_n


def _piece(state, mu, c_n, c_t):
    """Generalised Jacobian of (C_N, C_T) on the linear piece ``state``: C = W_F p + W_K (g, s).

    open:   C = (R_N, R_T)                                W_F = I,  W_K = 0
    stick:  C = (c_N g, c_T s)                            W_F = 0,  W_K = diag(c_N, c_T)
    slip:   C = (c_N g, R_T - mu xi (R_N - c_N g))        W_F = [[0, 0], [-mu xi, 1]],
                                                          W_K = [[c_N, 0], [mu xi c_N, 0]]
    with xi = sign(sigma_T). Returns W_F, W_K of shape (n_c, 2, 2).
    """
    one, zero = jnp.ones_like(mu), jnp.zeros_like(mu)
    xi = jnp.where(state == _SLIP_NEG, -1.0, 1.0)
    is_open, is_stick = state == _OPEN, state == _STICK
    is_slip = ~is_open & ~is_stick
    w_f = jnp.stack([jnp.stack([jnp.where(is_open, one, zero), zero], -1),
                     jnp.stack([jnp.where(is_slip, -mu * xi, zero), jnp.where(is_stick, zero, one)], -1)], -2)
    closed = jnp.where(is_open, zero, c_n * one)
    w_k = jnp.stack([jnp.stack([closed, zero], -1),
                     jnp.stack([jnp.where(is_slip, mu * xi * c_n, zero), jnp.where(is_stick, c_t * one, zero)],
                               -1)], -2)
    return w_f, w_k


def _piece_solution(K_star, r_star, d0, C, P, state, mu, c_n, c_t):
    """x = (du_c, dq) solving the Alart-Curnier equations linearised on the piece ``state`` (and the
    tool rows ``C^T p = P``): one dense solve of size 2 n_c + n_q."""
    n_c, n_q = state.shape[0], C.shape[1]
    w_f, w_k = _piece(state, mu, c_n, c_t)
    K3 = K_star.reshape(n_c, 2, 2 * n_c)
    top = jnp.einsum("iab,ibj->iaj", w_f, K3).reshape(2 * n_c, 2 * n_c) + _block_diag(w_k)
    rhs_top = (jnp.einsum("iab,ib->ia", w_f, r_star.reshape(n_c, 2))
               + jnp.einsum("iab,ib->ia", w_k, d0.reshape(n_c, 2))).reshape(-1)
    if n_q == 0:
        return jnp.linalg.solve(top, rhs_top)
    # n_q bordering rows, solved densely: K* is dense after condensation anyway.
    J = jnp.block([[top, -_block_diag(w_k) @ C], [C.T @ K_star, jnp.zeros((n_q, n_q), K_star.dtype)]])
    return jnp.linalg.solve(J, jnp.concatenate([rhs_top, P + C.T @ r_star]))


def polish(K_star, r_star, gap, slip, mu, du_c, dq, drive: ForceDrive | None = None, refine_iter: int = 0):
    """Refine a solution found by pivoting: classify each candidate (open / stick / slip with its
    direction) from ``(du_c, dq)`` and solve the contact equations on that piece exactly (one dense
    LU of the original data). If the refined point falls on another piece, the pivoting's values lie
    on a piece boundary within their round-off; then, with ``refine_iter`` > 0, semismooth Newton
    (:func:`ssn_contact`, at most ``refine_iter`` iterations) starts on the pivoting's piece, and its
    answer is taken if it converges; otherwise the pivoting's own answer is kept. Open candidates are
    given zero forces. Returns ``(du_c, p, dq, iterations, solved)``: the semismooth Newton iterations
    (0 when the piece held), and whether the answer is a solution by its own piece (the piece held, or
    semismooth Newton converged), whatever the pivoting's status. The pivoting need not have ended on a
    solution: its last basis (a ray, or an end that failed :func:`lemke`'s check) starts the same
    refinement.

    On the blankholder's lock (Lemke on a band of 256 nodes) the pivoting's values had an error of
    3e-8 mm (a stick-slip pair with |R_T| = mu R_N, land nodes at zero gap and zero force); without
    the semismooth Newton step the global Newton iteration's increment never fell below that, against
    its tolerance of 1e-9 mm, and the step was cut to its floor; with it, the step converges in 5
    iterations, as semismooth Newton on the same condensed problems does.

    Lemke's answer is exact in its active set but not in its values: the tableau and the basis
    solve carry the conditioning of the condensed problem (with a force-driven tool eliminated, the
    common motion of tool and sheet is nearly free), which left the tool's force balance at 2e-8 of
    the force on a frictionless clamp, above the Newton tolerance.
    """
    K_star = jnp.asarray(K_star)
    dtype = K_star.dtype
    r_star, gap, slip, mu = (jnp.asarray(a, dtype) for a in (r_star, gap, slip, mu))
    n_c = gap.shape[0]
    C, P = _coupling(drive, n_c, dtype)
    c_n, c_t = diagonal_parameters(K_star)
    d0 = -_interleave(gap, slip)

    def classify(du, dq):
        p = (K_star @ du - r_star).reshape(n_c, 2)
        kin = (du - C @ dq - d0).reshape(n_c, 2)
        return _alart_curnier(p[:, 0], p[:, 1], kin[:, 0], kin[:, 1], mu, c_n, c_t)[0]

    state = classify(du_c, dq)
    x = _piece_solution(K_star, r_star, d0, C, P, state, mu, c_n, c_t)
    du_new, dq_new = x[: 2 * n_c], x[2 * n_c:]
    keep = jnp.all(classify(du_new, dq_new) == state) & jnp.all(jnp.isfinite(x))

    def refine():
        # The exact solve on the pivoting's piece falls on another piece: the pivoting's values sit on
        # a boundary within their round-off (a pair with |R_T| = mu R_N, a node at zero gap and zero
        # force). Semismooth Newton on the same problem, started on that piece, settles it.
        s = ssn_contact(K_star, r_star, gap, slip, mu, drive=drive, c_n=c_n, c_t=c_t, max_iter=refine_iter,
                        start=state)
        ok = s.converged & jnp.all(jnp.isfinite(s.du_c))
        return jnp.where(ok, s.du_c, du_c), jnp.where(ok, s.dq, dq), s.iterations, ok

    if refine_iter:
        du, dq, iters, solved = jax.lax.cond(keep, lambda: (du_new, dq_new, jnp.array(0, jnp.int32), keep),
                                             refine)
    else:
        du, dq, iters, solved = (jnp.where(keep, du_new, du_c), jnp.where(keep, dq_new, dq),
                                 jnp.array(0, jnp.int32), keep)
    # The forces of the piece: an open candidate carries none. K* du - r* leaves it the round-off of
    # the forces around it (1e-8 N/mm next to 300 N/mm on the blankholder's lands), above the open
    # threshold of :func:`jaxfric.status.contact_status`, so that its status flipped between iterations.
    p = (K_star @ du - r_star).reshape(n_c, 2)
    p = jnp.where((classify(du, dq) == _OPEN)[:, None], 0.0, p)
    return du, p.reshape(-1), dq, iters, solved


def _keep_tools_touching(state, sig_n, e_dot_n):
    """Close (in stick) the candidate of largest sigma_N of every force-driven tool left with no
    closed candidate.

    With all its candidates open, a tool's row ``C^T p = P`` does not involve dq and the Newton
    matrix is singular. At a solution with P > 0 some candidate of the tool carries force, so this
    only steers the iteration; the convergence test uses the unmodified classification.
    ``e_dot_n`` (n_c, n_q) holds e_q . n per candidate and tool.
    """
    mine = e_dot_n > 0.0
    touching = jnp.any(mine & (state != _OPEN)[:, None], axis=0)
    nearest = jnp.argmax(jnp.where(mine, sig_n[:, None], -jnp.inf), axis=0)
    need = ~touching & jnp.any(mine, axis=0)
    return state.at[nearest].set(jnp.where(need, _STICK, state[nearest]))


def _block_diag(blocks: jax.Array) -> jax.Array:
    """(n_c, 2, 2) -> (2 n_c, 2 n_c) block-diagonal matrix."""
    n_c = blocks.shape[0]
    i = jnp.arange(n_c)
    dense = jnp.zeros((n_c, 2, n_c, 2), blocks.dtype).at[i, :, i, :].set(blocks)
    return dense.reshape(2 * n_c, 2 * n_c)


def diagonal_parameters(K_star) -> tuple[jax.Array, jax.Array]:
    """Per-candidate Alart-Curnier parameters ``(c_N, c_T)``, each (n_c,): the diagonal of K*.

    The spec's default (the mean diagonal, one value for all) is fine when the candidates'
    stiffnesses are alike, as on a uniformly meshed sheet (a factor 10 or so). When they spread
    over decades (graded meshes, penalty-like test data), one c misclassifies the soft or the stiff
    candidates and the iteration can stall; c following each candidate's stiffness does not.
    """
    diagonal = jnp.diagonal(jnp.asarray(K_star))
    return diagonal[0::2], diagonal[1::2]


def ssn_start(p, gap, mu) -> jax.Array:
    """The first active set of :func:`ssn_contact`, guessed from contact forces ``p`` (2 n_c,), e.g.
    those of the previous Newton iterate: (n_c,) int32 labels.

    A candidate carrying a normal force (above the open threshold) starts closed: in stick if its
    tangential force is inside the cone, else slipping in the direction of R_T (frictionless: slip).
    A candidate without force starts by the closed-at-zero-gap rule (stick if ``gap <= 0``, else open),
    the cold start's rule for all.
    """
    p = jnp.asarray(p).reshape(-1, 2)
    status = contact_status(p[:, 0], p[:, 1], jnp.broadcast_to(jnp.asarray(mu, p.dtype), p[:, 0].shape))
    slip = jnp.where((p[:, 1] >= 0.0) | (jnp.asarray(mu) == 0.0), _SLIP_POS, _SLIP_NEG)
    by_gap = jnp.where(jnp.asarray(gap) <= 0.0, _STICK, _OPEN)
    return jnp.select([status == OPEN, status == STICK], [by_gap, _STICK],
                      slip).astype(jnp.int32)


def ssn_contact(K_star, r_star, gap, slip, mu, *, drive: ForceDrive | None = None, c_n=None, c_t=None,
                max_iter: int = 50, tol: float = 1e-10, start=None) -> SSNResult:
    """Solve the linearised contact problem by semismooth Newton (``lcp_ssn`` of spec 1.7).

    Unknowns ``du_c`` (2 n_c,) and ``dq`` (n_q,), with ``p = K* du_c - r*``,
    ``(g_N, s) = (g_N^i, s^i) + du_c - C dq``. Equations, per candidate (Alart & Curnier 1991):

        sigma_N = R_N - c_N g_N,        sigma_T = R_T - c_T s,
        C_N = R_N - max(0, sigma_N) = 0,
        C_T = R_T - clip(sigma_T, -mu max(0, sigma_N), +mu max(0, sigma_N)) = 0,

    and, per force-driven tool, the ordinary equality ``C^T p - P = 0`` (spec 1.8).

    C = 0 is exactly the Signorini-Coulomb law: C_N = 0 is ``R_N = max(0, R_N - c_N g_N)``,
    i.e. the complementarity of (g_N, R_N); C_T = 0 projects R_T on [-mu R_N, mu R_N] and
    forces s = 0 inside, s opposite to R_T on the boundary. Hence the solutions are those of
    the LCP, for any c_N, c_T > 0.

    Method: primal-dual active sets (Hintermueller, Ito & Kunisch 2002), which is semismooth
    Newton for these piecewise-linear equations. Each candidate is classified from the current
    sigma's as open, stick or slip (with the slip direction); on that piece C is affine, and the
    Newton step solves it exactly, one dense solve of size 2 n_c + n_q per iteration:

        [W_F K* + W_K, -W_K C] [du]   [W_F r* + W_K d0]
        [C^T K*,            0] [dq] = [P + C^T r*     ]      d0 = -(g^i, s^i),

    with ``C = W_F p + W_K (g, s)`` on the piece (see ``_piece``). The first classification
    follows the closed-at-zero-gap rule (spec section 0): g_N^i <= 0 starts closed in stick.

    Globalisation. Plain active-set iterations can cycle when K* is not an M-matrix, which a
    condensed sheet stiffness never is (bending couples neighbouring normals with both signs):
    on clamped strips with random gaps, 2 problems in 16 to 7 in 30 cycled. The step is therefore accepted by a
    non-monotone Armijo test on ``theta = sum C_N^2 / c_N + C_T^2 / c_T (+ |C^T p - P|^2 / c)``
    against the largest theta of the last 5 iterates (Grippo, Lampariello & Lucidi 1986), halving
    it otherwise. The Newton direction d = -J^-1 C is a descent direction of theta wherever C is
    differentiable (theta' = -2 theta); near the solution the full step passes, so the iteration
    still ends exactly on the solution's piece.

    Stopping: converged when a full step leaves the classification unchanged (then C = 0 up to
    round-off), or when ``|C|_inf <= tol * max(|r*|, |p|, c_N |g^i|, c_T |s^i|, |P|)``, which
    covers candidates on a kink (g_N = R_N = 0) whose label may flip.

    Why Alart-Curnier rather than Fischer-Burmeister: (i) the max/clip equations are piecewise
    linear, so a full Newton step lands exactly on the solution of its piece: the iteration is a
    finite active-set method that returns the LCP solution to round-off, where the smooth FB
    function only approaches it superlinearly; (ii) its solution does not depend on c_N, c_T,
    which only steer the classification; (iii) its Jacobian is the bulk stiffness with rows
    swapped for kinematic constraints, and its labels are the open/stick/slip status of the
    spec. FB mixes each complementary pair into a nonlinear function, is degenerate where both
    members vanish (open candidates: R_N = phi+- = 0) and has no direct form for the 2D Coulomb
    law with a slip direction.

    Args:
        K_star, r_star, gap, slip, mu, drive: as for :func:`contact_lcp`.
        c_n, c_t: Alart-Curnier parameters (N/mm per mm), scalar or (n_c,); default the mean
            diagonal entry of K* (spec 1.7). See :func:`diagonal_parameters` for stiffnesses
            spread over decades.
        max_iter: linear solves allowed (static). If not converged by then, ``converged`` is
            False and the caller falls back to Lemke (spec 1.7).
        tol: relative residual test, see above.
        start: optional (n_c,) first active set (:func:`ssn_start`, from the previous Newton
            iterate's forces); the default classifies by the gaps alone. Inside a global Newton loop
            the active set changes little between iterates, and a cold start from the gaps walks
            every closed candidate through open/stick/slip again.

    Returns:
        :class:`SSNResult` ``(du_c, p, iterations, converged, dq)``. A failed line search or a
        non-finite iterate also ends the iteration with ``converged = False``.
    """
    n_c = _check_shapes(K_star, r_star, gap, slip, mu)
    K_star = jnp.asarray(K_star)
    dtype = K_star.dtype
    r_star, gap, slip, mu = (jnp.asarray(a, dtype) for a in (r_star, gap, slip, mu))
    C, P = _coupling(drive, n_c, dtype)
    n_q = C.shape[1]
    mean_diag = jnp.mean(jnp.diagonal(K_star))
    c_n = mean_diag if c_n is None else jnp.asarray(c_n, dtype)
    c_t = mean_diag if c_t is None else jnp.asarray(c_t, dtype)
    c_n, c_t = jnp.broadcast_to(c_n, (n_c,)), jnp.broadcast_to(c_t, (n_c,))
    d0 = -_interleave(gap, slip)
    scale = jnp.max(jnp.concatenate([jnp.abs(r_star), c_n * jnp.abs(gap), c_t * jnp.abs(slip), jnp.abs(P),
                                     jnp.array([jnp.finfo(dtype).tiny], dtype)]))

    def evaluate(x):
        """Classification, merit theta, |residual|_inf, |p|_inf and sigma_N at x = (du, dq)."""
        du, dq = x[: 2 * n_c], x[2 * n_c:]
        p = K_star @ du - r_star
        kin = (du - C @ dq - d0).reshape(n_c, 2)
        p2 = p.reshape(n_c, 2)
        state, res, sig_n = _alart_curnier(p2[:, 0], p2[:, 1], kin[:, 0], kin[:, 1], mu, c_n, c_t)
        res_q = C.T @ p - P
        # Merit in energy units (N/mm mm): C^2 / c per equation, so that candidates of very
        # different stiffness weigh alike when c follows the stiffness.
        theta = jnp.sum(res[:, 0] ** 2 / c_n + res[:, 1] ** 2 / c_t) + jnp.sum(res_q**2) / jnp.mean(c_n)
        res_norm = jnp.maximum(jnp.max(jnp.abs(res)), jnp.max(jnp.abs(res_q), initial=0.0))
        return state, theta, res_norm, jnp.max(jnp.abs(p)), sig_n

    def newton_point(state):
        return _piece_solution(K_star, r_star, d0, C, P, state, mu, c_n, c_t)

    def next_state(state, sig_n):
        return _keep_tools_touching(state, sig_n, C[0::2]) if n_q else state

    def line_search(x, x_full, theta, theta_ref):
        """Largest t = 2^-j with theta(x + t d) <= theta_ref - 2 sigma t theta (non-monotone Armijo)."""

        def accept(t, theta_t):
            return theta_t <= theta_ref - 2.0 * _ARMIJO * t * theta

        def cond(c):
            t, theta_t = c
            return ~accept(t, theta_t) & (t >= _MIN_STEP)

        def body(c):
            t = 0.5 * c[0]
            return t, evaluate(x + t * (x_full - x))[1]

        t, _ = lax.while_loop(cond, body, (jnp.array(1.0, dtype), evaluate(x_full)[1]))
        return t

    def cond(carry):
        k, done = carry[0], carry[4]
        return ~done & (k < max_iter)

    def body(carry):
        k, x, state, thetas, _, _ = carry
        x_full = newton_point(state)
        # The first step is taken in full: x0 = 0 is a guess, not an iterate; only its
        # classification (from the gaps) is used.
        t = line_search(x, x_full, thetas[-1], jnp.where(k == 0, jnp.inf, jnp.max(thetas)))
        x = jnp.where(t == 1.0, x_full, x + t * (x_full - x))
        new_state, theta, res_norm, p_norm, sig_n = evaluate(x)
        finite = jnp.all(jnp.isfinite(x))
        exact = (t == 1.0) & jnp.all(new_state == state)
        settled = finite & (exact | (res_norm <= tol * jnp.maximum(scale, p_norm)))
        failed = ~finite | (t < _MIN_STEP)
        thetas = jnp.concatenate([thetas[1:], theta[None]])
        return k + 1, x, next_state(new_state, sig_n), thetas, settled | failed, settled

    x0 = jnp.zeros(2 * n_c + n_q, dtype)
    _, theta0, _, _, sig_n0 = evaluate(x0)
    first = jnp.where(gap <= 0.0, _STICK, _OPEN) if start is None else jnp.asarray(start)
    state0 = next_state(first.astype(jnp.int32), sig_n0)
    thetas0 = jnp.full(_MEMORY, -jnp.inf, dtype).at[-1].set(theta0)
    carry0 = (jnp.array(0, jnp.int32), x0, state0, thetas0, jnp.array(False), jnp.array(False))
    k, x, _, _, _, converged = lax.while_loop(cond, body, carry0)
    du, dq = x[: 2 * n_c], x[2 * n_c:]
    return SSNResult(du, K_star @ du - r_star, k, converged, dq)
