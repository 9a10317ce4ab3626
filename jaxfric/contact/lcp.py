"""The linearised contact problem of node-to-rigid contact as a linear complementarity problem, and its
solution by Lemke's pivoting from inside ``jit``.

Benchmarks spec sections 1.7 (LCP of the linearised problem) and 1.8 (force-driven tools).

The problem. At a Newton iterate the bulk operators, condensed on the ``n_c`` candidate nodes and
rotated into their local (n, t) frames, give

    K* du_c = r* + p,        du_c, p: (2 n_c,), per candidate (normal, tangential)

with ``p = (R_N, R_T)`` the contact forces on the sheet (N/mm) and ``du_c`` the displacement
increments (mm). The linearised kinematics are ``g_N = g_N^i + du_N`` and ``s = s^i + du_T``
(gap and step slip, mm). The contact law is Signorini and 2D Coulomb (spec 1.4):

    g_N >= 0,  R_N >= 0,  g_N R_N = 0,
    |R_T| <= mu R_N,   |R_T| < mu R_N => s = 0,   s != 0 => R_T = -mu R_N sign(s).

:func:`contact_lcp` writes it as an LCP, :func:`lemke_contact_callback` solves that by
:func:`jaxfric.contact.lemke.lemke` on the host (``lcp_lemke``), and :func:`jaxfric.contact.alart_curnier.polish`
refines the answer on its own linear piece.

What is unique. For two solutions, ``du . K* du = sum dg dR_N + ds dR_T <= mu sum |dR_N| |ds|``
(differences marked d). So for K* positive definite (not necessarily symmetric) and mu small
against the normal-tangential coupling of K*, ``du_c``, ``p`` and the tool increments ``dq`` are
unique; for large mu they need not be (Klarbring 1990): on a clamped strip with mu = 0.99 Lemke
and semismooth Newton return different valid solutions. The LCP multipliers are never unique: on an
open candidate R_N = 0 forces R_T = 0, so phi+ = phi- = 0 and only ``s = lambda- - lambda+`` is
fixed; on a closed frictionless candidate the same holds. Compare solutions through ``(du_c, p)``
(:func:`recover_solution`), never through ``z``.

Force-driven tools (spec 1.8). ``n_q`` tools whose positions q_k are unknown get one extra LCP row
and column each; see :class:`ForceDrive` for the equations.

Units: lengths mm, forces N/mm (per unit width), stiffness N/mm per mm.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..numerics._checks import is_concrete
from .lemke import lemke
from .status import OPEN, STICK, contact_status

__all__ = [
    "DEFAULT_SHIFT",
    "ForceDrive",
    "contact_lcp",
    "coupling_matrix",
    "interleave",
    "lemke_contact_callback",
    "lemke_start",
    "recover_solution",
]

DEFAULT_SHIFT = 1e3    # mm: alpha of spec 1.8, larger than any tool increment |dq|


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
        shift: alpha, mm. The LCP of :func:`contact_lcp` pairs the tool row with ``z_q = dq + alpha``,
            which must stay > 0 so that complementarity forces the equality ``r_q = 0``; alpha must
            exceed any |dq| (default 1e3 mm, spec 1.8). :func:`lemke_contact_callback` takes the shift
            out again and eliminates the tool rows.
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


def coupling_matrix(drive: ForceDrive | None, n_c: int, dtype):
    """(C, P): the coupling matrix (2 n_c, n_q) and forces (n_q,); empty when no tool is force-driven."""
    if drive is None:
        return jnp.zeros((2 * n_c, 0), dtype), jnp.zeros((0,), dtype)
    if drive.coupling.shape[0] != 2 * n_c:
        raise ValueError(f"ForceDrive.coupling has {drive.coupling.shape[0]} rows, expected 2 n_c = {2 * n_c}")
    return jnp.asarray(drive.coupling, dtype), jnp.asarray(drive.force, dtype)


def interleave(normal: jax.Array, tangential: jax.Array) -> jax.Array:
    """(n_c,), (n_c,) -> (2 n_c,) in K* order (normal, tangential per candidate)."""
    return jnp.stack([normal, tangential], axis=-1).reshape(-1)


def _check_shapes(K_star, r_star, gap, slip, mu):
    """n_c, after checking the shapes of the arrays against it and that mu >= 0 where it is concrete."""
    n_c = jnp.shape(gap)[0]
    want = {"K_star": (2 * n_c, 2 * n_c), "r_star": (2 * n_c,), "slip": (n_c,), "mu": (n_c,)}
    got = {"K_star": jnp.shape(K_star), "r_star": jnp.shape(r_star), "slip": jnp.shape(slip), "mu": jnp.shape(mu)}
    for name, shape in want.items():
        if got[name] != shape:
            raise ValueError(f"'{name}' must have shape {shape} for n_c = {n_c} candidates, got {got[name]}")
    if is_concrete(mu) and np.any(np.asarray(mu) < 0):
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
    C, P = coupling_matrix(drive, n_c, dtype)
    A = _facet_matrix(jnp.asarray(mu, dtype))                         # (n_c, 3, 2)
    B = jnp.asarray(_B, dtype)
    d0 = -interleave(jnp.asarray(gap, dtype), jnp.asarray(slip, dtype))
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


def recover_solution(K_star, r_star, gap, slip, z_c, dq, C):
    """Displacements and forces from the candidates' part of an LCP solution (spec 1.7 step 6), the
    unique parts of the solution: ``du_c = B z_c + d0 + C dq``, ``p = K* du_c - r*``.

    Args:
        K_star, r_star, gap, slip: as for :func:`contact_lcp`.
        z_c: (3 n_c,) the LCP solution without the tool rows.
        dq: (n_q,) tool increments, mm; C: (2 n_c, n_q) their coupling (:func:`coupling_matrix`).

    Returns:
        (du_c, p): (2 n_c,) displacement increments (mm) and contact forces (R_N, R_T) on the sheet
        (N/mm).
    """
    dtype = K_star.dtype
    du = jnp.einsum("ab,ib->ia", jnp.asarray(_B, dtype), z_c.reshape(-1, 3)).reshape(-1)
    du = du - interleave(jnp.asarray(gap, dtype), jnp.asarray(slip, dtype)) + C @ dq
    return du, K_star @ du - jnp.asarray(r_star, dtype)


def lemke_start(p, slip, mu) -> jax.Array:
    """A complementary basis guessed from contact forces ``p`` (2 n_c,), e.g. those of the previous
    Newton iterate, for :func:`jaxfric.contact.lemke.lemke`'s warm start: (3 n_c,) bools, True where z is basic.

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
    """Solve the linearised contact problem by Lemke (``lcp_lemke`` of spec 1.7) from inside ``jit``: the
    LCP of :func:`contact_lcp` is built and the solution recovered (:func:`recover_solution`) in JAX, the
    pivoting (:func:`jaxfric.contact.lemke.lemke`) runs on the host through ``jax.pure_callback`` (``vmap`` runs
    it once per batch element). Arguments as for :func:`contact_lcp`; the default pivot budget is
    50 (3 n_c). Not differentiable.

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

    ``start``: optional (3 n_c,) bools, the starting basis of Lemke's pivoting (see :func:`lemke_start`).

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
    C, _ = coupling_matrix(drive, jnp.shape(gap)[0], K.dtype)
    du_c, p = recover_solution(K, r_star, gap, slip, z_c, dq, C)
    return du_c, p, dq, pivots, status
