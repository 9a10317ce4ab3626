"""Exact contact inside the global Newton loop (benchmarks spec 1.7 and 1.8): ``lcp_ssn``, ``lcp_lemke``.

At every Newton iterate x = (u, q_f) the contact conditions of the linearised problem are solved
exactly; the contact status comes out of that solve. Two ways:

* ``lcp_ssn`` (solver "ssn", :func:`active_set_step`): semismooth Newton on the Alart-Curnier
  equations of every candidate node, written on the block-tridiagonal system itself. The contact
  force of a node is its equilibrium force (internal force; kappa rows, step 1 below, on prescribed
  dofs), so on an active set the node's two rows become a row combination of the tangent plus a 2 x 2
  block of its own kinematics: one block-Thomas solve per active set, no condensation. The active set
  is re-read from the forces and gaps that solve predicts until it repeats (the linearised problem
  solved exactly). If it cycles for ``ssn_max_iter`` passes, the last pass's increment is taken
  (counted in ``ssn_fallbacks``) and the Newton loop goes on; a step converges only on an iteration
  whose active set settled. (Solving such iterates the condensed way instead was tried: on the
  three-cylinder bench it cost 7.8 s against 4.6 s, for 84 against 88 steps.) The Newton step is
  line-searched on the semismooth residual (:func:`semismooth_merit`: the equilibrium rows with each candidate's
  rows replaced by its Alart-Curnier residual), quartering a step that raises it, at most twice.
* ``lcp_lemke`` (solver "lemke"): the problem condensed on a band of candidates. Steps of one
  iteration:

1. Bulk operators of the sheet alone: K = d f_int / du and b = -f_int on the free dofs. A prescribed
   dof i gets the row ``kappa du_i = kappa (u_presc,i - u_i) + f_c,i - f_c,i^prev`` with
   kappa = 100 K_ii and f_c^prev the contact force of the previous iterate (the reaction's
   estimate). A candidate node with one prescribed component (the flat die's corner D) thus keeps
   its contact force in the condensed problem, as the LCP needs, while the prescribed value is met
   exactly once the forces settle (the error is the change of force over kappa). An identity row
   would drop the force from the LCP (R_T of a sticking D undetermined), and a huge kappa would cost
   Lemke its pivoting accuracy.
2. The proximity band: per candidate node the pair of smallest gap; of those, the ``band`` nodes
   nearest to a tool (all of them by default). Only the band enters the complementarity problem, so
   its size follows the contact zone. A node outside the band that penetrates a tool at the converged
   state fails the attempt (:attr:`~jaxfric.results.Result.CONTACT_BAND`).
3. Condensation on the band dofs c (spec 1.7 step 2), with the block-tridiagonal structure kept:
   ``K_ff^-1`` is the block-Thomas solve of K with the band dofs decoupled (their rows and columns
   replaced by a scaled identity), applied to the 2 n_c + 1 columns ``[K_fc | b_f]`` in one sweep:

       K* = K_cc - K_cf K_ff^-1 K_fc,     r* = b_c - K_cf K_ff^-1 b_f,

   then rotated into each band pair's (n, t) frame.
4. The linearised contact problem ``K* du_c = r* + p`` with ``g_N = g^i + du_N - (e_q . n) dq``,
   ``s = s^i + du_T - (e_q . t) dq`` and Signorini-Coulomb, plus the force balance of the force-driven
   tool (:mod:`jaxfric.contact_lcp`), by Lemke's pivoting (:mod:`jaxfric.lemke`, NumPy on the host
   through ``jax.pure_callback``), whose answer is solved again on its own piece and, where it lies on a
   piece boundary within its round-off, settled by a few semismooth Newton iterations on the same
   problem (:func:`jaxfric.alart_curnier.polish`).
5. Back-substitution ``du_f = K_ff^-1 (b_f - K_fc du_c)``; x <- x + (du, dq).

Convergence (spec 1.7 step 7): the bulk residual with the contact forces of the last solve,
``f_int - f_c(p)`` at the new iterate, passes the Newton test of :mod:`jaxfric.newton` (residual and
increment), and no pair changed its status (open / stick / slip from the forces, spec section 0).

Not differentiable: exact complementarity has no derivative where a pair changes status, and the
derivative of the converged step on a fixed status would need the active-set Jacobian. Gradients use
the penalty or augmented Lagrangian laws (with their optional smoothing); differentiating a run with
:class:`~jaxfric.contact.Complementarity` raises.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .alart_curnier import (
    OPEN,
    SLIP_NEG,
    SLIP_POS,
    STICK,
    alart_curnier_residual,
    keep_tools_touching,
    piece_jacobian,
    polish,
)
from .assembly import internal_force_and_tangent, shared_trace
from .contact import ContactStep, pair_mu, pair_nodes, split_pairs
from .contact_lcp import ForceDrive, lemke_contact_callback, lemke_start
from .lemke import LemkeStatus
from .linalg import BlockTridiag, Bordered, block_tridiag_solve, bordered_solve
from .newton import NewtonOptions, NewtonSolution
from .results import Result
from .status import contact_status
from .system import _constrain_rows
from .tools import project

# The pieces of one iteration are public for diagnostics (experiments/bench_contact.py,
# experiments/nine_newton_trace.py replay the loop on the host).
__all__ = ["exact_solve", "linearize_iterate", "iterate_residual", "pair_status", "contact_newton_step",
           "active_set_step", "contact_frames", "semismooth_merit"]

KAPPA = 1e2       # prescribed rows: kappa = KAPPA K_ii (see the module docstring)
REFINE_ITER = 10  # semismooth Newton iterations refining a Lemke answer on a piece boundary (polish)
GAP_FAR = 10.0    # mm: gap given to a band node that projects on no tool (it stays open)


class _Iterate(NamedTuple):
    """Bulk operators and pair geometry at one Newton iterate."""

    f_int: jax.Array      # (n_nodes, 2)
    K: BlockTridiag       # d f_int / du
    states: object
    det_min: jax.Array
    q: jax.Array          # (n_t,) tool positions
    gap: jax.Array        # (m,) GAP_OPEN where the pair projects on no primitive
    normal: jax.Array     # (m, 2)
    zeta: jax.Array       # (m,)
    slip: jax.Array       # (m,) slip since the start of the step
    valid: jax.Array      # (m,) bool
    jac: jax.Array        # (m, 4, 3) d(n_x, n_y, gap, slip) / d(u_a, q_k) of each pair (node, tool)


def _pair_tools(tools) -> np.ndarray:
    """Static: the index of each pair's tool (m,)."""
    return np.concatenate([np.full(len(t.candidates), k) for k, t in enumerate(tools)])


def _tool_positions(args, qf) -> jax.Array:
    """All tool positions: prescribed, or the unknown where the tool is force-driven in this phase."""
    c = args.contact
    if not args.force_idx:
        return c.q_presc
    idx = np.asarray(args.force_idx)
    return c.q_presc.at[idx].set(jnp.where(c.force_mask[idx], qf, c.q_presc[idx]))


def _geometry(step: ContactStep, nodes_ref, u, q):
    """Projection of every pair at (u, q): gap, normal, zeta, the slip since the step start, validity,
    and the derivatives of (normal, gap, slip) with respect to the pair's node displacement and its
    tool's position, all from one forward-mode pass per pair."""
    out, jac = [], []
    for k, tool in enumerate(step.tools):  # static: tools differ in structure
        idx = np.asarray(tool.candidates)

        def one(X, u_a, u_ref, tool=tool, k=k):
            def local(z):   # z = (u_a, q_k)
                increment = (z[:2] - u_ref) - (z[2] - step.q_ref[k]) * tool.drive
                pr = project(tool.geometry, X, step.q_ref[k] * tool.drive, displacement=u_ref,
                             increment=increment)
                return jnp.concatenate([pr.normal, pr.gap[None], pr.zeta_increment[None]]), pr

            return jax.jacfwd(local, has_aux=True)(jnp.concatenate([u_a, q[k][None]]))

        J, pr = jax.vmap(one)(nodes_ref[idx], u[idx], step.u_ref[k])
        out.append(pr)
        jac.append(J)
    cat = lambda name: jnp.concatenate([getattr(p, name) for p in out])  # noqa: E731
    return cat("gap"), cat("normal"), cat("zeta"), cat("zeta_increment"), cat("valid"), jnp.concatenate(jac)


@shared_trace     # the loop's shapes (filter_eval_shape before the loop) and its body: one trace
def linearize_iterate(x, args) -> _Iterate:
    n = args.mesh.n_dofs
    u = x[:n].reshape(-1, 2)
    q = _tool_positions(args, x[n:])
    a = internal_force_and_tangent(args.mesh, args.material, args.formulation, args.geo, u, args.states)
    assert a.tangent is not None
    gap, normal, zeta, slip, valid, jac = _geometry(args.contact, args.mesh.nodes, u, q)
    return _Iterate(a.f_int, a.tangent, a.states, a.det_min, q, gap, normal, zeta, slip, valid, jac)


def _tangents(normal):
    return jnp.stack([-normal[..., 1], normal[..., 0]], axis=-1)


def _pair_forces(it: _Iterate, p) -> jax.Array:
    """(m, 2) force on the sheet of every pair, R_N n + R_T t."""
    return p[:, :1] * it.normal + p[:, 1:] * _tangents(it.normal)


def iterate_residual(x, it: _Iterate, p, args):
    """Residual of the step at the iterate with contact forces p (m, 2); and the tool forces."""
    n = args.mesh.n_dofs
    c = args.contact
    f_pairs = _pair_forces(it, p)
    f_c = jnp.zeros_like(it.f_int).at[pair_nodes(c.tools)].add(f_pairs)
    R = jnp.where(args.mask, x[:n] - args.values, (it.f_int - f_c).reshape(-1))
    tool_f = jnp.stack([jnp.sum(f @ t.drive) for f, t in zip(split_pairs(c.tools, f_pairs), c.tools)])
    rows = [jnp.where(c.force_mask[k], tool_f[k] - c.force[k], x[n + j] - c.q_presc[k])
            for j, k in enumerate(args.force_idx)]
    if rows:
        R = jnp.concatenate([R, jnp.stack(rows)])
    return R, tool_f


# ---- the proximity band -----------------------------------------------------------------------------

class _Band(NamedTuple):
    nodes: jax.Array   # (n_c,) sheet nodes
    pairs: jax.Array   # (n_c,) the pair of each band node (index into the m pairs)


def _node_pairs(tools) -> tuple[np.ndarray, np.ndarray]:
    """Static: the distinct candidate nodes (n_u,) and their pairs (n_u, w), padded with m."""
    nodes = pair_nodes(tools)
    unique = np.unique(nodes)
    width = max(int(np.sum(nodes == a)) for a in unique)
    table = np.full((unique.size, width), nodes.size, dtype=np.int64)
    for i, a in enumerate(unique):
        mine = np.flatnonzero(nodes == a)
        table[i, : mine.size] = mine
    return unique, table


def _band(it: _Iterate, tools, size: int | None) -> _Band:
    unique, table = _node_pairs(tools)
    gap = jnp.concatenate([jnp.where(it.valid, it.gap, jnp.inf), jnp.array([jnp.inf])])
    g = gap[table]
    best = jnp.argmin(g, axis=1)
    pairs = jnp.asarray(table)[jnp.arange(unique.size), best]
    if size is None or size >= unique.size:
        return _Band(jnp.asarray(unique), pairs)
    _, sel = jax.lax.top_k(-jnp.min(g, axis=1), size)
    return _Band(jnp.asarray(unique)[sel], pairs[sel])


def _band_normals(it: _Iterate, band: _Band) -> tuple[jax.Array, jax.Array]:
    """Whether each band node's pair projects on its tool, and its normal ((0, 1) where it does not)."""
    valid = it.valid[band.pairs]
    return valid, jnp.where(valid[:, None], it.normal[band.pairs], jnp.array([0.0, 1.0]))


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


def _condense(it: _Iterate, args, x, band: _Band, normal, f_c_prev) -> _Condensed:
    n = args.mesh.n_dofs
    K = it.K
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
    rotation = jnp.stack([normal, _tangents(normal)], axis=-1)         # (n_c, 2, 2), columns n, t
    n_c = band.nodes.shape[0]
    # R^T K R and R^T r for the block-diagonal R of the 2 x 2 rotations, block by block: as dense
    # products they cost two (2 n_c)^3 matrix products, 4 GFLOP an iteration on the bead's band.
    K_loc = jnp.einsum("ica,icjd,jdb->iajb", rotation, K_cart.reshape(n_c, 2, n_c, 2), rotation)
    r_loc = jnp.einsum("ica,ic->ia", rotation, r_cart.reshape(n_c, 2))
    return _Condensed(K_loc.reshape(n_c2, n_c2), r_loc.reshape(n_c2), Y, dofs, rotation)


# ---- one Newton iteration ---------------------------------------------------------------------------

class _LCPSolution(NamedTuple):
    du_c: jax.Array     # (2 n_c,) local frames
    p: jax.Array        # (2 n_c,)
    dq: jax.Array       # (n_q,)
    pivots: jax.Array
    ssn_iters: jax.Array
    fallback: jax.Array
    solved: jax.Array


def _lemke(K, r, gap, slip, mu, drive, hint) -> _LCPSolution:
    """The condensed contact problem of one iteration by Lemke on the host, warm-started from the basis
    of the forces ``hint`` (the last iterate's), its active set then solved exactly
    (:func:`jaxfric.alart_curnier.polish`; an answer on a piece boundary, or the last basis of a pivoting
    that ended on a ray, is settled by at most ``REFINE_ITER`` semismooth Newton iterations on the same
    problem, counted with the ``ssn_iters``). Solved: Lemke's answer passed its check, or the refined
    one is a solution on its own piece."""
    du_c, p, dq, pivots, status = lemke_contact_callback(K, r, gap, slip, mu, drive,
                                                         start=lemke_start(hint, slip, mu))
    du_c, p, dq, refined, solved = polish(K, r, gap, slip, mu, du_c, dq, drive, refine_iter=REFINE_ITER)
    return _LCPSolution(du_c, p, dq, pivots, refined, jnp.array(0, jnp.int32),
                        (status == LemkeStatus.SOLVED) | solved)


def contact_newton_step(it: _Iterate, args, x, p_prev, law, hint):
    """The increment (du, dq) of one iteration, the new pair forces (m, 2), the band, the solver stats.

    ``hint`` (m, 2): forces whose active set starts Lemke or semismooth Newton (the last iterate's,
    or at the first iteration the last converged step's)."""
    c = args.contact
    n = args.mesh.n_dofs
    band = _band(it, c.tools, law.band)
    valid, normal = _band_normals(it, band)
    gap = jnp.where(valid, it.gap[band.pairs], GAP_FAR)
    pair_tool = _pair_tools(c.tools)
    mu = jnp.where(valid, pair_mu(c.tools, c.mu)[band.pairs], 0.0)
    slip = jnp.where(valid & (mu > 0), it.slip[band.pairs], 0.0)
    f_c_prev = jnp.zeros_like(it.f_int).at[pair_nodes(c.tools)].add(_pair_forces(it, p_prev))
    cond = _condense(it, args, x, band, normal, f_c_prev)
    tangent = _tangents(normal)

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


# ---- semismooth Newton inside the global Newton loop (solver "ssn") --------------------------------

def _pair_local(it: _Iterate, f_pairs):
    """Per pair ``(n . f, t . f, gap, slip)`` with the node force ``f`` (m, 2) held fixed: the values
    (m, 4) and the derivatives d/du (m, 4, 2) and d/dq (m, 4) with respect to the pair's node
    displacement and its tool's position (zero where a pair projects on no primitive)."""
    n, f = it.normal, f_pairs
    d_n = it.jac[:, :2, :]                                       # (m, 2, 3)
    d_nf = jnp.einsum("mi,mij->mj", f, d_n)
    d_tf = -f[:, :1] * d_n[:, 1, :] + f[:, 1:] * d_n[:, 0, :]    # t = (-n_y, n_x)
    values = jnp.stack([jnp.sum(n * f, -1), jnp.sum(_tangents(n) * f, -1), it.gap, it.slip], -1)
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


class _Frames(NamedTuple):
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
def contact_frames(it: _Iterate, args) -> tuple[_Frames, BlockTridiag]:
    """The frames and constants at the iterate, and the tangent with kappa rows on prescribed dofs."""
    c = args.contact
    band = _band(it, c.tools, None)
    nodes, pairs = band.nodes, band.pairs
    valid, normal = _band_normals(it, band)
    rotation = jnp.stack([normal, _tangents(normal)], axis=-1)
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
    return _Frames(nodes, pairs, valid, normal, rotation, mu, 0.01 * jnp.abs(K_loc[:, 0, 0]),
                   0.01 * jnp.abs(K_loc[:, 1, 1]), kappa), K


def _equilibrium_force(it: _Iterate, args, x, hint, kappa) -> jax.Array:
    """f~ (n_dofs,): the internal force on free dofs, ``f_c^prev + kappa (u - u_presc)`` on prescribed
    ones, with f_c^prev the pair forces ``hint`` (m, 2)."""
    n = args.mesh.n_dofs
    f_c_prev = jnp.zeros_like(it.f_int).at[pair_nodes(args.contact.tools)].add(_pair_forces(it, hint))
    return jnp.where(args.mask, f_c_prev.reshape(-1) + kappa * (x[:n] - args.values), it.f_int.reshape(-1))


def _driven_rows(args, fr: _Frames, x, f_tilde, n):
    """The force-driven tool's pairs among ``fr``, its drive vector on the dofs and its row residual
    (the force balance, or the prescribed position in a phase where the tool is held)."""
    c = args.contact
    k = args.force_idx[0]
    e = c.tools[k].drive
    mine = (jnp.asarray(_pair_tools(c.tools))[fr.pairs] == k) & fr.valid
    dofs = (2 * fr.nodes[:, None] + jnp.arange(2)[None, :]).reshape(-1)
    v = jnp.zeros(n).at[dofs].set(jnp.where(mine[:, None], e[None, :], 0.0).reshape(-1))
    r_q = jnp.where(c.force_mask[k], v @ f_tilde - c.force[k], x[n] - c.q_presc[k])
    return mine, dofs, v, r_q


def semismooth_merit(x, it: _Iterate, args, hint, fr: _Frames) -> jax.Array:
    """Squared norm of the semismooth residual the in-loop solver drives to zero: f~ on the sheet's
    dofs with every candidate node's two rows replaced by its Alart-Curnier residual (C_N, C_T),
    and the tool's row. The constants and kappa of ``fr`` (the iterate the search started from) are
    kept, so that trial points are compared on one function."""
    n = args.mesh.n_dofs
    f_tilde = _equilibrium_force(it, args, x, hint, fr.kappa)
    f_nodes = f_tilde.reshape(-1, 2)
    band = _band(it, args.contact.tools, None)      # the nearest pair may differ from fr's
    valid, normal = _band_normals(it, band)
    R_N = jnp.einsum("ui,ui->u", normal, f_nodes[band.nodes])
    R_T = jnp.einsum("ui,ui->u", _tangents(normal), f_nodes[band.nodes])
    gap = jnp.where(valid, it.gap[band.pairs], GAP_FAR)
    slip = jnp.where(valid & (fr.mu > 0), it.slip[band.pairs], 0.0)
    _, C, _ = alart_curnier_residual(R_N, R_T, gap, slip, fr.mu, fr.c_n, fr.c_t)
    total = jnp.sum(f_nodes.at[band.nodes].set(C) ** 2)
    if args.force_idx:
        now = fr._replace(pairs=band.pairs, valid=valid)
        total = total + _driven_rows(args, now, x, f_tilde, n)[3] ** 2
    return total


def active_set_step(it: _Iterate, args, x, p_prev, law, hint, frames=None):
    """One iteration of semismooth Newton on the whole step (solver ``"ssn"``): the increment (du, dq),
    the pair forces it predicts (m, 2), the pairs used, the solver stats; same contract as
    :func:`contact_newton_step`, at the cost of one bulk solve.

    The Alart-Curnier equations of :mod:`jaxfric.alart_curnier` are written for every candidate node (with its
    nearest pair) with the contact force taken from equilibrium, p_a = (n, t)^T f~_a, where f~ is the
    internal force on free dofs and ``f_c^prev + kappa (u - u_presc)`` on prescribed ones (the kappa rows
    of the module docstring, step 1). On the active set read off the iterate, the node's two equilibrium
    rows are replaced by C_a = W_F p_a + W_K (g_N, s) (open: p = 0; stick: g = s = 0; slip: g = 0 and
    R_T = mu xi R_N): a row combination of the bulk tangent plus a 2 x 2 block of the node's own
    kinematics, so the matrix keeps its block-tridiagonal structure and each active-set pass costs one
    block-Thomas solve, like a penalty iteration. The force-driven tool's row is sum_a e_q . f~_a = P
    over its candidates. ``hint`` gives f_c^prev and the first active set (the last converged forces at
    a step's first iteration); ``p_prev`` is not used (the signature is the condensed step's).
    ``frames``: the result of :func:`contact_frames` at ``it`` when the caller has it already.
    """
    c = args.contact
    n = args.mesh.n_dofs
    n_nodes = n // 2
    m = it.gap.shape[0]
    all_nodes = pair_nodes(c.tools)
    fr, K = contact_frames(it, args) if frames is None else frames
    nodes, pairs, valid, normal, rotation = fr.nodes, fr.pairs, fr.valid, fr.normal, fr.rotation
    f_tilde = _equilibrium_force(it, args, x, hint, fr.kappa)
    f_nodes = f_tilde.reshape(-1, 2)

    vals, d_u, d_q = _pair_local(it, f_nodes[all_nodes])
    valid_all = it.valid[:, None]
    vals = jnp.where(valid_all, vals, jnp.array([0.0, 0.0, GAP_FAR, 0.0]))
    d_u = jnp.where(valid_all[..., None], d_u, 0.0)
    d_q = jnp.where(valid_all, d_q, 0.0)
    R_N, R_T = jnp.where(valid, vals[pairs, 0], f_nodes[nodes] @ jnp.array([0.0, 1.0])), \
        jnp.where(valid, vals[pairs, 1], f_nodes[nodes] @ jnp.array([-1.0, 0.0]))
    gap, slip, mu = vals[pairs, 2], jnp.where(fr.mu > 0, vals[pairs, 3], 0.0), fr.mu
    c_n, c_t = fr.c_n, fr.c_t
    nb, bs = K.diag.shape[0], K.diag.shape[1]
    ny1 = bs // 2
    col, loc = nodes // ny1, nodes % ny1
    if len(args.force_idx) > 1:
        raise NotImplementedError("exact contact supports at most one force-driven tool per scene")
    driven = bool(args.force_idx)
    if driven:
        force_driven = c.force_mask[args.force_idx[0]]
        mine, dofs, v, r_q = _driven_rows(args, fr, x, f_tilde, n)
        e_dot_n = jnp.where(mine, normal @ c.tools[args.force_idx[0]].drive, 0.0)[:, None]
        C_row = jnp.where(force_driven, K.transpose().matvec(v), 0.0)

    def classify(R_N, R_T, g, s):
        state, _, sig_n = alart_curnier_residual(R_N, R_T, g, s, mu, c_n, c_t)
        if driven:
            state = jnp.where(force_driven, keep_tools_touching(state, sig_n, e_dot_n), state)
        return state

    def solve(state):
        """The increment on the active set ``state``, and the forces, gap and slip it predicts."""
        w_f, w_k = piece_jacobian(state, mu, c_n, c_t)
        # Rows of the candidate nodes: C_a = W_F (n, t)^T f~_a + W_K (g, s).
        A = jnp.einsum("uij,ukj->uik", w_f, rotation)                    # W_F R^T
        local = jnp.einsum("uij,ujk->uik", w_f, d_u[pairs, :2]) + jnp.einsum("uij,ujk->uik", w_k, d_u[pairs, 2:])
        C_rows = jnp.einsum("uij,uj->ui", w_f, jnp.stack([R_N, R_T], -1)) + \
            jnp.einsum("uij,uj->ui", w_k, jnp.stack([gap, slip], -1))
        T = jnp.broadcast_to(jnp.eye(2), (n_nodes, 2, 2)).at[nodes].set(A)
        J = _row_transform(K, T)
        Jd = J.diag.reshape(nb, ny1, 2, ny1, 2).at[col, loc, :, loc, :].add(local)
        J = BlockTridiag(J.lower, Jd.reshape(nb, bs, bs), J.upper)
        F = f_tilde.reshape(-1, 2).at[nodes].set(C_rows).reshape(-1)
        if driven:
            b_col = jnp.einsum("uij,uj->ui", w_f, d_q[pairs, :2]) + jnp.einsum("uij,uj->ui", w_k, d_q[pairs, 2:])
            B = jnp.zeros(n).at[dofs].set(jnp.where(mine[:, None], b_col, 0.0).reshape(-1))
            B = jnp.where(force_driven, B, 0.0)
            M = Bordered(A=J, B=B[:, None], C=C_row[None, :], D=jnp.where(force_driven, 0.0, 1.0).reshape(1, 1))
            dx = bordered_solve(M, -jnp.concatenate([F, r_q[None]]))
            du, dq_pairs = dx[:n], jnp.where(mine, dx[n], 0.0)
        else:
            du = block_tridiag_solve(J, -F)
            dx, dq_pairs = du, jnp.zeros(nodes.shape[0])
        du_a = du.reshape(-1, 2)[nodes]
        df = K.matvec(du).reshape(-1, 2)[nodes]
        linear = (vals[pairs] + jnp.einsum("uij,uj->ui", d_u[pairs], du_a) + d_q[pairs] * dq_pairs[:, None])
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
    state0 = classify(h[:, 0], h[:, 1], gap, slip)

    # One solve in the traced program (its first pass takes state0): each copy of the block solve
    # costs compile time.
    def next_state(state, p_l, g_l, s_l):
        """The active set read off the last solve's prediction. A node that penetrates at this iterate
        and whose sticking piece predicts a tensile force slips first (along the predicted tangential
        force) instead of opening: opened, it keeps penetrating and closes again, and stick <-> open
        cycles without end (Nine 60 x 2 at half the nominal increments, B's first touch: R_N = -1.5e-4
        N/mm closed, a penetration of 2.7e-5 mm open, every outer iteration of every cut step)."""
        new = classify(p_l[:, 0], p_l[:, 1], g_l, s_l)
        slip = jnp.where(p_l[:, 1] >= 0.0, SLIP_POS, SLIP_NEG)
        return jnp.where((state == STICK) & (new == OPEN) & (gap < 0.0) & (mu > 0.0), slip, new)

    def more(carry):
        i, state, _, p_l, g_l, s_l = carry
        return (i == 0) | ((i < law.ssn_max_iter) & jnp.any(next_state(state, p_l, g_l, s_l) != state))

    def again(carry):
        i, state, _, p_l, g_l, s_l = carry
        state = jnp.where(i == 0, state0, next_state(state, p_l, g_l, s_l))
        return (i + 1, state) + solve(state)

    n_u = nodes.shape[0]
    start = (jnp.array(0, jnp.int32), state0, jnp.zeros(n + len(args.force_idx)), jnp.zeros((n_u, 2)),
             jnp.zeros(n_u), jnp.zeros(n_u))
    iters, state, dx, p_new, g_l, s_l = jax.lax.while_loop(more, again, start)
    settled = jnp.all(next_state(state, p_new, g_l, s_l) == state)
    p_new = jnp.where((state != 0)[:, None], p_new, 0.0)
    p = jnp.zeros((m, 2)).at[pairs].set(p_new)
    in_band = jnp.zeros(m, bool).at[pairs].set(True)
    # An active set that cycles: the last pass's increment is taken all the same (counted as a
    # fallback). The Newton loop goes on from there, and its convergence test still asks for settled
    # statuses, so no converged step rests on it.
    stats = jnp.stack([jnp.array(0, jnp.int32), iters, (~settled).astype(jnp.int32)])
    return dx, p, in_band, stats, jnp.all(jnp.isfinite(dx))


def pair_status(p, mu_pairs):
    return contact_status(p[:, 0], p[:, 1], mu_pairs)


def _contact_out(it: _Iterate, p, tool_f, status):
    return dict(q=it.q, force=tool_f, rn=p[:, 0], rt=p[:, 1], zeta=it.zeta, gap=it.gap, normal=it.normal,
                status=status, slip=it.slip)


class _Trial(NamedTuple):
    """A Newton direction and the step length tried along it (the in-loop solver's line search)."""

    dx: jax.Array
    alpha: jax.Array     # () step length of the trial (1, 1/4 or 1/16 of dx)
    p_new: jax.Array     # (m, 2) forces the direction predicts (the hint of the trials' merit)
    in_band: jax.Array
    stats: jax.Array     # (3,) of the direction's solve
    lcp_ok: jax.Array
    merit: jax.Array     # () the merit at the point the direction starts from (with the direction's hint)
    frames: object       # _Frames there (constants of the merit), or None without a search


def _exact_newton(args, x0, x_ref, options: NewtonOptions, law):
    c = args.contact
    mu_pairs = pair_mu(c.tools, c.mu)
    m = mu_pairs.shape[0]
    pen_tol = 10.0 * options.du_atol

    def classify(k, x, it, R, dx_norm, same, band_ok, lcp_ok):
        r_norm = jnp.max(jnp.abs(R))
        leaves = (R, it.f_int, it.K.diag, it.gap)
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in leaves]))
        scale = jnp.max(jnp.abs(it.f_int))
        res_ok = r_norm <= options.atol + options.rtol * jnp.maximum(scale, 1e-6)
        dx_ok = dx_norm <= options.du_atol + options.du_rtol * jnp.max(jnp.abs(x - x_ref))
        done = (k >= 1) & res_ok & dx_ok & same
        # A band too small shows as a converged state with a penetrating outsider, or as a Newton loop
        # that cannot settle because the outsiders enter and leave the band: both are reported as such.
        out_of_iterations = k >= options.max_iterations
        code = jnp.select(
            [~finite, ~lcp_ok, it.det_min <= 0.0, (done | out_of_iterations) & ~band_ok, done, out_of_iterations],
            [Result.NONFINITE, Result.LCP_FAILED, Result.INVERTED_ELEMENT, Result.CONTACT_BAND, Result.SUCCESS,
             Result.MAX_ITERATIONS], Result.CONTINUE)
        return code.astype(jnp.int32), r_norm

    search = law.solver == "ssn" and options.line_search   # static
    step = active_set_step if law.solver == "ssn" else contact_newton_step
    no_stats = jnp.zeros(3, jnp.int32)

    # The loop evaluates one point per pass (the initial guess first, then each trial), then takes the
    # next trial: a new direction, the same one shortened, or none once the step is decided. So the
    # traced program holds one linearisation and one direction solve (each copy costs compile time).
    def body(carry):
        k, x, it, p, status, x_t, tr, _, r_hist, stats = carry     # k: index of the point x_t
        it_t = linearize_iterate(x_t, args)
        R, _ = iterate_residual(x_t, it_t, tr.p_new, args)
        status_new = pair_status(tr.p_new, mu_pairs)
        penetrating = it_t.valid & (it_t.gap < -pen_tol)
        band_ok = ~jnp.any(~tr.in_band & penetrating) | (k == 0)
        # An open pair of the band that penetrates at the new iterate closes at the next one.
        settled = jnp.all(status_new == status) & ~jnp.any(tr.in_band & penetrating & (tr.p_new[:, 0] <= 0.0))
        if law.solver == "ssn":  # static: no step converges on an active set that did not settle,
            settled = settled & (tr.stats[2] == 0) & (tr.alpha == 1.0)   # nor on a shortened step
        step_norm = jnp.max(jnp.abs(tr.alpha * tr.dx))
        code, r_norm = classify(k, x_t, it_t, R, step_norm, settled, band_ok, tr.lcp_ok)
        reject = jnp.array(False)
        if search:
            # Line search on the semismooth residual (:func:`semismooth_merit`): a step that raises it is retried
            # at a quarter, then a sixteenth of its length, which is then kept. Where the active set
            # jumps (a node reaching or leaving a tool on a soft, slipping strip) the full step can
            # overshoot: on the Nine test the residual then grew tenfold per iteration until an element
            # inverted, and the step was cut three times (about 75 iterations lost per event, one event
            # per node spacing drawn).
            # The trial is measured with the forces the direction predicts (tr.p_new), which are the
            # hint the next direction's merit starts from, so the merits of accepted iterates form one
            # non-increasing sequence. Measured with the direction's own hint instead, each new
            # direction re-based the merit: where a candidate node has a prescribed dof (the Nine's
            # entry-guided tail reaching A), f~ there is hint-driven and the re-based merit of the same
            # point rose 5 to 20 times per iteration, so the iterates drifted along the strip's soft
            # draw-in mode (Nine 300 x 3 at 0.4 mm increments: residual 4.6e-3 -> 37 N/mm over 30
            # iterations of a 6.6e-4 mm step, and the run stopped at U = 43.7 mm).
            worse = ~(semismooth_merit(x_t, it_t, args, tr.p_new, tr.frames) <= tr.merit)
            reject = (k > 0) & worse & (tr.alpha > 1.0 / 16.0) & (code != Result.SUCCESS)
            code = jnp.where(reject & (k < options.max_iterations), Result.CONTINUE, code).astype(jnp.int32)
        keep = lambda a, b: jnp.where(reject, a, b)  # noqa: E731
        x, it = keep(x, x_t), jax.tree_util.tree_map(keep, it, it_t)
        p, status = keep(p, tr.p_new), keep(status, status_new)

        def fresh():
            hint = jnp.where(k == 0, p_step, p)
            if not search:
                dx, p_new, in_band, s, lcp_ok = step(it, args, x, p, law, hint)
                return _Trial(dx, jnp.array(1.0), p_new, in_band, s, lcp_ok, tr.merit, tr.frames), s
            # The frames (nodes, constants, kappa rows) serve the direction and the merit alike.
            frames = contact_frames(it, args)
            dx, p_new, in_band, s, lcp_ok = active_set_step(it, args, x, p, law, hint, frames=frames)
            merit = semismooth_merit(x, it, args, hint, frames[0])
            return _Trial(dx, jnp.array(1.0), p_new, in_band, s, lcp_ok, merit, frames[0]), s

        def shorter():
            return tr._replace(alpha=0.25 * tr.alpha), no_stats

        def stop():
            return tr, no_stats

        branch = jnp.where(code != Result.CONTINUE, 2, jnp.where(reject, 1, 0))
        tr, s = jax.lax.switch(branch, [fresh, shorter, stop])
        return (k + 1, x, it, p, status, x + tr.alpha * tr.dx, tr, code, r_hist.at[k].set(r_norm),
                stats + s)

    zeros = lambda tree: jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), tree)  # noqa: E731
    it_shape = eqx.filter_eval_shape(linearize_iterate, x0, args)
    frames0 = zeros(eqx.filter_eval_shape(lambda i, a: contact_frames(i, a)[0], it_shape, args)) if search else None
    p0 = jnp.zeros((m, 2))
    # The last converged forces (simulate passes them as lam_n, lam_t): the first active set.
    p_step = jnp.stack([jnp.concatenate(c.lam_n), jnp.concatenate(c.lam_t)], -1)
    tr0 = _Trial(jnp.zeros_like(x0), jnp.array(1.0), p0, jnp.zeros(m, bool), no_stats, jnp.array(True),
                 jnp.array(jnp.inf), frames0)
    r_hist = jnp.full(options.max_iterations + 1, jnp.nan)
    carry = (jnp.array(0, jnp.int32), x0, zeros(it_shape), p0, jnp.zeros(m, jnp.int8), x0, tr0,
             jnp.array(Result.CONTINUE, jnp.int32), r_hist, no_stats)
    k, x, it, p, status, _, _, code, r_hist, stats = jax.lax.while_loop(lambda c: c[7] == Result.CONTINUE, body,
                                                                        carry)
    _, tool_f = iterate_residual(x, it, p, args)
    aux = (it.f_int, it.states, _contact_out(it, p, tool_f, status))
    return NewtonSolution(x, aux, k - 1, code, r_hist[k - 1], r_hist), stats


@eqx.filter_custom_jvp
def exact_solve(args, x0, x_ref, *, options: NewtonOptions, law):
    """Solve one load step with exact contact from the initial guess ``x0`` (``x_ref``: the last
    converged state, reference of the increment test).

    Returns ``(NewtonSolution, stats)`` with ``stats`` = (Lemke pivots, semismooth Newton iterations
    (with ``lcp_lemke``: those refining its answers), ``lcp_ssn`` iterations whose active set did not
    settle) summed over the step's iterations; the solution's ``aux`` has the layout of the penalty
    path: (f_int, material states, contact outputs).
    """
    return _exact_newton(args, x0, x_ref, options, law)


@exact_solve.def_jvp
def _exact_solve_jvp(primals, tangents, *, options, law):
    raise NotImplementedError(
        "derivatives of a run with exact contact (Complementarity, algorithms lcp_lemke / lcp_ssn) are not "
        "defined; differentiate with Penalty or AugmentedLagrangian (optionally with smoothing) instead")
