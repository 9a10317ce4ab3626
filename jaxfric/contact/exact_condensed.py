"""Exact contact, one iteration on the condensed problem (solver "lemke", algorithm ``lcp_lemke``): the
proximity band, the condensation of the bulk stiffness on it, and Lemke's solution of the contact LCP
(:mod:`jaxfric.contact.exact`, steps 1 to 5)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..numerics.linalg import BlockTridiag, block_tridiag_solve
from .alart_curnier import (
    polish,
)
from .exact_iterate import (
    GAP_FAR,
    KAPPA,
    REFINE_ITER,
    Band,
    Iterate,
    band_normals,
    pair_forces,
    pair_tools,
    proximity_band,
    tangents,
)
from .lcp import ForceDrive, lemke_contact_callback, lemke_start
from .lemke import LemkeStatus
from .rigid import pair_friction, pair_nodes, pair_speeds
from .system import _constrain_rows

__all__ = ["contact_newton_step"]


# ---- condensation -----------------------------------------------------------------------------------

def _decoupled(J: BlockTridiag, band_mask, scale) -> BlockTridiag:
    """J with the rows and columns of the band dofs replaced by ``scale`` times the identity."""
    nb, m = J.diag.shape[0], J.diag.shape[1]
    keep = 1.0 - band_mask.reshape(nb, m)
    diag = J.diag * keep[:, :, None] * keep[:, None, :] + jax.vmap(jnp.diag)(scale * (1.0 - keep))
    lower = J.lower * keep[1:, :, None] * keep[:-1, None, :]
    upper = J.upper * keep[:-1, :, None] * keep[1:, None, :]
    return BlockTridiag(lower=lower, diag=diag, upper=upper)


class _Condensed(NamedTuple):
    K_star: jax.Array   # (2 n_c, 2 n_c) in the pairs' (n, t) frames
    r_star: jax.Array   # (2 n_c,)
    Y: jax.Array        # (n, 2 n_c + 1) = K_ff^-1 [K_fc | b_f] (zero rows at band dofs)
    dofs: jax.Array     # (2 n_c,) band dofs
    rotation: jax.Array  # (n_c, 2, 2) columns n, t per band node


def _condense(it: Iterate, args, x, band: Band, normal, f_c_prev) -> _Condensed:
    n = args.mesh.n_dofs
    K = it.K
    assert K is not None   # a linearised iterate
    diag = jnp.abs(jax.vmap(jnp.diagonal)(K.diag).reshape(-1))
    J = _constrain_rows(K, args.mask, KAPPA * diag)
    b = jnp.where(args.mask, KAPPA * diag * (args.values - x[:n]) - f_c_prev.reshape(-1), -it.f_int.reshape(-1))
    dofs = (2 * band.nodes[:, None] + jnp.arange(2)[None, :]).reshape(-1)
    n_c2 = dofs.shape[0]
    E = jnp.zeros((n, n_c2)).at[dofs, jnp.arange(n_c2)].set(1.0)
    band_mask = jnp.zeros(n).at[dofs].set(1.0)
    free = (1.0 - band_mask)[:, None]
    JE = J.matvec(E)
    rhs = jnp.concatenate([JE * free, (b[:, None] * free)], axis=1)
    scale = jnp.mean(jnp.where(args.mask, 0.0, diag)) + jnp.finfo(diag.dtype).tiny
    Y = block_tridiag_solve(_decoupled(J, band_mask, scale), rhs)
    JY = J.matvec(Y)[dofs]
    K_cart = JE[dofs] - JY[:, :n_c2]
    r_cart = b[dofs] - JY[:, n_c2]
    rotation = jnp.stack([normal, tangents(normal)], axis=-1)         # (n_c, 2, 2), columns n, t
    n_c = band.nodes.shape[0]
    # R^T K R and R^T r for the block-diagonal R of the 2 x 2 rotations, block by block: as dense
    # products they cost two (2 n_c)^3 matrix products, 4 GFLOP an iteration on the bead's band.
    K_loc = jnp.einsum("ica,icjd,jdb->iajb", rotation, K_cart.reshape(n_c, 2, n_c, 2), rotation)
    r_loc = jnp.einsum("ica,ic->ia", rotation, r_cart.reshape(n_c, 2))
    return _Condensed(K_loc.reshape(n_c2, n_c2), r_loc.reshape(n_c2), Y, dofs, rotation)


# ---- one Newton iteration ---------------------------------------------------------------------------

class LCPSolution(NamedTuple):
    du_c: jax.Array     # (2 n_c,) local frames
    p: jax.Array        # (2 n_c,)
    dq: jax.Array       # (n_q,)
    pivots: jax.Array
    ssn_iters: jax.Array
    fallback: jax.Array
    solved: jax.Array


def _lemke(K, r, gap, slip, mu, drive, hint) -> LCPSolution:
    """The condensed contact problem of one iteration by Lemke on the host, warm-started from the basis
    of the forces ``hint`` (the last iterate's), its active set then solved exactly
    (:func:`jaxfric.contact.alart_curnier.polish`; an answer on a piece boundary, or the last basis of a pivoting
    that ended on a ray, is settled by at most ``REFINE_ITER`` semismooth Newton iterations on the same
    problem, counted with the ``ssn_iters``). Solved: Lemke's answer passed its check, or the refined
    one is a solution on its own piece."""
    du_c, p, dq, pivots, status = lemke_contact_callback(K, r, gap, slip, mu, drive,
                                                         start=lemke_start(hint, slip, mu))
    du_c, p, dq, refined, solved = polish(K, r, gap, slip, mu, du_c, dq, drive, refine_iter=REFINE_ITER)
    return LCPSolution(du_c, p, dq, pivots, refined, jnp.array(0, jnp.int32),
                        (status == LemkeStatus.SOLVED) | solved)


def contact_newton_step(it: Iterate, args, x, p_prev, law, hint):
    """The increment (du, dq) of one iteration, the new pair forces (m, 2), the band, the solver stats.

    ``hint`` (m, 2): forces whose active set starts Lemke or semismooth Newton (the last iterate's,
    or at the first iteration the last converged step's)."""
    c = args.contact
    n = args.mesh.n_dofs
    band = proximity_band(it, c.tools, law.band)
    valid, normal = band_normals(it, band)
    gap = jnp.where(valid, it.gap[band.pairs], GAP_FAR)
    pair_tool = pair_tools(c.tools)
    # A friction law's coefficients are those of the forces the last direction predicted (``hint``).
    mu = jnp.where(valid, pair_friction(c.tools, c.mu, args.mesh.nodes, hint[:, 0], pair_speeds(c))[band.pairs], 0.0)
    slip = jnp.where(valid & (mu > 0), it.slip[band.pairs], 0.0)
    f_c_prev = jnp.zeros_like(it.f_int).at[pair_nodes(c.tools)].add(pair_forces(it, p_prev))
    cond = _condense(it, args, x, band, normal, f_c_prev)
    tangent = tangents(normal)

    def solve(driven: bool):
        drive = None
        if driven:
            k = args.force_idx[0]
            mine = (jnp.asarray(pair_tool)[band.pairs] == k) & valid
            e = c.tools[k].drive
            drive = ForceDrive.single(jnp.where(mine, normal @ e, 0.0), jnp.where(mine, tangent @ e, 0.0),
                                      c.force[k])
        sol = _lemke(cond.K_star, cond.r_star, gap, slip, mu, drive, jnp.where(valid[:, None], hint[band.pairs], 0.0))
        dq = sol.dq if driven else jnp.zeros(len(args.force_idx))
        return sol._replace(dq=dq)

    if not args.force_idx:
        sol = solve(False)
    elif len(args.force_idx) == 1:
        sol = jax.lax.cond(c.force_mask[args.force_idx[0]], lambda: solve(True), lambda: solve(False))
    else:
        raise NotImplementedError("exact contact supports at most one force-driven tool per scene")

    n_c = band.nodes.shape[0]
    du_c = jnp.einsum("iab,ib->ia", cond.rotation, sol.du_c.reshape(n_c, 2)).reshape(-1)
    du = cond.Y[:, -1] - cond.Y[:, :-1] @ du_c
    du = du.at[cond.dofs].set(du_c)
    m = it.gap.shape[0]
    p = jnp.zeros((m, 2)).at[band.pairs].set(jnp.where(valid[:, None], sol.p.reshape(n_c, 2), 0.0))
    in_band = jnp.zeros(m, bool).at[band.pairs].set(True)
    dq_f = []
    for j, k in enumerate(args.force_idx):
        # Displacement-driven in this phase: the unknown jumps to its prescribed value.
        dq_f.append(jnp.where(c.force_mask[k], sol.dq[j], c.q_presc[k] - x[n + j]))
    dx = jnp.concatenate([du] + ([jnp.stack(dq_f)] if dq_f else []))
    stats = jnp.stack([sol.pivots, sol.ssn_iters, sol.fallback]).astype(jnp.int32)
    return dx, p, in_band, stats, sol.solved
