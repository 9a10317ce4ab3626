"""Complementary bases of a linear complementarity problem ``w = M z + q``: their matrix, their basic
solution and their tableau, for Lemke's pivoting (:mod:`jaxfric.contact.lemke`).

A complementary basis picks one variable of every pair (w_i, z_i); Lemke's augmented system adds z0
with the covering vector d. Basic variables are numbered as in :class:`jaxfric.contact.lemke.LemkeResult`:
i < n is w_i, n + j is z_j, 2n is z0. The basis matrix B holds the original columns ``(I, -M, -d)`` of
the basic variables, and its basic solution solves ``B x = q``.

Everything here is NumPy (float64), on the host.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.linalg import lapack

__all__ = ["NOISE", "FactoredBasis", "factor_basis", "flip_opposite", "opposite_columns", "tableau", "z_from_basis"]

NOISE = 1e-11   # relative round-off scale of the basic values in Lemke (ties within it)


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


def z_from_basis(M, q, basis, fallback, d):
    """z from the basis: ``B x_B = q`` solved with the original columns (I, -M, -d) by one LU (d: the
    covering vector of the run, (n,)).

    Solving once with the original data, instead of reading the Gauss-Jordan tableau, keeps the
    round-off of the pivots out of the answer. ``fallback`` (the tableau's x) serves if B is
    numerically singular.
    """
    n = q.size
    cols = _basis_columns(M, basis, d)
    try:
        values = np.linalg.solve(cols, q)
    except np.linalg.LinAlgError:
        values = fallback.copy()
    z = np.zeros(n)
    in_z = (basis >= n) & (basis < 2 * n)
    z[basis[in_z] - n] = values[in_z]
    return z


class FactoredBasis(NamedTuple):
    """A complementary basis factored through its principal submatrix (see :func:`factor_basis`)."""
    basis: np.ndarray   # (n,) basic variable of each row
    x: np.ndarray       # (n,) basic values B^-1 q
    Z: np.ndarray       # rows whose z is basic
    W: np.ndarray       # rows whose w is basic
    lu: np.ndarray      # LU of M_ZZ (dgetrf)
    piv: np.ndarray


def factor_basis(M, q, start):
    """The complementary basis ``start`` (True: z basic) and its basic values ``x = B^-1 q``, as a
    :class:`FactoredBasis`; None if it is numerically singular.

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
    return FactoredBasis(basis, x, Z, W, lu, piv)


def tableau(M, f: FactoredBasis) -> tuple[np.ndarray, np.ndarray]:
    """The tableau ``B^-1 [I, -M, -d, q]`` of the factored basis with covering vector ``d = B 1`` (so
    its z0 column is -1 and its last column x), and d.

    From the split of :func:`factor_basis`: ``B^-1 b`` has rows ``Z: -M_ZZ^-1 b_Z`` and
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


def opposite_columns(M) -> np.ndarray:
    """(n,) bools: column j of M is exactly the negative of column j + 1 (lambda+ and lambda- of a
    contact candidate: ``s = lambda- - lambda+`` enters M through B's columns (0, -1) and (0, 1))."""
    n = M.shape[0]
    out = np.zeros(n, bool)
    if n > 1:
        out[:-1] = np.all(M[:, :-1] == -M[:, 1:], axis=0)
    return out


def flip_opposite(M, q, start, x, opposite):
    """The basis ``start`` with the sign of each free slip corrected, or None if none needs it.

    Where z_j and z_j+1 have opposite columns and only one of them is basic, the basic one with a
    negative value v can be exchanged for the other at -v when the other's complement w is zero
    there: M z + q is unchanged, so every other basic value stays. That is an open candidate (R_N =
    R_T = 0, so phi+ = phi- = 0) whose guessed slip direction was wrong; the warm start cannot know
    it, since the forces of the last iterate say nothing about a pair that is open."""
    value = np.where(start, x, 0.0)                   # z of the basic point
    w = np.where(start, 0.0, x)                       # w of the basic point
    # Round-off of w (forces); a z of either sign at round-off may flip, which changes nothing.
    tol = 1e3 * NOISE * (np.abs(M) @ np.abs(value) + np.abs(q))
    j = np.flatnonzero(opposite)
    lo = start[j] & ~start[j + 1] & (x[j] < 0.0) & (np.abs(w[j + 1]) <= tol[j + 1])
    hi = start[j + 1] & ~start[j] & (x[j + 1] < 0.0) & (np.abs(w[j]) <= tol[j])
    if not (np.any(lo) or np.any(hi)):
        return None
    out = start.copy()
    for a, b in ((j[lo], j[lo] + 1), (j[hi] + 1, j[hi])):
        out[a], out[b] = False, True
    return out

