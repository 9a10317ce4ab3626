"""Exact contact, one iteration by semismooth Newton on the whole step (solver "ssn", algorithm
``lcp_ssn``): the Alart-Curnier equations of every candidate written on the block-tridiagonal system, and
the merit of the line search (:mod:`jaxfric.contact.exact`)."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from ..fem.assembly import shared_trace
from ..numerics.linalg import BlockTridiag, Bordered, block_tridiag_solve, bordered_solve
from .alart_curnier import (
    OPEN,
    SLIP_NEG,
    SLIP_POS,
    STICK,
    alart_curnier_residual,
    keep_tools_touching,
    piece_jacobian,
)
from .exact_iterate import (
    GAP_FAR,
    KAPPA,
    Iterate,
    band_normals,
    pair_forces,
    pair_tools,
    proximity_band,
    tangents,
)
from .rigid import has_friction_law, pair_friction, pair_mu, pair_nodes, pair_speeds
from .system import _constrain_rows

# Active sets kept to recognise a cycle of the passes: at most ``ssn_max_iter`` of them, every set of the
# linearised problem, so that every cycle that repeats within its passes is seen.
CYCLE_WINDOW = 64

__all__ = ["active_set_step", "contact_frames", "frames_at_forces", "semismooth_merit", "Frames", "PieceData",
           "piece_data", "classify", "piece_system", "Compliance", "compliance_of"]


# ---- semismooth Newton inside the global Newton loop (solver "ssn") --------------------------------

def _pair_local(it: Iterate, f_pairs):
    """Per pair ``(n . f, t . f, gap, slip)`` with the node force ``f`` (m, 2) held fixed: the values
    (m, 4) and the derivatives d/du (m, 4, 2) and d/dq (m, 4) with respect to the pair's node
    displacement and its tool's position (zero where a pair projects on no primitive)."""
    n, f = it.normal, f_pairs
    d_n = it.jac[:, :2, :]                                       # (m, 2, 3)
    d_nf = jnp.einsum("mi,mij->mj", f, d_n)
    d_tf = -f[:, :1] * d_n[:, 1, :] + f[:, 1:] * d_n[:, 0, :]    # t = (-n_y, n_x)
    values = jnp.stack([jnp.sum(n * f, -1), jnp.sum(tangents(n) * f, -1), it.gap, it.slip], -1)
    d = jnp.stack([d_nf, d_tf, it.jac[:, 2, :], it.jac[:, 3, :]], 1)   # (m, 4, 3)
    return values, d[:, :, :2], d[:, :, 2]


def _row_transform(K: BlockTridiag, T: jax.Array) -> BlockTridiag:
    """Rows of K combined node by node: the two rows of node a become ``T_a @ rows_a``; T (n_nodes, 2, 2)."""
    nb, m = K.diag.shape[0], K.diag.shape[1]
    Tb = T.reshape(nb, m // 2, 2, 2)

    def apply(blocks, Tsel):
        b = blocks.reshape(blocks.shape[0], m // 2, 2, m)
        return jnp.einsum("bnij,bnjk->bnik", Tsel, b).reshape(blocks.shape)

    return BlockTridiag(lower=apply(K.lower, Tb[1:]), diag=apply(K.diag, Tb), upper=apply(K.upper, Tb[:-1]))


class Frames(NamedTuple):
    """The candidate nodes of the in-loop solver at one iterate, each with its nearest pair."""

    nodes: jax.Array     # (n_u,) every candidate node
    pairs: jax.Array     # (n_u,) its pair of smallest gap
    valid: jax.Array     # (n_u,) the pair projects on its tool
    normal: jax.Array    # (n_u, 2)
    rotation: jax.Array  # (n_u, 2, 2) columns n, t
    mu: jax.Array        # (n_u,)
    c_n: jax.Array       # (n_u,) Alart-Curnier constants
    c_t: jax.Array
    kappa: jax.Array     # (n_dofs,) the rows of prescribed dofs (module docstring, step 1)


@shared_trace
def contact_frames(it: Iterate, args) -> tuple[Frames, BlockTridiag]:
    """The frames and constants at the iterate, and the tangent with kappa rows on prescribed dofs."""
    c = args.contact
    assert it.K is not None   # a linearised iterate
    band = proximity_band(it, c.tools, None)
    nodes, pairs = band.nodes, band.pairs
    valid, normal = band_normals(it, band)
    rotation = jnp.stack([normal, tangents(normal)], axis=-1)
    kappa = KAPPA * jnp.abs(jax.vmap(jnp.diagonal)(it.K.diag).reshape(-1))
    # Alart-Curnier constants: a hundredth of the node's own stiffness in its frame, the order of the
    # condensed stiffness of a thin sheet's node (the sheet around it is far softer than K_aa alone).
    # Iterations whose active set cycled, three-cylinder bench with 0.6 mm of drawing and no fallback:
    # K_aa 62 of 280, K_aa / 10 14 of 227, K_aa / 100 6 of 224, K_aa / 1000 11 of 248.
    K = _constrain_rows(it.K, args.mask, kappa)
    nb, bs = K.diag.shape[0], K.diag.shape[1]
    ny1 = bs // 2
    K_aa = K.diag.reshape(nb, ny1, 2, ny1, 2)[nodes // ny1, nodes % ny1, :, nodes % ny1, :]   # (n_u, 2, 2)
    K_loc = jnp.einsum("uia,uij,ujb->uab", rotation, K_aa, rotation)
    mu = jnp.where(valid, pair_mu(c.tools, c.mu)[pairs], 0.0)
    return Frames(nodes, pairs, valid, normal, rotation, mu, 0.01 * jnp.abs(K_loc[:, 0, 0]),
                   0.01 * jnp.abs(K_loc[:, 1, 1]), kappa), K


def frames_at_forces(fr: Frames, args, p) -> Frames:
    """``fr`` with the friction coefficients a tool's friction law gives at the pair forces ``p`` (m, 2)
    and the last step's speeds (:mod:`jaxfric.contact.friction`; Coulomb tools keep theirs)."""
    c = args.contact
    if not has_friction_law(c.tools):   # static
        return fr
    mu = pair_friction(c.tools, c.mu, args.mesh.nodes, p[:, 0], pair_speeds(c))
    return fr._replace(mu=jnp.where(fr.valid, mu[fr.pairs], 0.0))


class Compliance(NamedTuple):
    """The penalty law's compliance written into the Alart-Curnier equations (a compliant
    :class:`~jaxfric.contact.formulations.Complementarity`). The penalty law (:mod:`jaxfric.contact.laws`,
    lambda_N = 0) is the Signorini-Coulomb law of the compliant gap and slip

        g~ = g_N + R_N / eps_N,        s~ = s + (R_T - R_T,n) / eps_T:

    R_N = eps_N <-g_N> is R_N >= 0, g~ >= 0, R_N g~ = 0; the stick predictor R_T = R_T,n - eps_T s is
    s~ = 0 inside the Coulomb cone, and on its boundary s~ is opposite to R_T as Coulomb's slip is. So the
    semismooth Newton pass, with (g~, s~) in place of (g_N, s), solves the penalty law's step (exactly the
    unsmoothed law's)."""

    inv_eps_n: jax.Array   # () 1 / eps_N (mm per N/mm)
    inv_eps_t: jax.Array   # () 1 / eps_T (0 where eps_T = 0: no tangential compliance)
    lam_t: jax.Array       # (m,) R_T,n per pair: the last converged tangential forces


def compliance_of(args) -> Compliance:
    """The compliance of the penalty law of ``args`` (its ``contact.law``: the penalties of the step, softened
    where a continuation stage softens them)."""
    law = args.contact.law
    eps_t = jnp.asarray(law.eps_t)
    return Compliance(1.0 / law.eps_n, jnp.where(eps_t > 0.0, 1.0 / jnp.where(eps_t > 0.0, eps_t, 1.0), 0.0),
                      jnp.concatenate(args.contact.lam_t))


def compliant(cp: Compliance | None, pairs, mu, R_N, R_T, g, s):
    """The gap and slip the Alart-Curnier equations take for candidates with forces (R_N, R_T), gaps g and
    slips s, each (n_u,), whose pairs are ``pairs``: (g, s) themselves without compliance, (g~, s~) of
    :class:`Compliance` with it (s~ = 0 where mu = 0, as the frictionless candidates' slip)."""
    if cp is None:
        return g, s
    return g + cp.inv_eps_n * R_N, jnp.where(mu > 0, s + cp.inv_eps_t * (R_T - cp.lam_t[pairs]), 0.0)


def compliant_frames(fr: Frames, cp: Compliance | None) -> Frames:
    """``fr`` with Alart-Curnier constants for the compliant equations: c eps / (c + eps) in place of each c
    (``fr`` itself without compliance). The solution does not depend on them; the classification does:
    sigma_N = R_N - c (g_N + R_N / eps_N) weighs the force by 1 - c / eps_N, which this choice keeps
    positive (c << eps_N: exact contact's constant; c >> eps_N: about eps_N, where sigma_N is the penalty
    law's own trial force -eps_N g_N). With c above eps_N the classification of a pair's predicted force
    turns over, and on thin sheets, whose nodes are far stiffer in their frame than the penalty, the solve
    did not converge."""
    if cp is None:
        return fr
    harmonic = lambda c, inv_eps: c / (1.0 + c * inv_eps)  # noqa: E731
    return fr._replace(c_n=harmonic(fr.c_n, cp.inv_eps_n), c_t=harmonic(fr.c_t, cp.inv_eps_t))


def equilibrium_force(it: Iterate, args, x, hint, kappa) -> jax.Array:
    """f~ (n_dofs,): the internal force on free dofs, ``f_c^prev + kappa (u - u_presc)`` on prescribed
    ones, with f_c^prev the pair forces ``hint`` (m, 2)."""
    n = args.mesh.n_dofs
    f_c_prev = jnp.zeros_like(it.f_int).at[pair_nodes(args.contact.tools)].add(pair_forces(it, hint))
    return jnp.where(args.mask, f_c_prev.reshape(-1) + kappa * (x[:n] - args.values), it.f_int.reshape(-1))


def driven_rows(args, fr: Frames, x, f_tilde, n):
    """The force-driven tool's pairs among ``fr``, its drive vector on the dofs and its row residual
    (the force balance, or the prescribed position in a phase where the tool is held)."""
    c = args.contact
    k = args.force_idx[0]
    e = c.tools[k].drive
    mine = (jnp.asarray(pair_tools(c.tools))[fr.pairs] == k) & fr.valid
    dofs = (2 * fr.nodes[:, None] + jnp.arange(2)[None, :]).reshape(-1)
    v = jnp.zeros(n).at[dofs].set(jnp.where(mine[:, None], e[None, :], 0.0).reshape(-1))
    r_q = jnp.where(c.force_mask[k], v @ f_tilde - c.force[k], x[n] - c.q_presc[k])
    return mine, dofs, v, r_q


def semismooth_merit(x, it: Iterate, args, hint, fr: Frames, compliance: Compliance | None = None) -> jax.Array:
    """Squared norm of the semismooth residual the in-loop solver drives to zero: f~ on the sheet's
    dofs with every candidate node's two rows replaced by its Alart-Curnier residual (C_N, C_T; of the
    compliant gap and slip with a ``compliance``), and the tool's row. The constants and kappa of ``fr`` (the
    iterate the search started from) are kept, so that trial points are compared on one function."""
    n = args.mesh.n_dofs
    f_tilde = equilibrium_force(it, args, x, hint, fr.kappa)
    f_nodes = f_tilde.reshape(-1, 2)
    band = proximity_band(it, args.contact.tools, None)      # the nearest pair may differ from fr's
    valid, normal = band_normals(it, band)
    R_N = jnp.einsum("ui,ui->u", normal, f_nodes[band.nodes])
    R_T = jnp.einsum("ui,ui->u", tangents(normal), f_nodes[band.nodes])
    gap = jnp.where(valid, it.gap[band.pairs], GAP_FAR)
    slip = jnp.where(valid & (fr.mu > 0), it.slip[band.pairs], 0.0)
    gap, slip = compliant(compliance, band.pairs, fr.mu, R_N, R_T, gap, slip)
    fr = compliant_frames(fr, compliance)
    _, C, _ = alart_curnier_residual(R_N, R_T, gap, slip, fr.mu, fr.c_n, fr.c_t)
    total = jnp.sum(f_nodes.at[band.nodes].set(C) ** 2)
    if args.force_idx:
        now = fr._replace(pairs=band.pairs, valid=valid)
        total = total + driven_rows(args, now, x, f_tilde, n)[3] ** 2
    return total


class PieceData(NamedTuple):
    """What the semismooth system of an iterate is built from, before an active set is chosen
    (:func:`piece_data`): per candidate node (``frames`` order) its contact force from equilibrium
    in its pair's frame, gap and slip, and their derivatives."""

    fr: Frames
    K: BlockTridiag          # the tangent with kappa rows on prescribed dofs
    f_tilde: jax.Array       # (n_dofs,) :func:`equilibrium_force`
    vals: jax.Array          # (m, 4) per pair (n . f, t . f, gap, slip); GAP_FAR where it projects on nothing
    d_u: jax.Array           # (m, 4, 2) their derivatives in the pair's node displacement
    d_q: jax.Array           # (m, 4) and in its tool's position
    R_N: jax.Array           # (n_u,) per candidate node
    R_T: jax.Array
    gap: jax.Array
    slip: jax.Array
    driven: Any              # (mine, dofs, v, r_q, e_dot_n, C_row) of the force-driven tool, or None
    compliance: Compliance | None = None   # the penalty law's (a compliant solve), or None: exact contact


def piece_data(it: Iterate, args, x, hint, frames=None, compliance: Compliance | None = None) -> PieceData:
    """:class:`PieceData` at the iterate ``it`` (at x), with ``hint`` (m, 2) the contact forces of the
    prescribed dofs' rows (:func:`equilibrium_force`); ``frames``: :func:`contact_frames` at ``it`` when the
    caller has it already, with a friction law's coefficients at ``hint`` (:func:`frames_at_forces`).
    ``gap`` and ``slip`` are the geometric ones; ``compliance`` makes the equations the penalty law's."""
    c = args.contact
    n = args.mesh.n_dofs
    if frames is None:
        fr, K = contact_frames(it, args)
        # A friction law's coefficients are those of the forces the last direction predicted (``hint``);
        # a caller that passes ``frames`` has set them (:func:`frames_at_forces`).
        fr = frames_at_forces(fr, args, hint)
    else:
        fr, K = frames
    fr = compliant_frames(fr, compliance)
    nodes, pairs, valid = fr.nodes, fr.pairs, fr.valid
    f_tilde = equilibrium_force(it, args, x, hint, fr.kappa)
    f_nodes = f_tilde.reshape(-1, 2)
    vals, d_u, d_q = _pair_local(it, f_nodes[pair_nodes(c.tools)])
    valid_all = it.valid[:, None]
    vals = jnp.where(valid_all, vals, jnp.array([0.0, 0.0, GAP_FAR, 0.0]))
    d_u = jnp.where(valid_all[..., None], d_u, 0.0)
    d_q = jnp.where(valid_all, d_q, 0.0)
    R_N = jnp.where(valid, vals[pairs, 0], f_nodes[nodes] @ jnp.array([0.0, 1.0]))
    R_T = jnp.where(valid, vals[pairs, 1], f_nodes[nodes] @ jnp.array([-1.0, 0.0]))
    gap, slip = vals[pairs, 2], jnp.where(fr.mu > 0, vals[pairs, 3], 0.0)
    if len(args.force_idx) > 1:
        raise NotImplementedError("exact contact supports at most one force-driven tool per scene")
    driven = None
    if args.force_idx:
        mine, dofs, v, r_q = driven_rows(args, fr, x, f_tilde, n)
        e_dot_n = jnp.where(mine, fr.normal @ c.tools[args.force_idx[0]].drive, 0.0)[:, None]
        C_row = jnp.where(c.force_mask[args.force_idx[0]], K.transpose().matvec(v), 0.0)
        driven = (mine, dofs, v, r_q, e_dot_n, C_row)
    return PieceData(fr, K, f_tilde, vals, d_u, d_q, R_N, R_T, gap, slip, driven, compliance)


def classify(d: PieceData, args, R_N, R_T, g, s) -> jax.Array:
    """The active set (open / stick / slip with its sign) of forces (R_N, R_T), gaps and slips of the
    candidate nodes (the compliant ones of ``d.compliance``); a force-driven tool keeps touching the sheet
    (:func:`keep_tools_touching`)."""
    fr = d.fr
    g, s = compliant(d.compliance, fr.pairs, fr.mu, R_N, R_T, g, s)
    state, _, sig_n = alart_curnier_residual(R_N, R_T, g, s, fr.mu, fr.c_n, fr.c_t)
    if d.driven is not None:
        force_driven = args.contact.force_mask[args.force_idx[0]]
        state = jnp.where(force_driven, keep_tools_touching(state, sig_n, d.driven[4]), state)
    return state


def piece_system(d: PieceData, args, state, constrained=None, x=None, mu_force=None):
    """The semismooth system on the active set ``state``: its matrix (BlockTridiag, Bordered with a
    force-driven tool) and its residual F (the equilibrium rows with each candidate node's two rows
    replaced by C_a = W_F (n, t)^T f~_a + W_K (g, s), then the tool's row), so that the increment solves
    ``M dx = -F``. ``constrained`` (n_u,) bool, with the iterate ``x``: candidates whose second row (the slip law) is
    replaced by the row of their one prescribed dof, kappa (u_i - u_presc,i)
    (:mod:`jaxfric.contact.exact_derivative`). ``mu_force`` (n_u,): the matrix's slip rows take it as the
    coefficient of R_N (:func:`~jaxfric.contact.alart_curnier.piece_jacobian`; the residual keeps mu).
    With ``d.compliance``, C_a = W_F p_a + W_K (g~, s~) (:class:`Compliance`), whose matrix takes
    W_F + W_K diag(1 / eps_N, 1 / eps_T) where exact contact's takes W_F."""
    c = args.contact
    fr, K = d.fr, d.K
    n = args.mesh.n_dofs
    nodes, pairs, rotation = fr.nodes, fr.pairs, fr.rotation
    nb, bs = K.diag.shape[0], K.diag.shape[1]
    ny1 = bs // 2
    col, loc = nodes // ny1, nodes % ny1
    w_f, w_k = piece_jacobian(state, fr.mu, fr.c_n, fr.c_t)
    g, s = compliant(d.compliance, pairs, fr.mu, d.R_N, d.R_T, d.gap, d.slip)
    C_rows = jnp.einsum("uij,uj->ui", w_f, jnp.stack([d.R_N, d.R_T], -1)) + \
        jnp.einsum("uij,uj->ui", w_k, jnp.stack([g, s], -1))
    if mu_force is not None:
        w_f = piece_jacobian(state, fr.mu, fr.c_n, fr.c_t, mu_force)[0]
    if d.compliance is not None:
        cp = d.compliance
        w_f = w_f + w_k * jnp.stack([jnp.broadcast_to(cp.inv_eps_n, fr.mu.shape),
                                     jnp.where(fr.mu > 0, cp.inv_eps_t, 0.0)], -1)[:, None, :]
    A = jnp.einsum("uij,ukj->uik", w_f, rotation)                    # W_F R^T
    local = jnp.einsum("uij,ujk->uik", w_f, d.d_u[pairs, :2]) + jnp.einsum("uij,ujk->uik", w_k, d.d_u[pairs, 2:])
    if constrained is not None:
        e = args.mask[:n].reshape(-1, 2)[nodes].astype(A.dtype)          # the prescribed dof of each node
        A = A.at[:, 1, :].set(jnp.where(constrained[:, None], e, A[:, 1, :]))
        local = local.at[:, 1, :].set(jnp.where(constrained[:, None], 0.0, local[:, 1, :]))
        row = fr.kappa * (x[:n] - args.values)
        C_rows = C_rows.at[:, 1].set(jnp.where(constrained, jnp.sum(e * row.reshape(-1, 2)[nodes], -1),
                                               C_rows[:, 1]))
    T = jnp.broadcast_to(jnp.eye(2), (n // 2, 2, 2)).at[nodes].set(A)
    J = _row_transform(K, T)
    Jd = J.diag.reshape(nb, ny1, 2, ny1, 2).at[col, loc, :, loc, :].add(local)
    J = BlockTridiag(J.lower, Jd.reshape(nb, bs, bs), J.upper)
    F = d.f_tilde.reshape(-1, 2).at[nodes].set(C_rows).reshape(-1)
    if d.driven is None:
        return J, F
    mine, dofs, _, r_q, _, C_row = d.driven
    force_driven = c.force_mask[args.force_idx[0]]
    b_col = jnp.einsum("uij,uj->ui", w_f, d.d_q[pairs, :2]) + jnp.einsum("uij,uj->ui", w_k, d.d_q[pairs, 2:])
    B = jnp.zeros(n).at[dofs].set(jnp.where(mine[:, None], b_col, 0.0).reshape(-1))
    B = jnp.where(force_driven, B, 0.0)
    M = Bordered(A=J, B=B[:, None], C=C_row[None, :], D=jnp.where(force_driven, 0.0, 1.0).reshape(1, 1))
    return M, jnp.concatenate([F, r_q[None]])


def active_set_step(it: Iterate, args, x, p_prev, law, hint, frames=None):
    """One iteration of semismooth Newton on the whole step (solver ``"ssn"``): the increment (du, dq),
    the pair forces it predicts (m, 2), the pairs used, the solver stats; same contract as
    :func:`contact_newton_step`, at the cost of one bulk solve.

    The Alart-Curnier equations of :mod:`jaxfric.contact.alart_curnier` are written for every candidate node (with its
    nearest pair) with the contact force taken from equilibrium, p_a = (n, t)^T f~_a, where f~ is the
    internal force on free dofs and ``f_c^prev + kappa (u - u_presc)`` on prescribed ones (the kappa rows
    of the module docstring, step 1). On the active set read off the iterate, the node's two equilibrium
    rows are replaced by C_a = W_F p_a + W_K (g_N, s) (open: p = 0; stick: g = s = 0; slip: g = 0 and
    R_T = mu xi R_N): a row combination of the bulk tangent plus a 2 x 2 block of the node's own
    kinematics, so the matrix keeps its block-tridiagonal structure and each active-set pass costs one
    block-Thomas solve, like a penalty iteration (:func:`piece_system`). The force-driven tool's row is
    sum_a e_q . f~_a = P over its candidates. ``hint`` gives f_c^prev and the first active set (the last
    converged forces at a step's first iteration); ``p_prev`` is not used (the signature is the condensed
    step's). ``frames``: the result of :func:`contact_frames` at ``it`` when the caller has it already.
    A compliant ``law`` solves the penalty law of ``args`` instead (:class:`Compliance`).
    """
    n = args.mesh.n_dofs
    m = it.gap.shape[0]
    d = piece_data(it, args, x, hint, frames, compliance_of(args) if law.compliant else None)
    fr, K = d.fr, d.K
    nodes, pairs, valid, rotation, mu = fr.nodes, fr.pairs, fr.valid, fr.rotation, fr.mu
    # The gap at this iterate (the compliant one with the penalty's compliance: a closed pair's penetration
    # R_N / eps_N is its contact, not an overlap).
    gap = compliant(d.compliance, pairs, mu, d.R_N, d.R_T, d.gap, d.slip)[0]

    def solve(state):
        """The increment on the active set ``state``, and the forces, gap and slip it predicts."""
        M, F = piece_system(d, args, state)
        if d.driven is None:
            du = block_tridiag_solve(M, -F)
            dx, dq_pairs = du, jnp.zeros(nodes.shape[0])
        else:
            dx = bordered_solve(M, -F)
            du, dq_pairs = dx[:n], jnp.where(d.driven[0], dx[n], 0.0)
        du_a = du.reshape(-1, 2)[nodes]
        df = K.matvec(du).reshape(-1, 2)[nodes]
        linear = (d.vals[pairs] + jnp.einsum("uij,uj->ui", d.d_u[pairs], du_a) + d.d_q[pairs] * dq_pairs[:, None])
        # Forces: the node force f~ in the frame, both moved along the increment.
        p_lin = linear[:, :2] + jnp.einsum("uji,uj->ui", rotation, df)
        p_lin = jnp.where(valid[:, None], p_lin, 0.0)
        return dx, p_lin, linear[:, 2], linear[:, 3]

    # Semismooth Newton on the linearised problem: the active set is read off the forces and gaps the
    # last solve predicts until it repeats (each pass one block-Thomas solve; the bulk is not
    # re-linearised), as the condensed solvers solve the linearised contact problem exactly.
    # The first active set from the forces of ``hint`` (the last iterate's prediction, or the last
    # converged step's) with this iterate's gaps: on the three-cylinder bench 18.6 passes per step
    # against 25.8 when read off this iterate's own (unbalanced) forces.
    h = jnp.where(valid[:, None], hint[pairs], 0.0)
    state0 = classify(d, args, h[:, 0], h[:, 1], d.gap, d.slip)

    # One solve in the traced program (its first pass takes state0): each copy of the block solve
    # costs compile time.
    def next_state(state, p_l, g_l, s_l):
        """The active set read off the last solve's prediction. A node that penetrates at this iterate
        and whose sticking piece predicts a tensile force slips first (along the predicted tangential
        force) instead of opening: opened, it keeps penetrating and closes again, and stick <-> open
        cycles without end (Nine 60 x 2 at half the nominal increments, B's first touch: R_N = -1.5e-4
        N/mm closed, a penetration of 2.7e-5 mm open, every outer iteration of every cut step)."""
        new = classify(d, args, p_l[:, 0], p_l[:, 1], g_l, s_l)
        slip = jnp.where(p_l[:, 1] >= 0.0, SLIP_POS, SLIP_NEG)
        return jnp.where((state == STICK) & (new == OPEN) & (gap < 0.0) & (mu > 0.0), slip, new)

    # A cycle: the next set is one that a pass of the window (the last CYCLE_WINDOW sets) solved. The
    # passes are a function of the set alone, so from there they repeat with the cycle's period, and the
    # set that pass ssn_max_iter - 1 would solve is known: the loop solves it and stops, with the
    # increment of ssn_max_iter passes in fewer (module docstring). ``iters`` counts the passes made.
    n_max = law.ssn_max_iter
    window_len = min(CYCLE_WINDOW, n_max)

    def more(carry):
        i, state, _, p_l, g_l, s_l, _, _, last = carry
        return (i == 0) | (~last & (i < n_max) & jnp.any(next_state(state, p_l, g_l, s_l) != state))

    def again(carry):
        i, state, _, p_l, g_l, s_l, seen, seen_at, _ = carry
        new = jnp.where(i == 0, state0, next_state(state, p_l, g_l, s_l))
        match = jnp.all(seen == new, axis=1) & (seen_at >= 0)
        cycle = jnp.any(match)
        j = jnp.max(jnp.where(match, seen_at, -1))           # the pass that solved ``new`` before
        last_pass = j + (n_max - 1 - j) % jnp.maximum(i - j, 1)
        state = jnp.where(cycle, seen[last_pass % window_len], new)
        # (after a cycle's pass the loop stops: what this pass writes to the window is not read)
        seen, seen_at = seen.at[i % window_len].set(state), seen_at.at[i % window_len].set(i)
        return (i + 1, state) + solve(state) + (seen, seen_at, cycle)

    n_u = nodes.shape[0]
    start = (jnp.array(0, jnp.int32), state0, jnp.zeros(n + len(args.force_idx)), jnp.zeros((n_u, 2)),
             jnp.zeros(n_u), jnp.zeros(n_u), jnp.zeros((window_len, n_u), state0.dtype),
             jnp.full(window_len, -1, jnp.int32), jnp.array(False))
    iters, state, dx, p_new, g_l, s_l, _, _, _ = jax.lax.while_loop(more, again, start)
    settled = jnp.all(next_state(state, p_new, g_l, s_l) == state)
    p_new = jnp.where((state != 0)[:, None], p_new, 0.0)
    p = jnp.zeros((m, 2)).at[pairs].set(p_new)
    in_band = jnp.zeros(m, bool).at[pairs].set(True)
    # An active set that cycles: the last pass's increment is taken all the same (counted as a
    # fallback). The Newton loop goes on from there, and its convergence test still asks for settled
    # statuses, so no converged step rests on it.
    stats = jnp.stack([jnp.array(0, jnp.int32), iters, (~settled).astype(jnp.int32)])
    return dx, p, in_band, stats, jnp.all(jnp.isfinite(dx))
