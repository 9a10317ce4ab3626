"""Structured linear solves for the sheet stiffness.

A sheet is a long strip of quadrilaterals numbered column by column, so the global tangent
stiffness is block-tridiagonal: ``nb = nx + 1`` node columns, blocks of size ``m = 2 (ny + 1)``
(elements quadratic along the strip: two node columns per block, :mod:`jaxfric.fem.mesh`).
Friction makes it non-symmetric, so nothing here assumes symmetry. A force-driven tool adds
``k`` global unknowns that border the strip matrix,

    [[A, B],   [x]   [f]
     [C, D]] @ [z] = [g],

with ``A`` block-tridiagonal (n x n, n = nb m), ``B`` (n, k), ``C`` (k, n), ``D`` (k, k).

``block_tridiag_solve`` is block LU without pivoting across blocks (the block Thomas
algorithm; Golub & Van Loan, *Matrix Computations*, block tridiagonal systems), with partial
pivoting inside each m x m block. ``bordered_solve`` eliminates the border by a Schur
complement. ``linear_solve`` wraps either in ``jax.lax.custom_linear_solve`` so that forward and
reverse derivatives (and implicit differentiation of a Newton solve) reuse the structured solver.
``dense_solve`` is the dense reference for tests.

``block_cyclic_solve`` is the same elimination in odd-even order (block cyclic reduction; Golub & Van
Loan, ibid.): about twice the flops, but log2(nb) batched levels instead of nb sequential steps. On a
CPU the Thomas sweep is faster; on a GPU, where each sequential step is a kernel launch of a few
microseconds' work, the levels win. :func:`block_solver` chooses which one the solves trace.
"""

import contextlib
import contextvars

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax


def _mT(a: jax.Array) -> jax.Array:
    """Transpose of the trailing two axes (leading batch axes untouched)."""
    return jnp.swapaxes(a, -1, -2)


class BlockTridiag(eqx.Module):
    """Block-tridiagonal matrix ``A`` with ``nb`` square blocks of size ``m``.

    ``A[i, i] = diag[i]``, ``A[i+1, i] = lower[i]``, ``A[i, i+1] = upper[i]``; the unknown
    vector is ordered block by block (node column by node column).

    Attributes:
        lower: sub-diagonal blocks, shape (nb-1, m, m).
        diag: diagonal blocks, shape (nb, m, m).
        upper: super-diagonal blocks, shape (nb-1, m, m).
    """

    lower: jax.Array
    diag: jax.Array
    upper: jax.Array

    def __check_init__(self):
        # Only trailing axes are checked, so that a batch of matrices (leading axes) can be
        # built and then vmapped over.
        if jnp.ndim(self.diag) < 3 or self.diag.shape[-1] != self.diag.shape[-2]:
            raise ValueError(f"diag must have shape (nb, m, m), got {jnp.shape(self.diag)}")
        nb, m = self.diag.shape[-3], self.diag.shape[-1]
        for name in ("lower", "upper"):
            shape = jnp.shape(getattr(self, name))
            if len(shape) < 3 or shape[-3:] != (nb - 1, m, m):
                raise ValueError(f"{name} must have shape ({nb - 1}, {m}, {m}), got {shape}")

    @property
    def num_blocks(self) -> int:
        """Number of diagonal blocks ``nb`` (static)."""
        return self.diag.shape[-3]

    @property
    def block_size(self) -> int:
        """Block size ``m`` (static)."""
        return self.diag.shape[-1]

    @property
    def shape(self) -> tuple[int, int]:
        """``(nb m, nb m)`` (static)."""
        n = self.num_blocks * self.block_size
        return (n, n)

    def matvec(self, x: jax.Array) -> jax.Array:
        """``A @ x`` for ``x`` of shape (n,) or (n, r); same shape out."""
        nb, m = self.num_blocks, self.block_size
        xb = x.reshape(nb, m, -1)
        zero = jnp.zeros((1,) + xb.shape[1:], dtype=xb.dtype)
        y = jnp.einsum("bij,bjr->bir", self.diag, xb)
        # Concatenating a zero block instead of scattering keeps this a few fused ops.
        y = y + jnp.concatenate([zero, jnp.einsum("bij,bjr->bir", self.lower, xb[:-1])], 0)
        y = y + jnp.concatenate([jnp.einsum("bij,bjr->bir", self.upper, xb[1:]), zero], 0)
        return y.reshape(x.shape)

    def transpose(self) -> "BlockTridiag":
        """``A.T``: the block pattern swaps lower and upper, every block is transposed."""
        return BlockTridiag(lower=_mT(self.upper), diag=_mT(self.diag), upper=_mT(self.lower))

    def to_dense(self) -> jax.Array:
        """Dense (n, n) matrix, for tests and the reference solver."""
        nb, m = self.num_blocks, self.block_size
        i = jnp.arange(nb)
        # Indexing (block row, row, block column, column) puts the block index first, which
        # matches the (nb, m, m) layout of the block arrays.
        dense = jnp.zeros((nb, m, nb, m), dtype=self.diag.dtype)
        dense = dense.at[i, :, i, :].set(self.diag)
        dense = dense.at[i[1:], :, i[:-1], :].set(self.lower)
        dense = dense.at[i[:-1], :, i[1:], :].set(self.upper)
        return dense.reshape(nb * m, nb * m)


class Bordered(eqx.Module):
    """Block-tridiagonal ``A`` bordered by ``k`` extra unknowns: ``[[A, B], [C, D]]``.

    The unknown vector is ``[x, z]`` with ``x`` the n strip dofs and ``z`` the k global
    unknowns (e.g. positions of force-driven tools).

    Attributes:
        A: the strip matrix, n x n block-tridiagonal.
        B: coupling of the strip equations to the extra unknowns, shape (n, k).
        C: coupling of the extra equations to the strip dofs, shape (k, n).
        D: extra equations in the extra unknowns, shape (k, k).
    """

    A: BlockTridiag
    B: jax.Array
    C: jax.Array
    D: jax.Array

    def __check_init__(self):
        if jnp.ndim(self.D) < 2:
            raise ValueError(f"D must have shape (k, k), got {jnp.shape(self.D)}")
        n, k = self.A.shape[0], self.D.shape[-1]
        expected = {"B": (n, k), "C": (k, n), "D": (k, k)}
        for name, want in expected.items():
            shape = jnp.shape(getattr(self, name))
            if len(shape) < 2 or shape[-2:] != want:
                raise ValueError(f"{name} must have shape {want} (n={n}, k={k}), got {shape}")

    @property
    def num_extra(self) -> int:
        """Number of bordering unknowns ``k`` (static)."""
        return self.D.shape[-1]

    @property
    def shape(self) -> tuple[int, int]:
        """``(n + k, n + k)`` (static)."""
        n = self.A.shape[0] + self.num_extra
        return (n, n)

    def matvec(self, x: jax.Array) -> jax.Array:
        """``[[A, B], [C, D]] @ x`` for ``x`` of shape (n+k,) or (n+k, r); same shape out."""
        n = self.A.shape[0]
        x_strip, z = x[:n], x[n:]
        top = self.A.matvec(x_strip) + self.B @ z
        bottom = self.C @ x_strip + self.D @ z
        return jnp.concatenate([top, bottom], axis=0)

    def transpose(self) -> "Bordered":
        """``[[A.T, C.T], [B.T, D.T]]``."""
        return Bordered(A=self.A.transpose(), B=_mT(self.C), C=_mT(self.B), D=_mT(self.D))

    def to_dense(self) -> jax.Array:
        """Dense (n+k, n+k) matrix, for tests and the reference solver."""
        top = jnp.concatenate([self.A.to_dense(), self.B], axis=1)
        bottom = jnp.concatenate([self.C, self.D], axis=1)
        return jnp.concatenate([top, bottom], axis=0)


def _small_matmul(a: jax.Array, b: jax.Array) -> jax.Array:
    """``a @ b`` for small blocks as a broadcast product and a sum.

    XLA:CPU fuses this with its neighbours, whereas a ``dot`` is a separate kernel call per
    scan step; for m = 8 to 14 this is measurably faster (about 0.3 us less per product).
    """
    return jnp.sum(a[:, :, None] * b[None, :, :], axis=1)


def _lu_solve(S: jax.Array, R: jax.Array) -> jax.Array:
    """``S^{-1} R`` for one small block by LU with partial pivoting. S (m, m), R (m, r).

    LAPACK's getrf on the wide matrix ``[S | R]`` chooses its pivots in the first m columns
    and carries the row swaps and the elimination through R:
    ``P [S | R] = L [U | L^{-1} P R]``. What is left is one upper triangular solve, with no
    permutation to apply and no separate lower triangular solve.
    """
    m = S.shape[-1]
    lu, _, _ = lax.linalg.lu(jnp.concatenate([S, R], axis=-1))
    return lax.linalg.triangular_solve(lu[:, :m], lu[:, m:], left_side=True, lower=False)


def _block_thomas(A: BlockTridiag, rhs: jax.Array) -> jax.Array:
    """Solve ``A X = R`` for ``R`` of shape (nb, m, r); returns X of shape (nb, m, r).

    Forward sweep, with ``S_0 = D_0``, ``y_0 = R_0``:

        S_i = D_i - L_{i-1} G_{i-1},   y_i = R_i - L_{i-1} g_{i-1},
        [G_i | g_i] = S_i^{-1} [U_i | y_i],

    where ``L_{i-1} = A[i, i-1]`` and ``U_i = A[i, i+1]``; backward sweep
    ``x_{nb-1} = g_{nb-1}``, ``x_i = g_i - G_i x_{i+1}``.
    """
    nb, m, r = rhs.shape
    dtype = A.diag.dtype
    zero_block = jnp.zeros((1, m, m), dtype=dtype)
    # A zero L before the first block and a zero U after the last one make every step
    # identical (S_0 = D_0, G_{nb-1} = 0), so nb = 1 needs no special case.
    lower = jnp.concatenate([zero_block, A.lower], axis=0)
    upper = jnp.concatenate([A.upper, zero_block], axis=0)
    diag_rhs = jnp.concatenate([A.diag, rhs], axis=2)

    def forward(prev, block):
        lower_i, diag_rhs_i, upper_i = block
        # [S_i | y_i] in one matmul, since both subtract L_{i-1} times the previous [G | g].
        schur_rhs = diag_rhs_i - _small_matmul(lower_i, prev)
        # One LU of S_i serves U_i and the rhs together: a single pair of triangular solves.
        out = _lu_solve(schur_rhs[:, :m], jnp.concatenate([upper_i, schur_rhs[:, m:]], axis=1))
        return out, out

    init = jnp.zeros((m, m + r), dtype=dtype)
    _, Gg = lax.scan(forward, init, (lower, diag_rhs, upper))

    # Keeping G_i = S_i^{-1} U_i (not the LU factors) from the forward sweep leaves one small
    # matrix product per block for the backward sweep.
    def backward(x_next, Gg_i):
        x_i = Gg_i[:, m:] - _small_matmul(Gg_i[:, :m], x_next)
        return x_i, x_i

    _, x = lax.scan(backward, jnp.zeros((m, r), dtype=dtype), Gg, reverse=True)
    return x


def _gauss_jordan(S: jax.Array, R: jax.Array) -> jax.Array:
    """``S^{-1} R`` for a batch of small blocks: S (..., m, m), R (..., m, r).

    Gauss-Jordan elimination with partial pivoting on ``[S | R]``, unrolled over the m pivots and
    written in elementwise operations, so that it vectorises over any leading axes (levels of the
    cyclic reduction, vmapped members) without a library call per block. A zero pivot gives
    non-finite output (the caller checks).
    """
    m = S.shape[-1]
    M = jnp.concatenate([S, R], axis=-1)
    rows = jnp.arange(m)
    for k in range(m):
        # Pivot: the largest |entry| of column k among rows k..m-1, swapped into row k.
        p = jnp.argmax(jnp.where(rows >= k, jnp.abs(M[..., :, k]), -1.0), axis=-1)
        row_p = jnp.take_along_axis(M, p[..., None, None], axis=-2)
        M = jnp.where((rows == p[..., None])[..., None], M[..., k:k + 1, :], M)
        pivot_row = row_p / row_p[..., k:k + 1]
        M = jnp.where((rows == k)[:, None], pivot_row, M - M[..., :, k:k + 1] * pivot_row)
    return M[..., :, m:]


def _cyclic_reduction(lower, diag, upper, rhs):
    """Solve one block-tridiagonal system by odd-even reduction; blocks as full-length arrays.

    ``lower[i] = A[i, i-1]`` (zero for i = 0), ``upper[i] = A[i, i+1]`` (zero for the last block),
    all of shape (N, m, m) with N a power of two; rhs (N, m, r). Each level solves the odd rows for
    their unknowns in terms of the even neighbours, ``x_i = c_i - P_i x_{i-1} - Q_i x_{i+1}`` with
    ``[P_i | Q_i | c_i] = D_i^{-1} [L_i | U_i | r_i]``, and substitutes them into the even rows:

        L'_j = -L_j P_{j-1},   D'_j = D_j - L_j Q_{j-1} - U_j P_{j+1},   U'_j = -U_j Q_{j+1},
        r'_j = r_j - L_j c_{j-1} - U_j c_{j+1},

    which is again block tridiagonal, on the even rows; then back-substitutes the odd rows.
    """
    n, m, r = rhs.shape
    if n == 1:
        return _gauss_jordan(diag, rhs)
    PQc = _gauss_jordan(diag[1::2], jnp.concatenate([lower[1::2], upper[1::2], rhs[1::2]], axis=-1))
    P, Q, c = PQc[..., :m], PQc[..., m:2 * m], PQc[..., 2 * m:]
    # Even row j = 2k: its right odd neighbour is k of the odd arrays, its left one k - 1 (none for
    # k = 0, where L_0 = 0; a zero block stands in).
    def left(a):
        return jnp.concatenate([jnp.zeros_like(a[:1]), a[:-1]], axis=0)

    Le, De, Ue, re = lower[0::2], diag[0::2], upper[0::2], rhs[0::2]
    mm = jnp.matmul
    x_even = _cyclic_reduction(-mm(Le, left(P)), De - mm(Le, left(Q)) - mm(Ue, P), -mm(Ue, Q),
                               re - mm(Le, left(c)) - mm(Ue, c))
    # Odd row i = 2k + 1: neighbours x_even[k] and x_even[k + 1] (none after the last; Q is zero there).
    x_next = jnp.concatenate([x_even[1:], jnp.zeros_like(x_even[:1])], axis=0)
    x_odd = c - mm(P, x_even) - mm(Q, x_next)
    return jnp.stack([x_even, x_odd], axis=1).reshape(n, m, r)


def block_cyclic_solve(A: BlockTridiag, b: jax.Array) -> jax.Array:
    """Solve ``A x = b`` by block cyclic reduction: log2(nb) batched levels (see the module doc).

    The system is padded to a power of two of blocks with identity blocks; small blocks are
    inverted by Gauss-Jordan with partial pivoting inside each block, none across blocks (as the
    Thomas sweep). Same arguments and result as :func:`block_tridiag_solve`.
    """
    nb, m = A.num_blocks, A.block_size
    rhs = b.reshape(nb, m, -1)
    n = 1 << max(nb - 1, 0).bit_length()
    pad = n - nb
    dtype = A.diag.dtype
    zeros = jnp.zeros((1, m, m), dtype=dtype)
    eye = jnp.broadcast_to(jnp.eye(m, dtype=dtype), (pad, m, m))
    lower = jnp.concatenate([zeros, A.lower, jnp.zeros((pad, m, m), dtype)], axis=0)
    upper = jnp.concatenate([A.upper, jnp.zeros((pad + 1, m, m), dtype)], axis=0)
    diag = jnp.concatenate([A.diag, eye], axis=0)
    rhs = jnp.concatenate([rhs, jnp.zeros((pad,) + rhs.shape[1:], dtype=rhs.dtype)], axis=0)
    x = _cyclic_reduction(lower, diag, upper, rhs)[:nb]
    return x.reshape(b.shape)


BLOCK_SOLVERS = ("auto", "thomas", "cyclic")
_SOLVER = contextvars.ContextVar("block_solver", default="auto")


@contextlib.contextmanager
def block_solver(name: str):
    """Trace the block-tridiagonal solves with ``name``: ``"thomas"``, ``"cyclic"`` or ``"auto"``.

    ``"auto"`` (the default) is the cyclic reduction where JAX's default backend is a GPU and the
    Thomas sweep elsewhere (docs/results.md, batched sweeps: on a CPU the sweep is faster and compiles
    in less than half the time; on an H100 the Thomas sweep's 241 sequential steps cost 22 ms an
    iteration, the reduction 0.5 ms). A setting read when a program is traced, not when it runs: a
    program already compiled keeps its solver, and ``jax.jit`` reuses a function's trace."""
    if name not in BLOCK_SOLVERS:
        raise ValueError(f"block solver must be one of {BLOCK_SOLVERS}, got {name!r}")
    token = _SOLVER.set(name)
    try:
        yield
    finally:
        _SOLVER.reset(token)


def on_gpu() -> bool:
    """Whether JAX's default backend (where programs traced now will run) is a GPU."""
    return jax.default_backend() in ("gpu", "cuda", "rocm")


def resolved_block_solver() -> str:
    """The solver a solve traced now uses: ``"thomas"`` or ``"cyclic"`` (``"auto"`` resolved)."""
    name = _SOLVER.get()
    if name == "auto":
        return "cyclic" if on_gpu() else "thomas"
    return name


def block_tridiag_solve(A: BlockTridiag, b: jax.Array) -> jax.Array:
    """Solve ``A x = b`` by block LU (block Thomas algorithm) in two ``lax.scan`` sweeps.

    No pivoting across blocks; each m x m Schur block ``S_i = D_i - L_{i-1} S_{i-1}^{-1}
    U_{i-1}`` is factorised by LU with partial pivoting. Cost about nb (14/3 m^3 + 6 m^2 r)
    flops, memory nb m (m + r). A singular Schur block gives non-finite output (the caller
    checks). Traced on a GPU, or under ``block_solver("cyclic")``, it is :func:`block_cyclic_solve`.

    Args:
        A: block-tridiagonal matrix, n = nb m.
        b: right-hand side, shape (n,) or (n, r).

    Returns:
        x with the shape of b.
    """
    if resolved_block_solver() == "cyclic":
        return block_cyclic_solve(A, b)
    nb, m = A.num_blocks, A.block_size
    x = _block_thomas(A, b.reshape(nb, m, -1))
    return x.reshape(b.shape)


def bordered_solve(M: Bordered, b: jax.Array) -> jax.Array:
    """Solve ``[[A, B], [C, D]] [x; z] = [f; g]`` by a Schur complement on the border.

    ``A [X | y] = [B | f]`` is solved in one block-Thomas sweep with k + r right-hand sides
    (a single factorisation of A), then the k x k Schur system

        (D - C X) z = g - C y,   x = y - X z.

    Args:
        M: bordered matrix, n strip dofs and k extra unknowns.
        b: right-hand side ``[f; g]``, shape (n+k,) or (n+k, r).

    Returns:
        ``[x; z]`` with the shape of b.
    """
    n, k = M.A.shape[0], M.num_extra
    if k == 0:
        return block_tridiag_solve(M.A, b)
    rhs = b.reshape(n + k, -1)
    f, g = rhs[:n], rhs[n:]
    sol = block_tridiag_solve(M.A, jnp.concatenate([M.B, f], axis=1))
    X, y = sol[:, :k], sol[:, k:]
    z = _lu_solve(M.D - M.C @ X, g - M.C @ y)
    x = y - X @ z
    return jnp.concatenate([x, z], axis=0).reshape(b.shape)


def dense_solve(M: BlockTridiag | Bordered, b: jax.Array) -> jax.Array:
    """Reference ``M x = b`` through the dense matrix (O(n^3); tests only)."""
    return jnp.linalg.solve(M.to_dense(), b)


def _structured_solve(M: BlockTridiag | Bordered, b: jax.Array) -> jax.Array:
    """Dispatch on the (static) type of M."""
    if isinstance(M, Bordered):
        return bordered_solve(M, b)
    if isinstance(M, BlockTridiag):
        return block_tridiag_solve(M, b)
    raise TypeError(f"linear_solve expects a BlockTridiag or Bordered, got {type(M).__name__}")


def linear_solve(M: BlockTridiag | Bordered, b: jax.Array) -> jax.Array:
    """Differentiable structured solve of ``M x = b``, b of shape (n,) or (n, r).

    Wraps the structured solver in ``lax.custom_linear_solve``: the jvp is
    ``dx = M^{-1} (db - dM x)`` and the vjp uses the structured solve of ``M.T``, so
    derivatives (and implicit differentiation of a Newton solve) never differentiate through
    the LU factorisations.
    """
    # Fail at trace time for unsupported types, not inside custom_linear_solve's tracing.
    if not isinstance(M, (BlockTridiag, Bordered)):
        raise TypeError(f"linear_solve expects a BlockTridiag or Bordered, got {type(M).__name__}")
    return lax.custom_linear_solve(
        M.matvec,
        b,
        solve=lambda _matvec, rhs: _structured_solve(M, rhs),
        transpose_solve=lambda _vecmat, rhs: _structured_solve(M.transpose(), rhs),
    )
