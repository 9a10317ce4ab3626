"""The nonlinear system of one load step: residual and Jacobian of the strip with its tools.

Unknowns x = (u, q_f): the nodal displacements, node-major, and the positions of the tools that are
force-driven in some phase. Residual (spec 1.3, 1.8):

    R_u = f_int(u) - f_c(u, q) [+ eta (u - u_n)]   free dofs;  u - u_presc on prescribed dofs
    R_q = sum_a e_q . f_c,a - P                    force-driven phase;  q - q_presc otherwise

The bracketed term is the step controller's stabilisation (:class:`jaxfric.loadpath.controller.StepControl`,
``stabilize``): a damper of stiffness eta on every node, acting on the step's displacement increment from
the converged u_n; absent (``StepArgs.damping`` None) or zero in every other attempt.

The Jacobian is block-tridiagonal (strip, plus a 2x2 block per contact pair on the diagonal), bordered
by the force-driven tools (:class:`jaxfric.numerics.linalg.Bordered`); prescribed dofs get identity rows. All
derivatives come from automatic differentiation (element tangents, pair Jacobians).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..fem.assembly import internal_force, internal_force_and_tangent, shared_trace
from ..fem.element import ElementGeometry
from ..fem.material import J2Material
from ..fem.mesh import StripMesh
from ..numerics.linalg import BlockTridiag, Bordered
from ..numerics.newton import Linearization
from .preselection import holds
from .rigid import ContactStep, evaluate_pairs, pair_friction, pair_nodes, pair_speeds, tool_forces
from .status import settled_status
from .tools import GAP_OPEN

__all__ = ["StepArgs", "residual", "linearize", "damped", "kept_predictor"]


class StepArgs(eqx.Module):
    """Everything the residual of one step depends on (the differentiable data travels here): the
    strip, its converged history, the prescribed values and mask of the phase, the contact data."""

    mesh: StripMesh
    material: J2Material
    geo: ElementGeometry
    states: object
    mask: jax.Array
    values: jax.Array
    contact: ContactStep | None
    formulation: str = eqx.field(static=True)
    force_idx: tuple = eqx.field(static=True)
    damping: jax.Array | None = None    # () eta (N/mm per mm) of the stabilisation; None: no such term
    u_start: jax.Array | None = None    # (n_dofs,) the converged displacements the damper acts from
    # (n_el, n_alpha, 9) the enhanced parameters' predictor the linearisation starts from (the enhanced-strain
    # update: alpha carried with the Newton iterate, jaxfric.fem.element); None: alpha condensed by the
    # elements' local solve. Newton passes it from each linearisation to the next (`carry`, `with_carry`).
    predictor: jax.Array | None = None

    @property
    def carry(self):
        """What the first evaluation of the step starts from besides x (:mod:`jaxfric.numerics.newton`)."""
        return self.predictor

    def with_carry(self, predictor) -> StepArgs:
        """These args for an evaluation that continues from ``predictor`` (None: the local solve)."""
        return dataclasses.replace(self, predictor=predictor)


def kept_predictor(states) -> jax.Array:
    """The enhanced predictor the point states of a converged solution keep (``anst`` and ``eas`` with the
    enhanced-strain update): its last linearisation's, from which a Newton solve that starts at that solution
    continues (:attr:`StepArgs.predictor`)."""
    return states.enhanced[:, 0]


def _constrain_rows(K: BlockTridiag, mask: jax.Array, scale=1.0) -> BlockTridiag:
    """Replace the row of every prescribed dof i by ``scale_i e_i`` (default: identity rows; ``scale``
    a scalar or one value per dof); keeps the block structure."""
    nb, m = K.diag.shape[0], K.diag.shape[1]
    fixed = mask.reshape(nb, m)
    keep = jnp.where(fixed, 0.0, 1.0)
    scale = jnp.broadcast_to(jnp.asarray(scale, K.diag.dtype), mask.shape).reshape(nb, m)
    diag = K.diag * keep[:, :, None] + jax.vmap(jnp.diag)((1.0 - keep) * scale)
    return BlockTridiag(lower=K.lower * keep[1:, :, None], diag=diag, upper=K.upper * keep[:-1, :, None])


def _contact_of(args: StepArgs) -> ContactStep:
    """The contact data of a step with tools (the callers below run only for a model with tools)."""
    assert args.contact is not None
    return args.contact


def _contact_terms(args: StepArgs, u, qf, jacobian: bool):
    """Contact forces at (u, q): per-node forces, per-tool clamping forces, and the pair results."""
    c = _contact_of(args)
    q = c.q_presc.at[np.asarray(args.force_idx)].set(qf) if args.force_idx else c.q_presc
    pairs = evaluate_pairs(c, args.mesh.nodes, u, q, jacobian)
    f_c = jnp.zeros_like(u).at[pair_nodes(c.tools)].add(jnp.concatenate([p.f for p in pairs]))
    return q, pairs, f_c, tool_forces(c, pairs)


def _contact_out(q, pairs, tool_f):
    cat = lambda name: jnp.concatenate([getattr(p, name) for p in pairs])  # noqa: E731
    return dict(q=q, force=tool_f, rn=cat("rn"), rt=cat("rt"), zeta=cat("zeta"), gap=cat("gap"),
                normal=cat("normal"), status=cat("status"), slip=cat("slip"))


def _evaluate(x, args: StepArgs, jacobian: bool):
    n = args.mesh.n_dofs
    u, qf = x[:n].reshape(-1, 2), x[n:]
    if jacobian:
        a = internal_force_and_tangent(args.mesh, args.material, args.formulation, args.geo, u, args.states,
                                       args.predictor)
    else:
        a = internal_force(args.mesh, args.material, args.formulation, args.geo, u, args.states)
    r_u, _ = damped(args, x[:n], f_int=a.f_int)
    contact = None
    if args.contact is not None:
        q, pairs, f_c, tool_f = _contact_terms(args, u, qf, jacobian)
        r_u = r_u - f_c
        contact = (q, pairs, tool_f)
    R = jnp.where(args.mask, x[:n] - args.values, r_u.reshape(-1))
    if args.force_idx:
        assert contact is not None    # force-driven tools are tools
        R = jnp.concatenate([R, _tool_rows(args, contact[1], contact[2], qf)])
    return R, a, contact


def _seeking(pair) -> tuple:
    """Whether a force-driven tool seeks the sheet (no pair closed, but some pair projects on a
    primitive), the index of its nearest pair, and the pairs' gaps (inf where open)."""
    closed = pair.status > 0
    valid = pair.gap < GAP_OPEN / 2
    gap = jnp.where(valid, pair.gap, jnp.inf)
    nearest = jnp.argmin(gap)
    return ~jnp.any(closed) & jnp.any(valid), nearest, gap


def _tool_rows(args: StepArgs, pairs, tool_f, qf):
    """Residual rows of the force-driven tools: force balance; q - q_presc when displacement-driven.

    A tool that has lost every contact cannot balance a force, and its balance row does not depend on
    its position. Its row then asks it to close the nearest gap, R_q = -g_min / (e_q . n), so one Newton
    step brings it back onto the sheet, where the balance row takes over. With P = 0 the tool rests
    touching the sheet with zero force, one admissible answer to an otherwise indeterminate position.
    """
    c = _contact_of(args)
    rows = []
    for j, k in enumerate(args.force_idx):
        tool, p = c.tools[k], pairs[k]
        seeking, nearest, gap = _seeking(p)
        closing = jnp.maximum(p.normal[nearest] @ tool.drive, 0.1)  # gap decrease per unit of q
        seek = -jnp.where(seeking, gap[nearest], 0.0) / closing
        balance = jnp.where(seeking, seek, tool_f[k] - c.force[k])
        rows.append(jnp.where(c.force_mask[k], balance, qf[j] - c.q_presc[k]))
    return jnp.stack(rows)


def residual(x, args: StepArgs):
    R, a, contact = _evaluate(x, args, jacobian=False)
    return R, (a.f_int, a.states, None if contact is None else _contact_out(*contact))


def _contact_jacobian(args: StepArgs, K: BlockTridiag, pairs, keep):
    """Add the pair Jacobians to the diagonal blocks and build the border of the force-driven tools."""
    nodes = pair_nodes(_contact_of(args).tools)
    cols, rows = args.mesh.block_rows(nodes)
    dfdx = jnp.concatenate([p.df_dx for p in pairs])
    # R_u = f_int - f_c: the pair blocks enter with a minus sign (free rows only: `keep`).
    diag = K.diag.at[cols[:, None, None], rows[:, :, None], rows[:, None, :]].add(-dfdx)
    K = BlockTridiag(K.lower, diag, K.upper)
    if not args.force_idx:
        return K
    c = _contact_of(args)
    n = args.mesh.n_dofs
    B_cols, C_rows, D_diag = [], [], []
    for k in args.force_idx:
        tool, p = c.tools[k], pairs[k]
        dofs = (2 * np.asarray(tool.candidates)[:, None] + np.arange(2)[None, :]).ravel()
        B_cols.append(jnp.zeros(n).at[dofs].add(-p.df_dq.ravel()) * keep)
        driven = c.force_mask[k]
        # d(e_q . f)/dx per pair, scattered to the pair's node dofs.
        row = jnp.zeros(n).at[dofs].add(jnp.einsum("i,pij->pj", tool.drive, p.df_dx).ravel())
        seeking, _, _ = _seeking(p)
        lost = ~jnp.any(p.status > 0)
        C_rows.append(jnp.where(driven & ~lost, row, 0.0))
        # Seeking: d(-g_min / (e_q . n))/dq = 1. No pair on any primitive at all: the balance row has no
        # derivative; eps_n keeps the matrix regular (the attempt then fails, the residual is -P).
        d = jnp.where(seeking, 1.0, jnp.sum(p.df_dq @ tool.drive) + jnp.where(lost, c.law.eps_n, 0.0))
        D_diag.append(jnp.where(driven, d, 1.0))
    return Bordered(A=K, B=jnp.stack(B_cols, axis=1), C=jnp.stack(C_rows), D=jnp.diag(jnp.stack(D_diag)))


def damped(args: StepArgs, u, f_int=None, K=None):
    """The step controller's damper (module docstring) where the attempt has one (``args.damping``): the
    internal force ``f_int`` (n_nodes, 2) plus eta (u - u_n) on the free dofs, and the tangent ``K``
    (BlockTridiag) plus eta on its diagonal; either may be None (not asked for). Without a damper both come
    back as given. ``u``: (n_dofs,). The exact solvers' iterate carries it too
    (:mod:`jaxfric.contact.exact_iterate`)."""
    if args.damping is None:   # static: a run without the stabilised attempt
        return f_int, K
    assert args.u_start is not None
    if f_int is not None:
        f_int = f_int + jnp.where(args.mask, 0.0, args.damping * (u - args.u_start)).reshape(f_int.shape)
    if K is not None:
        K = BlockTridiag(K.lower, K.diag + args.damping * jnp.eye(K.diag.shape[-1]), K.upper)
    return f_int, K


@shared_trace     # a Newton loop's shapes (filter_eval_shape before the loop) and its body: one trace
def linearize(x, args: StepArgs) -> Linearization:
    R, a, contact = _evaluate(x, args, jacobian=True)
    keep = jnp.where(args.mask, 0.0, 1.0)
    assert a.tangent is not None
    _, strip = damped(args, x[:args.mesh.n_dofs], K=a.tangent)
    K: BlockTridiag | Bordered = strip
    status = None
    aux_contact = None
    if contact is not None and args.contact is not None:
        q, pairs, tool_f = contact
        K = _contact_jacobian(args, strip, pairs, keep)
        aux_contact = _contact_out(q, pairs, tool_f)
        # Newton's "no status change" test (jaxfric.contact.status.settled_status) with the default force
        # tolerance of the residual test.
        negligible = 1e-10 + 1e-8 * jnp.max(jnp.abs(a.f_int))
        status = settled_status(aux_contact["status"], aux_contact["rn"], aux_contact["rt"],
                                pair_friction(args.contact.tools, args.contact.mu, args.mesh.nodes,
                                              aux_contact["rn"], pair_speeds(args.contact)), negligible)
    # Prescribed dofs: R = x - values, so their Jacobian rows are identity rows.
    J: BlockTridiag | Bordered
    if isinstance(K, Bordered):
        J = Bordered(A=_constrain_rows(K.A, args.mask), B=K.B, C=K.C, D=K.D)
    else:
        J = _constrain_rows(K, args.mask)
    presc = jnp.max(jnp.where(args.mask, jnp.abs(R[: args.mesh.n_dofs]), 0.0))
    # Only the sheet's prescribed dofs enter this test, not the rows q - q_presc of a tool that has a
    # position unknown but is displacement-driven in this phase (the blankholder's lower tool while it
    # closes): Newton's line search may then shorten a first step that carries such a tool's increment,
    # and the next iterations apply the rest (the row is linear). That damping of the tool's first
    # advance is what lets the blankholder's 'close' phase converge at the spec mesh.
    # Round-off of the residual (Newton's floor, where the caller asks for it: jaxfric.numerics.newton): the
    # contact gaps are computed from the positions X + u, so with tools it is relative to those. Only
    # a formulation's continuation stages ask (jaxfric.loadpath.controller.StepControl); no other traces it.
    preselected = magnitude = None
    n = args.mesh.n_dofs
    if contact is not None and args.contact is not None:
        preselected = holds(args.contact, x[:n].reshape(-1, 2), contact[0])
    if contact is not None and args.contact is not None and args.contact.law.continuation:
        magnitude = jnp.concatenate([jnp.abs(args.mesh.nodes.reshape(-1) + x[:n]), jnp.abs(x[n:])])
    return Linearization(R, J, jnp.max(jnp.abs(a.f_int)), a.det_min > 0.0,
                         (a.f_int, a.states, aux_contact), status, presc, magnitude, preselected,
                         carry=a.predictor, inner=a.enhanced_gap)

