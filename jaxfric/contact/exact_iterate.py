"""Exact contact, one Newton iterate: the bulk operators and the pair geometry at x = (u, q_f), the
step residual with given contact forces, and the status those forces give (:mod:`jaxfric.contact.exact`)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..fem.assembly import internal_force, internal_force_and_tangent, shared_trace
from ..numerics.linalg import BlockTridiag
from .pair_batches import PairTool, map_pairs
from .preselection import expand, gather
from .rigid import ContactStep, pair_nodes, split_pairs
from .status import contact_status
from .system import damped
from .tools import GAP_OPEN

__all__ = ["KAPPA", "REFINE_ITER", "GAP_FAR", "Iterate", "linearize_iterate", "iterate_values", "iterate_residual",
           "pair_status", "pair_forces", "pair_tools", "tangents", "iterate_tool_positions", "Band", "proximity_band",
           "band_normals"]


KAPPA = 1e2       # prescribed rows: kappa = KAPPA K_ii (see the module docstring)
REFINE_ITER = 10  # semismooth Newton iterations refining a Lemke answer on a piece boundary (polish)
GAP_FAR = 10.0    # mm: gap given to a band node that projects on no tool (it stays open)


class Iterate(NamedTuple):
    """Bulk operators and pair geometry at one Newton iterate."""

    f_int: jax.Array      # (n_nodes, 2)
    K: BlockTridiag | None  # d f_int / du (None: the values only, :func:`iterate_values`)
    states: object
    det_min: jax.Array
    q: jax.Array          # (n_t,) tool positions
    gap: jax.Array        # (m,) GAP_OPEN where the pair projects on no primitive
    normal: jax.Array     # (m, 2)
    zeta: jax.Array       # (m,)
    slip: jax.Array       # (m,) slip since the start of the step
    valid: jax.Array      # (m,) bool
    jac: jax.Array        # (m, 4, 3) d(n_x, n_y, gap, slip) / d(u_a, q_k) of each pair (node, tool)
    predictor: jax.Array | None = None     # the next iterate's enhanced predictor (jaxfric.fem.assembly.Assembled)
    enhanced_gap: jax.Array | None = None  # () force the elements' own equations still move (N/mm)


def pair_tools(tools) -> np.ndarray:
    """Static: the index of each pair's tool (m,)."""
    return np.concatenate([np.full(len(t.candidates), k) for k, t in enumerate(tools)])


def iterate_tool_positions(args, qf) -> jax.Array:
    """All tool positions: prescribed, or the unknown where the tool is force-driven in this phase."""
    c = args.contact
    if not args.force_idx:
        return c.q_presc
    idx = np.asarray(args.force_idx)
    return c.q_presc.at[idx].set(jnp.where(c.force_mask[idx], qf, c.q_presc[idx]))


def _geometry(step: ContactStep, nodes_ref, u, q, derivatives: bool = True):
    """Projection of every pair at (u, q): gap, normal, zeta, the slip since the step start, validity,
    and the derivatives of (normal, gap, slip) with respect to the pair's node displacement and its
    tool's position, in closed form from the projection (:meth:`jaxfric.contact.pair_batches.PairTool.jacobian`;
    ``derivatives`` False: zeros instead). Tools of one structure are evaluated as one batch
    (:func:`jaxfric.contact.pair_batches.map_pairs`)."""
    def pair_fn(tool: PairTool, tool_values, pair_values):
        q_k, q_ref = tool_values
        X, u_a, u_ref = pair_values
        pr = tool.projection(X, u_a, u_ref, q_k, q_ref)
        return (tool.jacobian(pr) if derivatives else jnp.zeros((4, 3))), pr

    def pair_args(k):
        idx = np.asarray(step.tools[k].candidates)
        return tuple(gather(step.selected(k), a) for a in (nodes_ref[idx], u[idx], step.u_ref[k]))

    out, jac = [], []
    evaluated = map_pairs(step.tools, pair_fn, lambda k: (q[k], step.q_ref[k]), pair_args, friction=False)
    for k, (J, pr) in enumerate(evaluated):
        near, n_k = step.selected(k), len(step.tools[k].candidates)
        # The pairs left out are open (jaxfric.contact.preselection): the open projection, no derivative.
        jac.append(expand(near, J, n_k))
        out.append(pr._replace(**{f: expand(near, getattr(pr, f), n_k, GAP_OPEN if f == "gap" else 0.0)
                                  for f in pr._fields}))
    cat = lambda name: jnp.concatenate([getattr(p, name) for p in out])  # noqa: E731
    return cat("gap"), cat("normal"), cat("zeta"), cat("zeta_increment"), cat("valid"), jnp.concatenate(jac)


def _iterate(x, args, derivatives: bool) -> Iterate:
    n = args.mesh.n_dofs
    u = x[:n].reshape(-1, 2)
    q = iterate_tool_positions(args, x[n:])
    if derivatives:
        a = internal_force_and_tangent(args.mesh, args.material, args.formulation, args.geo, u, args.states,
                                       args.predictor)
    else:
        a = internal_force(args.mesh, args.material, args.formulation, args.geo, u, args.states)
    gap, normal, zeta, slip, valid, jac = _geometry(args.contact, args.mesh.nodes, u, q, derivatives)
    # The stabilised attempt's damper: the exact solvers solve f_int + eta (u - u_n) = f_c (their contact
    # forces read off that equilibrium are the damped problem's).
    f_int, K = damped(args, x[:n], a.f_int, a.tangent)
    return Iterate(f_int, K, a.states, a.det_min, q, gap, normal, zeta, slip, valid, jac,
                   a.predictor, a.enhanced_gap)


@shared_trace     # the loop's shapes (filter_eval_shape before the loop) and its body: one trace
def linearize_iterate(x, args) -> Iterate:
    return _iterate(x, args, derivatives=True)


def iterate_values(x, args) -> Iterate:
    """The iterate's values without its derivatives: the internal forces and material states, the pairs'
    geometry (``K`` None, ``jac`` zeros); what the residual at x is a function of."""
    return _iterate(x, args, derivatives=False)


def tangents(normal):
    return jnp.stack([-normal[..., 1], normal[..., 0]], axis=-1)


def pair_forces(it: Iterate, p) -> jax.Array:
    """(m, 2) force on the sheet of every pair, R_N n + R_T t."""
    return p[:, :1] * it.normal + p[:, 1:] * tangents(it.normal)


def iterate_residual(x, it: Iterate, p, args):
    """Residual of the step at the iterate with contact forces p (m, 2); and the tool forces."""
    n = args.mesh.n_dofs
    c = args.contact
    f_pairs = pair_forces(it, p)
    f_c = jnp.zeros_like(it.f_int).at[pair_nodes(c.tools)].add(f_pairs)
    R = jnp.where(args.mask, x[:n] - args.values, (it.f_int - f_c).reshape(-1))
    tool_f = jnp.stack([jnp.sum(f @ t.drive) for f, t in zip(split_pairs(c.tools, f_pairs), c.tools)])
    rows = [jnp.where(c.force_mask[k], tool_f[k] - c.force[k], x[n + j] - c.q_presc[k])
            for j, k in enumerate(args.force_idx)]
    if rows:
        R = jnp.concatenate([R, jnp.stack(rows)])
    return R, tool_f


def pair_status(p, mu_pairs):
    return contact_status(p[:, 0], p[:, 1], mu_pairs)


# ---- the proximity band -----------------------------------------------------------------------------

class Band(NamedTuple):
    nodes: jax.Array   # (n_c,) sheet nodes
    pairs: jax.Array   # (n_c,) the pair of each band node (index into the m pairs)


def node_pairs(tools) -> tuple[np.ndarray, np.ndarray]:
    """Static: the distinct candidate nodes (n_u,) and their pairs (n_u, w), padded with m."""
    nodes = pair_nodes(tools)
    unique = np.unique(nodes)
    width = max(int(np.sum(nodes == a)) for a in unique)
    table = np.full((unique.size, width), nodes.size, dtype=np.int64)
    for i, a in enumerate(unique):
        mine = np.flatnonzero(nodes == a)
        table[i, : mine.size] = mine
    return unique, table


def proximity_band(it: Iterate, tools, size: int | None) -> Band:
    unique, table = node_pairs(tools)
    gap = jnp.concatenate([jnp.where(it.valid, it.gap, jnp.inf), jnp.array([jnp.inf])])
    g = gap[table]
    best = jnp.argmin(g, axis=1)
    pairs = jnp.asarray(table)[jnp.arange(unique.size), best]
    if size is None or size >= unique.size:
        return Band(jnp.asarray(unique), pairs)
    _, sel = jax.lax.top_k(-jnp.min(g, axis=1), size)
    return Band(jnp.asarray(unique)[sel], pairs[sel])


def band_normals(it: Iterate, band: Band) -> tuple[jax.Array, jax.Array]:
    """Whether each band node's pair projects on its tool, and its normal ((0, 1) where it does not)."""
    valid = it.valid[band.pairs]
    return valid, jnp.where(valid[:, None], it.normal[band.pairs], jnp.array([0.0, 1.0]))
