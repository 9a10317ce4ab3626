"""Lemke's complementary pivoting for the linear complementarity problem ``w = M z + q, z >= 0, w >= 0,
z.w = 0`` (NumPy, float64, on the host).

Lemke (1965), "Bimatrix equilibrium points and mathematical programming"; Cottle, Pang & Stone, *The
Linear Complementarity Problem* (1992), sections 4.4 and 4.9: covering vector e = 1, the lexicographic
minimum ratio test with ties judged against the round-off of the basic values, a warm start from a
guessed complementary basis, and every answer checked on the original data. The contact LCP it solves
and its call from inside ``jit`` are in :mod:`jaxfric.contact.lcp`; the linear algebra of a basis is
in :mod:`jaxfric.contact.complementary_basis`.
"""

from __future__ import annotations

import enum
from typing import NamedTuple

import numpy as np
from scipy.linalg.blas import dger

from .complementary_basis import NOISE, factor_basis, flip_opposite, opposite_columns, tableau, z_from_basis

__all__ = ["LemkeStatus", "LemkeResult", "lemke"]


class LemkeStatus(enum.IntEnum):
    SOLVED = 0
    RAY = 1               # ray termination: no blocking variable (infeasible, or not processable)
    MAX_PIVOTS = 2        # pivot budget exhausted
    INACCURATE = 3        # pivoting ended (z0 left), but the point fails the check on the original data


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
    noise_d = NOISE * (terms[:, 0] + np.abs(d[rows]))
    keep = d[rows] > noise_d
    rows, terms, noise_d = rows[keep], terms[keep], noise_d[keep]
    if rows.size == 0:
        return rows
    x = T[rows, -1]
    noise_x = NOISE * (terms[:, 1] + np.abs(x))
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
    (see :func:`jaxfric.contact.lcp.lemke_contact_callback`).

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
    solution (:func:`flip_opposite`): a guessed lambda that comes out negative there is exchanged for
    its opposite, which leaves the point unchanged.
    """
    n = q.size
    pivots = 0
    opposite = opposite_columns(M)
    for _ in range(restarts + 1):
        factors = factor_basis(M, q, start)
        if factors is None:
            return None
        flipped = flip_opposite(M, q, start, factors.x, opposite)
        if flipped is not None:
            # Same point, other sign of a free slip: the basis changed, so factor it again.
            start = flipped
            factors = factor_basis(M, q, start)
            if factors is None:
                return None
        basis, x = factors.basis, factors.x
        z = np.zeros(n)
        z[basis[start] - n] = np.maximum(x[start], 0.0)
        if _is_solution(M, q, z):  # the guessed basis is feasible (to round-off): no pivot
            return LemkeResult(z, M @ z + q, pivots, int(LemkeStatus.SOLVED), basis)
        T, d = tableau(M, factors)
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
            z = z_from_basis(M, q, basis, T[:, -1], d)
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

    z = z_from_basis(M, q, basis, T[:, -1], d)
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
    tol = 1e3 * NOISE * (np.abs(M) @ z + np.abs(q))
    return bool(np.all(w >= -tol) and np.all((z == 0.0) | (np.abs(w) <= tol)))


