"""Structured solvers against dense references, under vmap and under jvp/grad.

Every check runs inside one ``jax.jit`` per test case, and test data and value references come
from NumPy: compiling is what costs time here, not solving.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfric.numerics.linalg import (
    BlockTridiag,
    Bordered,
    block_cyclic_solve,
    block_solver,
    block_tridiag_solve,
    bordered_solve,
    dense_solve,
    linear_solve,
    resolved_block_solver,
)

RTOL = 1e-10


def rel_err(x, ref):
    x, ref = np.asarray(x), np.asarray(ref)
    return np.linalg.norm(x - ref) / np.linalg.norm(ref)


def random_block_tridiag(seed, nb, m, batch=()):
    """Non-symmetric, block-diagonally dominant (hence well-conditioned) matrix."""
    rng = np.random.default_rng(seed)
    lower = rng.standard_normal(batch + (nb - 1, m, m))
    upper = rng.standard_normal(batch + (nb - 1, m, m))
    # Row sums of |off-diagonal| entries are about 2.4 m, so 4 m on the diagonal dominates.
    diag = rng.standard_normal(batch + (nb, m, m)) + 4.0 * m * np.eye(m)
    return BlockTridiag(lower=jnp.asarray(lower), diag=jnp.asarray(diag), upper=jnp.asarray(upper))


def random_bordered(seed, nb, m, k, batch=(), coupling=1.0):
    """Bordered matrix with a well-conditioned Schur complement D - C A^-1 B."""
    rng = np.random.default_rng(seed + 1000)
    n = nb * m
    B = coupling * rng.standard_normal(batch + (n, k))
    C = coupling * rng.standard_normal(batch + (k, n))
    D = rng.standard_normal(batch + (k, k)) + 2.0 * n * np.eye(k)
    A = random_block_tridiag(seed, nb, m, batch)
    return Bordered(A=A, B=jnp.asarray(B), C=jnp.asarray(C), D=jnp.asarray(D))


def numpy_dense(M):
    """Dense matrix assembled in NumPy, independently of ``to_dense``."""
    if isinstance(M, Bordered):
        A = numpy_dense(M.A)
        return np.block([[A, np.asarray(M.B)], [np.asarray(M.C), np.asarray(M.D)]])
    nb, m = M.num_blocks, M.block_size
    dense = np.zeros((nb * m, nb * m))
    for i in range(nb):
        dense[i * m : (i + 1) * m, i * m : (i + 1) * m] = M.diag[i]
    for i in range(nb - 1):
        dense[(i + 1) * m : (i + 2) * m, i * m : (i + 1) * m] = M.lower[i]
        dense[i * m : (i + 1) * m, (i + 1) * m : (i + 2) * m] = M.upper[i]
    return dense


def random_like(seed, tree):
    """Standard normal pytree with the structure and shapes of ``tree``."""
    rng = np.random.default_rng(seed)
    return jax.tree.map(lambda leaf: jnp.asarray(rng.standard_normal(leaf.shape)), tree)


def tree_axpy(alpha, x, y):
    """alpha x + y, leaf by leaf."""
    return jax.tree.map(lambda a, b: alpha * a + b, x, y)


def make_matrix(kind, seed, batch=()):
    if kind == "tridiag":
        return random_block_tridiag(seed, 7, 4, batch)
    return random_bordered(seed, 7, 4, 2, batch)


def take(tree, i):
    return jax.tree.map(lambda leaf: leaf[i], tree)


# --- the matrix types --------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["tridiag", "bordered"])
def test_matvec_transpose_to_dense(kind):
    M = make_matrix(kind, 0)
    rng = np.random.default_rng(1)
    x = rng.standard_normal(M.shape[0])
    X = rng.standard_normal((M.shape[0], 3))

    @jax.jit
    def compute(M, x, X):
        return M.to_dense(), M.matvec(x), M.matvec(X), M.transpose().to_dense()

    dense, Mx, MX, transposed = compute(M, x, X)
    reference = numpy_dense(M)
    assert dense.shape == M.shape == M.transpose().shape
    assert np.array_equal(dense, reference)
    assert np.array_equal(transposed, reference.T)
    assert rel_err(Mx, reference @ x) < 1e-14
    assert rel_err(MX, reference @ X) < 1e-14


def test_bad_shapes_raise():
    A = random_block_tridiag(0, 4, 2)
    with pytest.raises(ValueError, match="upper"):
        BlockTridiag(lower=A.lower, diag=A.diag, upper=A.upper[1:])
    with pytest.raises(ValueError, match="diag"):
        BlockTridiag(lower=A.lower, diag=A.diag[..., :1], upper=A.upper)
    with pytest.raises(ValueError, match="C"):
        Bordered(A=A, B=jnp.zeros((8, 1)), C=jnp.zeros((1, 7)), D=jnp.zeros((1, 1)))


# --- solves against the dense reference --------------------------------------------------------


@pytest.mark.parametrize("nb", [1, 2, 7, 50])
@pytest.mark.parametrize("m", [2, 8])
def test_block_tridiag_solve_matches_dense(nb, m):
    A = random_block_tridiag(nb * 100 + m, nb, m)
    rng = np.random.default_rng(1)
    b = rng.standard_normal(nb * m)
    B = rng.standard_normal((nb * m, 3))
    x, X = jax.jit(lambda A, b, B: (block_tridiag_solve(A, b), block_tridiag_solve(A, B)))(A, b, B)
    assert x.shape == b.shape and X.shape == B.shape
    dense = numpy_dense(A)
    assert rel_err(x, np.linalg.solve(dense, b)) < RTOL
    assert rel_err(X, np.linalg.solve(dense, B)) < RTOL


def test_block_tridiag_solve_pivots_inside_blocks():
    # Reversing the rows inside every block row keeps the solution but puts an exact zero on
    # the (0, 0) entry of the first Schur block: an unpivoted block LU would divide by zero.
    nb, m = 6, 4
    A = random_block_tridiag(3, nb, m)
    A = BlockTridiag(lower=A.lower, diag=A.diag.at[0, m - 1, 0].set(0.0), upper=A.upper)
    flipped = BlockTridiag(lower=A.lower[:, ::-1], diag=A.diag[:, ::-1], upper=A.upper[:, ::-1])
    assert flipped.diag[0, 0, 0] == 0.0
    b = np.random.default_rng(4).standard_normal(nb * m)
    b_flipped = b.reshape(nb, m)[:, ::-1].reshape(-1)
    x = jax.jit(block_tridiag_solve)(flipped, b_flipped)
    assert rel_err(x, np.linalg.solve(numpy_dense(A), b)) < RTOL


@pytest.mark.parametrize("nb", [1, 2, 3, 8, 9, 50])
def test_block_cyclic_solve_matches_dense_and_thomas(nb):
    """Odd-even reduction (padded to a power of two of blocks) against the dense solve and the
    Thomas sweep: block counts at, below and above a power of two, one and several right-hand sides."""
    m = 6
    A = random_block_tridiag(nb * 10 + 1, nb, m)
    rng = np.random.default_rng(2)
    b = rng.standard_normal(nb * m)
    B = rng.standard_normal((nb * m, 3))
    x, X, X_thomas = jax.jit(lambda A, b, B: (block_cyclic_solve(A, b), block_cyclic_solve(A, B),
                                             block_tridiag_solve(A, B)))(A, b, B)
    assert x.shape == b.shape and X.shape == B.shape
    dense = numpy_dense(A)
    assert rel_err(x, np.linalg.solve(dense, b)) < RTOL
    assert rel_err(X, np.linalg.solve(dense, B)) < RTOL
    assert rel_err(X, X_thomas) < RTOL


def test_block_cyclic_solve_pivots_inside_blocks():
    # As for the Thomas sweep: an exact zero on the (0, 0) entry of a diagonal block (here of an
    # odd block, the first one the reduction inverts, and of the first) needs a row swap.
    nb, m = 6, 4
    A = random_block_tridiag(5, nb, m)
    diag = A.diag.at[:, 0, 0].set(0.0)
    A = BlockTridiag(lower=A.lower, diag=diag, upper=A.upper)
    b = np.random.default_rng(6).standard_normal(nb * m)
    x = jax.jit(block_cyclic_solve)(A, b)
    assert rel_err(x, np.linalg.solve(numpy_dense(A), b)) < RTOL


def test_block_solver_switches_what_linear_solve_traces():
    """``block_solver("cyclic")`` makes the solves traced under it (bordered, vmapped, through
    ``linear_solve`` and its derivatives) use the cyclic reduction; the answers agree."""
    M = random_bordered(3, 9, 4, 2, batch=(2,), coupling=10.0)
    bs = np.random.default_rng(9).standard_normal((2, M.shape[-1]))

    def f(M, b):
        return jnp.sum(linear_solve(M, b) ** 2)

    def program():
        # A new function each time: jit's trace cache is keyed on the function, not on the setting.
        return jax.jit(lambda M, b: jax.vmap(lambda M, b: (linear_solve(M, b),
                                                           jax.grad(f, argnums=1)(M, b)))(M, b))

    thomas = program()
    ref = thomas(M, bs)
    with block_solver("cyclic"):
        cyclic = program()
        lowered = cyclic.lower(M, bs).as_text()
        cyc = cyclic(M, bs)
    for a, r in zip(cyc, ref):
        assert rel_err(a, r) < RTOL
    # The cyclic program has no sequential sweep over the 9 blocks (its loops left are the pivoting
    # of the border's 2 x 2 LU); the Thomas one sweeps forward and back, for the solve and its transpose.
    assert "dense<9>" not in lowered
    assert "dense<9>" in thomas.lower(M, bs).as_text()
    with pytest.raises(ValueError, match="block solver"):
        with block_solver("lu"):
            pass
    # "auto" (the default) is the Thomas sweep on a CPU, as every other test here runs.
    if jax.default_backend() == "cpu":
        assert resolved_block_solver() == "thomas"
        with block_solver("cyclic"):
            assert resolved_block_solver() == "cyclic"


@pytest.mark.parametrize(
    ("nb", "k", "num_rhs"), [(7, 0, None), (7, 1, None), (7, 3, None), (1, 3, 2)]
)
def test_bordered_solve_matches_dense(nb, k, num_rhs):
    # Strong coupling, so that the border matters: z differs from the decoupled D^-1 g.
    M = random_bordered(10 * k + nb, nb, 4, k, coupling=10.0)
    shape = (M.shape[0],) if num_rhs is None else (M.shape[0], num_rhs)
    b = np.random.default_rng(1).standard_normal(shape)
    x = jax.jit(bordered_solve)(M, b)
    assert x.shape == b.shape
    assert rel_err(x, np.linalg.solve(numpy_dense(M), b)) < RTOL
    if k > 0:
        decoupled_z = np.linalg.solve(M.D, b[-k:])
        assert np.max(np.abs(x[-k:] - decoupled_z)) > 1e-3


# --- vmap ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["tridiag", "bordered"])
def test_vmap_matches_loop(kind):
    batch = 3
    Ms = make_matrix(kind, 7, batch=(batch,))
    bs = np.random.default_rng(8).standard_normal((batch, Ms.shape[0]))
    structured_solve = block_tridiag_solve if kind == "tridiag" else bordered_solve

    @jax.jit
    def compute(Ms, bs):
        looped = jax.lax.map(lambda Mb: structured_solve(*Mb), (Ms, bs))
        batched = jax.vmap(structured_solve)(Ms, bs)
        # One matrix, a batch of right-hand sides, through the custom_linear_solve wrapper.
        rhs_batched = jax.vmap(linear_solve, in_axes=(None, 0))(take(Ms, 0), bs)
        return looped, batched, rhs_batched

    looped, batched, rhs_batched = compute(Ms, bs)
    assert rel_err(batched, looped) < 1e-13
    dense_0 = numpy_dense(take(Ms, 0))
    assert rel_err(looped[0], np.linalg.solve(dense_0, bs[0])) < RTOL
    assert rel_err(rhs_batched, np.linalg.solve(dense_0, bs.T).T) < RTOL


# --- derivatives of linear_solve --------------------------------------------------------------


@pytest.mark.parametrize("kind", ["tridiag", "bordered"])
def test_linear_solve_jvp_matches_dense_and_finite_differences(kind):
    M = make_matrix(kind, 11)
    b = np.random.default_rng(12).standard_normal(M.shape[0])
    dM = random_like(13, M)
    db = np.random.default_rng(14).standard_normal(b.shape)
    eps = 1e-5

    @jax.jit
    def compute(M, b, dM, db):
        x, dx = jax.jvp(linear_solve, (M, b), (dM, db))
        x_ref, dx_ref = jax.jvp(dense_solve, (M, b), (dM, db))
        # Central difference along the same random direction.
        perturbed = lambda t: linear_solve(tree_axpy(t, dM, M), b + t * db)  # noqa: E731
        x_minus, x_plus = jax.vmap(perturbed)(jnp.array([-eps, eps]))
        return x, dx, x_ref, dx_ref, (x_plus - x_minus) / (2 * eps)

    x, dx, x_ref, dx_ref, dx_fd = compute(M, b, dM, db)
    assert rel_err(x_ref, np.linalg.solve(numpy_dense(M), b)) < RTOL
    assert rel_err(x, x_ref) < RTOL
    assert rel_err(dx, dx_ref) < 1e-8
    assert rel_err(dx_fd, dx) < 1e-6


@pytest.mark.parametrize("kind", ["tridiag", "bordered"])
def test_linear_solve_grad_matches_dense(kind):
    M = make_matrix(kind, 21)
    b = np.random.default_rng(22).standard_normal(M.shape[0])
    weights = jnp.arange(M.shape[0], dtype=jnp.float64)

    def loss(solve, M, b):
        # Non-linear in x so that the cotangent is not constant.
        return jnp.sum(jnp.sin(solve(M, b)) * weights)

    @jax.jit
    def compute(M, b):
        grad = jax.grad(lambda M, b: loss(linear_solve, M, b), argnums=(0, 1))(M, b)
        grad_ref = jax.grad(lambda M, b: loss(dense_solve, M, b), argnums=(0, 1))(M, b)
        return grad, grad_ref

    (gM, gb), (gM_ref, gb_ref) = compute(M, b)
    assert rel_err(gb, gb_ref) < 1e-8
    for leaf, leaf_ref in zip(jax.tree.leaves(gM), jax.tree.leaves(gM_ref), strict=True):
        assert rel_err(leaf, leaf_ref) < 1e-8


@pytest.mark.parametrize("kind", ["tridiag", "bordered"])
def test_linear_solve_dot_product(kind):
    """<w, J v> = <J^T w, v> for the linear map rhs -> x, J^T from jax.linear_transpose."""
    M = make_matrix(kind, 31)
    rng = np.random.default_rng(32)
    w, v = (rng.standard_normal(M.shape[0]) for _ in range(2))

    @jax.jit
    def compute(M, w, v):
        solve_rhs = lambda rhs: linear_solve(M, rhs)  # noqa: E731
        # linear_transpose runs the structured solve of M.T (custom_linear_solve's transpose).
        (JT_w,) = jax.linear_transpose(solve_rhs, v)(w)
        return JT_w, jnp.vdot(w, solve_rhs(v)), jnp.vdot(JT_w, v)

    JT_w, lhs, rhs = compute(M, w, v)
    assert abs(lhs - rhs) < 1e-12 * abs(lhs)
    assert rel_err(JT_w, np.linalg.solve(numpy_dense(M).T, w)) < RTOL


def test_linear_solve_vmap_of_grad():
    Ms = random_block_tridiag(41, 5, 2, batch=(2,))
    bs = np.random.default_rng(42).standard_normal((2, Ms.shape[0]))
    grad = jax.grad(lambda b, M: jnp.sum(linear_solve(M, b) ** 2))
    g = jax.jit(jax.vmap(grad))(bs, Ms)
    for i in range(2):
        # d/db |A^-1 b|^2 = 2 A^-T A^-1 b
        dense = numpy_dense(take(Ms, i))
        expected = 2.0 * np.linalg.solve(dense.T, np.linalg.solve(dense, bs[i]))
        assert rel_err(g[i], expected) < 1e-10


def test_linear_solve_rejects_dense_matrix():
    with pytest.raises(TypeError, match="BlockTridiag or Bordered"):
        linear_solve(jnp.eye(2), jnp.ones(2))
