"""The Alart-Curnier equations of the linearised contact problem (Alart & Curnier 1991), solved piece by
piece: the refinement of Lemke's answers (:func:`polish`) and the active-set labels, residual and
generalised Jacobian that the in-loop solver ``lcp_ssn`` (:mod:`jaxfric.contact.exact`) writes for every node.

Per candidate, with ``sigma_N = R_N - c_N g_N`` and ``sigma_T = R_T - c_T s``,

    C_N = R_N - max(0, sigma_N) = 0,
    C_T = R_T - clip(sigma_T, -mu max(0, sigma_N), +mu max(0, sigma_N)) = 0,

is exactly the Signorini-Coulomb law of :mod:`jaxfric.contact.lcp`, for any c_N, c_T > 0 (N/mm per
mm), which only steer the classification. The equations are piecewise linear: on the piece of an
active set (open, stick, or slip with its direction) they are affine, and one linear solve lands on
that piece's solution exactly.

Units: lengths mm, forces N/mm (per unit width), stiffness N/mm per mm.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

from .lcp import ForceDrive, coupling_matrix, interleave

__all__ = [
    "OPEN",
    "STICK",
    "SLIP_POS",
    "SLIP_NEG",
    "alart_curnier_residual",
    "diagonal_parameters",
    "keep_tools_touching",
    "piece_jacobian",
    "polish",
]

_MEMORY = 5            # semismooth Newton: iterates in the non-monotone line search reference
_ARMIJO = 1e-4         # sufficient decrease factor
_MIN_STEP = 2.0**-30   # smallest step before the line search gives up

# Active-set labels of one candidate inside the Newton iteration. The slip direction is part of
# the label: a change of sign is a change of the linear piece.
OPEN, STICK, SLIP_POS, SLIP_NEG = 0, 1, 2, 3


def alart_curnier_residual(R_N, R_T, g, s, mu, c_n, c_t):
    """Active set and residual ``(C_N, C_T)`` of the Alart-Curnier equations, per candidate."""
    sig_n = R_N - c_n * g
    sig_t = R_T - c_t * s
    bound = mu * jnp.maximum(sig_n, 0.0)
    C_N = R_N - jnp.maximum(sig_n, 0.0)
    C_T = R_T - jnp.clip(sig_t, -bound, bound)
    state = jnp.where(sig_n <= 0.0, OPEN,
                      jnp.where(jnp.abs(sig_t) < bound, STICK,
                                # Without friction the slip direction plays no part.
                                jnp.where((sig_t >= 0.0) | (mu == 0.0), SLIP_POS, SLIP_NEG)))
    return state.astype(jnp.int32), jnp.stack([C_N, C_T], axis=-1), sig_n


def piece_jacobian(state, mu, c_n, c_t, mu_force=None):
    """Generalised Jacobian of (C_N, C_T) on the linear piece ``state``: C = W_F p + W_K (g, s).

    open:   C = (R_N, R_T)                                W_F = I,  W_K = 0
    stick:  C = (c_N g, c_T s)                            W_F = 0,  W_K = diag(c_N, c_T)
    slip:   C = (c_N g, R_T - mu xi (R_N - c_N g))        W_F = [[0, 0], [-mu xi, 1]],
                                                          W_K = [[c_N, 0], [mu xi c_N, 0]]
    with xi = sign(sigma_T). Returns W_F, W_K of shape (n_c, 2, 2). ``mu_force`` (n_c,), where mu is a
    function of R_N (a friction law of the pressure): the slip row's derivative in R_N,
    mu + mu'(R_N) (R_N - c_N g), in W_F in place of mu (the derivative of C_T, not a linear piece).
    """
    one, zero = jnp.ones_like(mu), jnp.zeros_like(mu)
    xi = jnp.where(state == SLIP_NEG, -1.0, 1.0)
    is_open, is_stick = state == OPEN, state == STICK
    is_slip = ~is_open & ~is_stick
    mu_f = mu if mu_force is None else mu_force
    w_f = jnp.stack([jnp.stack([jnp.where(is_open, one, zero), zero], -1),
                     jnp.stack([jnp.where(is_slip, -mu_f * xi, zero), jnp.where(is_stick, zero, one)], -1)], -2)
    closed = jnp.where(is_open, zero, c_n * one)
    w_k = jnp.stack([jnp.stack([closed, zero], -1),
                     jnp.stack([jnp.where(is_slip, mu * xi * c_n, zero), jnp.where(is_stick, c_t * one, zero)],
                               -1)], -2)
    return w_f, w_k


def _piece_solution(K_star, r_star, d0, C, P, state, mu, c_n, c_t):
    """x = (du_c, dq) solving the Alart-Curnier equations linearised on the piece ``state`` (and the
    tool rows ``C^T p = P``): one dense solve of size 2 n_c + n_q."""
    n_c, n_q = state.shape[0], C.shape[1]
    w_f, w_k = piece_jacobian(state, mu, c_n, c_t)
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
    (:func:`_semismooth_newton`, at most ``refine_iter`` iterations) starts on the pivoting's piece, and its
    answer is taken if it converges; otherwise the pivoting's own answer is kept. Open candidates are
    given zero forces. Returns ``(du_c, p, dq, iterations, solved)``: the semismooth Newton iterations
    (0 when the piece held), and whether the answer is a solution by its own piece (the piece held, or
    semismooth Newton converged), whatever the pivoting's status. The pivoting need not have ended on a
    solution: its last basis (a ray, or an end that failed :func:`jaxfric.contact.lemke.lemke`'s check) starts
    the same refinement.

    On the blankholder's lock (Lemke on a band of 256 nodes) the pivoting's values had an error of
    3e-8 mm (a stick-slip pair with |R_T| = mu R_N, land nodes at zero gap and zero force); without
    the semismooth Newton step the global Newton iteration's increment never fell below that, against
    its tolerance of 1e-9 mm, and the step was cut to its floor; with it, the step converges in 5
    iterations (``test_lemke_runs_the_blankholder_lock_and_agrees_with_semismooth_newton``).

    Lemke's answer is exact in its active set but not in its values: the tableau and the basis
    solve carry the conditioning of the condensed problem (with a force-driven tool eliminated, the
    common motion of tool and sheet is nearly free), which left the tool's force balance at 2e-8 of
    the force on a frictionless clamp, above the Newton tolerance.

    Args:
        K_star, r_star, gap, slip, mu, drive: as for :func:`jaxfric.contact.lcp.contact_lcp`.
        du_c, dq: (2 n_c,), (n_q,) the pivoting's increments, mm.
        refine_iter: semismooth Newton iterations allowed (static); 0: none.
    """
    K_star = jnp.asarray(K_star)
    dtype = K_star.dtype
    r_star, gap, slip, mu = (jnp.asarray(a, dtype) for a in (r_star, gap, slip, mu))
    n_c = gap.shape[0]
    C, P = coupling_matrix(drive, n_c, dtype)
    c_n, c_t = diagonal_parameters(K_star)
    d0 = -interleave(gap, slip)

    def classify(du, dq):
        p = (K_star @ du - r_star).reshape(n_c, 2)
        kin = (du - C @ dq - d0).reshape(n_c, 2)
        return alart_curnier_residual(p[:, 0], p[:, 1], kin[:, 0], kin[:, 1], mu, c_n, c_t)[0]

    state = classify(du_c, dq)
    x = _piece_solution(K_star, r_star, d0, C, P, state, mu, c_n, c_t)
    du_new, dq_new = x[: 2 * n_c], x[2 * n_c:]
    keep = jnp.all(classify(du_new, dq_new) == state) & jnp.all(jnp.isfinite(x))

    def refine():
        # The exact solve on the pivoting's piece falls on another piece: the pivoting's values sit on
        # a boundary within their round-off (a pair with |R_T| = mu R_N, a node at zero gap and zero
        # force). Semismooth Newton on the same problem, started on that piece, settles it.
        du_s, dq_s, iters, converged = _semismooth_newton(K_star, r_star, gap, slip, mu, drive, c_n, c_t, state,
                                                          refine_iter)
        ok = converged & jnp.all(jnp.isfinite(du_s))
        return jnp.where(ok, du_s, du_c), jnp.where(ok, dq_s, dq), iters, ok

    if refine_iter:
        du, dq, iters, solved = jax.lax.cond(keep, lambda: (du_new, dq_new, jnp.array(0, jnp.int32), keep),
                                             refine)
    else:
        du, dq, iters, solved = (jnp.where(keep, du_new, du_c), jnp.where(keep, dq_new, dq),
                                 jnp.array(0, jnp.int32), keep)
    # The forces of the piece: an open candidate carries none. K* du - r* leaves it the round-off of
    # the forces around it (1e-8 N/mm next to 300 N/mm on the blankholder's lands), above the open
    # threshold of :func:`jaxfric.contact.status.contact_status`, so that its status flipped between iterations.
    p = (K_star @ du - r_star).reshape(n_c, 2)
    p = jnp.where((classify(du, dq) == OPEN)[:, None], 0.0, p)
    return du, p.reshape(-1), dq, iters, solved


def keep_tools_touching(state, sig_n, e_dot_n):
    """Close (in stick) the candidate of largest sigma_N of every force-driven tool left with no
    closed candidate.

    With all its candidates open, a tool's row ``C^T p = P`` does not involve dq and the Newton
    matrix is singular. At a solution with P > 0 some candidate of the tool carries force, so this
    only steers the iteration; the convergence test uses the unmodified classification.
    ``e_dot_n`` (n_c, n_q) holds e_q . n per candidate and tool.
    """
    mine = e_dot_n > 0.0
    touching = jnp.any(mine & (state != OPEN)[:, None], axis=0)
    nearest = jnp.argmax(jnp.where(mine, sig_n[:, None], -jnp.inf), axis=0)
    need = ~touching & jnp.any(mine, axis=0)
    return state.at[nearest].set(jnp.where(need, STICK, state[nearest]))


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


def _semismooth_newton(K_star, r_star, gap, slip, mu, drive: ForceDrive | None, c_n, c_t, start, max_iter: int,
                       tol: float = 1e-10):
    """Solve the linearised contact problem by semismooth Newton on the Alart-Curnier equations, from the
    active set ``start`` (:func:`polish`'s refinement of a pivoting's answer).

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

    with ``C = W_F p + W_K (g, s)`` on the piece (see :func:`piece_jacobian`).

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
        K_star, r_star, gap, slip, mu, drive: as for :func:`jaxfric.contact.lcp.contact_lcp`.
        c_n, c_t: (n_c,) Alart-Curnier parameters, N/mm per mm (:func:`diagonal_parameters`).
        start: (n_c,) int32 first active set (labels :data:`OPEN` ... :data:`SLIP_NEG`).
        max_iter: linear solves allowed (static).
        tol: relative residual test, see above.

    Returns:
        ``(du_c, dq, iterations, converged)``: (2 n_c,) displacement increments (mm), (n_q,) tool
        increments (mm), the linear solves performed, and whether it converged. A failed line search,
        a non-finite iterate or ``max_iter`` solves end the iteration with ``converged = False``.
    """
    K_star = jnp.asarray(K_star)
    dtype = K_star.dtype
    r_star, gap, slip, mu = (jnp.asarray(a, dtype) for a in (r_star, gap, slip, mu))
    n_c = gap.shape[0]
    C, P = coupling_matrix(drive, n_c, dtype)
    n_q = C.shape[1]
    c_n, c_t = jnp.broadcast_to(jnp.asarray(c_n, dtype), (n_c,)), jnp.broadcast_to(jnp.asarray(c_t, dtype), (n_c,))
    d0 = -interleave(gap, slip)
    scale = jnp.max(jnp.concatenate([jnp.abs(r_star), c_n * jnp.abs(gap), c_t * jnp.abs(slip), jnp.abs(P),
                                     jnp.array([jnp.finfo(dtype).tiny], dtype)]))

    def evaluate(x):
        """Classification, merit theta, |residual|_inf, |p|_inf and sigma_N at x = (du, dq)."""
        du, dq = x[: 2 * n_c], x[2 * n_c:]
        p = K_star @ du - r_star
        kin = (du - C @ dq - d0).reshape(n_c, 2)
        p2 = p.reshape(n_c, 2)
        state, res, sig_n = alart_curnier_residual(p2[:, 0], p2[:, 1], kin[:, 0], kin[:, 1], mu, c_n, c_t)
        res_q = C.T @ p - P
        # Merit in energy units (N/mm mm): C^2 / c per equation, so that candidates of very
        # different stiffness weigh alike when c follows the stiffness.
        theta = jnp.sum(res[:, 0] ** 2 / c_n + res[:, 1] ** 2 / c_t) + jnp.sum(res_q**2) / jnp.mean(c_n)
        res_norm = jnp.maximum(jnp.max(jnp.abs(res)), jnp.max(jnp.abs(res_q), initial=0.0))
        return state, theta, res_norm, jnp.max(jnp.abs(p)), sig_n

    def newton_point(state):
        return _piece_solution(K_star, r_star, d0, C, P, state, mu, c_n, c_t)

    def next_state(state, sig_n):
        return keep_tools_touching(state, sig_n, C[0::2]) if n_q else state

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
        # classification (``start``) is used.
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
    first = jnp.asarray(start)
    state0 = next_state(first.astype(jnp.int32), sig_n0)
    thetas0 = jnp.full(_MEMORY, -jnp.inf, dtype).at[-1].set(theta0)
    carry0 = (jnp.array(0, jnp.int32), x0, state0, thetas0, jnp.array(False), jnp.array(False))
    k, x, _, _, _, converged = lax.while_loop(cond, body, carry0)
    return x[: 2 * n_c], x[2 * n_c:], k, converged
