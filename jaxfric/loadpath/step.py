"""One load step: its data, its solve by the model's contact formulation, and the state it gives.

:func:`step_args` gathers everything the residual of a step from a converged state to a target
pseudo-time depends on (:class:`jaxfric.contact.system.StepArgs`: prescribed values, the tools' positions or
forces, the contact multipliers); :func:`solve_step` solves it with the model's contact formulation
(:mod:`jaxfric.contact.formulations`) and returns the new :class:`~jaxfric.loadpath.model.SimState`. The formulation's
continuation (:class:`jaxfric.loadpath.controller.StepControl`) enters here as a softened formulation.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..contact.formulations import newton_step
from ..contact.friction import sliding_speed
from ..contact.preselection import complete_geometry, select_pairs
from ..contact.rigid import (
    ContactState,
    ContactStep,
    Force,
    Move,
    pair_friction,
    pair_speed_periods,
    pair_speeds,
    split_pairs,
)
from ..contact.status import contact_status
from ..contact.system import StepArgs, kept_predictor, linearize
from ..fem.assembly import mesh_geometry
from ..fem.element import ElementGeometry, enhanced_count
from ..fem.loading import constraint_masks, prescribed_values
from ..numerics.newton import Linearization, NewtonOptions
from .controller import StepControl
from .model import SimState, StripModel, tool_positions

__all__ = ["StepContext", "step_args", "unknowns", "linearize_step", "solve_step", "step_state",
           "continuation_on", "continuation_stages", "softened_args"]


class StepContext(eqx.Module):
    """Loop-invariant data of a run, computed once before the loop."""

    model: StripModel
    geo: ElementGeometry
    masks: jax.Array

    @classmethod
    def build(cls, model: StripModel) -> StepContext:
        masks = jnp.asarray(constraint_masks(model.mesh.n_nodes, model.phases))
        return cls(model, mesh_geometry(model.mesh, model.thickness_points), masks)


def _contact_step(model: StripModel, state: SimState, phase, tau, law, dt=0.0) -> tuple:
    """The contact data of a step in ``phase`` at phase-local time ``tau``, from the last state; ``dt``:
    the step's duration in seconds (``StripModel.phase_seconds``)."""
    c = state.contact
    assert c is not None   # a model with tools
    new_phase = phase != state.phase
    # Controls are relative to the tool's position / force at the start of the phase.
    q_start = jnp.where(new_phase, c.q, c.q_start)
    f_start = jnp.where(new_phase, c.force, c.f_start)
    q_table, f_table = [], []
    for p in range(model.n_phases):  # static: the control type of each tool changes with the phase
        q_row, f_row = [], []
        for k, tool in enumerate(model.tools):
            ctrl = tool.controls[p]
            q_row.append(ctrl.position(q_start[k], tau) if isinstance(ctrl, Move) else c.q[k])
            f_row.append(ctrl.force(f_start[k], tau) if isinstance(ctrl, Force) else jnp.zeros(()))
        q_table.append(jnp.stack(q_row))
        f_table.append(jnp.stack(f_row))
    force_mask = np.array([[isinstance(t.controls[p], Force) for t in model.tools]
                           for p in range(model.n_phases)])
    mu_now = tuple(t.mu[phase] for t in model.tools)
    lam_t = []
    for tool, rt in zip(model.tools, split_pairs(model.tools, c.rt)):
        # R_T,n restarts from 0 at a phase boundary where the tool's mu changes (spec 1.5).
        reset = new_phase & (tool.mu[phase] != tool.mu[state.phase])
        lam_t.append(jnp.where(reset, 0.0, rt))
    # lambda_N: the last converged R_N where the formulation starts from it (the augmented Lagrangian's
    # warm start, spec 1.6; exact contact's guess of the first active set); the penalty law's is 0.
    lam_n = split_pairs(model.tools, c.rn if law.warm_start else jnp.zeros_like(c.rn))
    # The candidates each tool's pairs are evaluated at in this step (jaxfric.contact.preselection).
    near, clearance = select_pairs(model.tools, model.mesh.nodes, state.u, c.q, c.gap,
                                   law.forces_at_any_gap)
    step = ContactStep(tools=model.tools, law=law, mu=mu_now, lam_n=lam_n, lam_t=tuple(lam_t),
                       u_ref=_candidates(model, state.u), q_ref=c.q, q_presc=jnp.stack(q_table)[phase],
                       force=jnp.stack(f_table)[phase], force_mask=jnp.asarray(force_mask)[phase], dt=dt,
                       speed=split_pairs(model.tools, c.speed), near=near, clearance=clearance)
    return step, q_start, f_start


def _candidates(model: StripModel, u: jax.Array) -> tuple:
    """Per tool, the displacements (n_k, 2) of its candidate nodes."""
    return tuple(u[np.asarray(t.candidates)] for t in model.tools)


def step_args(model: StripModel, state: SimState, phase, t_target, ctx: StepContext, damping=None):
    """The data of the step from ``state`` to ``t_target`` in ``phase``; ``damping`` (may be traced): the
    stabilisation's eta (N/mm per mm, 0: none) acting on the increment from ``state``, or None (no such
    term in the program)."""
    phase = jnp.asarray(phase, jnp.int32)
    t_target = jnp.asarray(t_target, jnp.float64)
    tau = t_target - phase.astype(t_target.dtype)
    values = prescribed_values(model.mesh.nodes, model.phases, phase, tau)
    contact, q_start, f_start = (None, None, None)
    if model.tools:
        dt = 0.0
        if model.phase_seconds is not None:   # None or not: static (the tree's structure)
            dt = (t_target - state.time) * jnp.asarray(model.phase_seconds)[phase]
        contact, q_start, f_start = _contact_step(model, state, phase, tau, model.contact, dt)
    u_start = None if damping is None else state.u.reshape(-1)
    args = StepArgs(model.mesh, model.material, ctx.geo, state.material, ctx.masks[phase], values,
                    contact, model.formulation, model.force_tools, damping, u_start, enhanced_carry(model, state))
    return args, q_start, f_start


def enhanced_carry(model: StripModel, state: SimState):
    """The enhanced parameters' predictor a step from ``state`` starts from (:class:`StepArgs`'s
    ``predictor``), or None where the elements condense them by their local solve.

    It is the last linearisation's predictor of the converged step, which the point states keep, so
    Newton's first point (the secant guess) gets the enhanced parameters linearised about the converged
    ones."""
    if enhanced_count(model.formulation, model.mesh.nodes_per_element) and model.enhanced_update == "iterate":
        return kept_predictor(state.material)
    return None


def unknowns(model: StripModel, u, q) -> jax.Array:
    """The Newton unknowns x = (u, q_f) from displacements u and all tool positions q."""
    q_f = q[np.asarray(model.force_tools)] if model.force_tools else jnp.zeros(0)
    return jnp.concatenate([u.reshape(-1), q_f])


def linearize_step(model: StripModel, state: SimState, phase, t_target) -> Linearization:
    """Residual and Jacobian (BlockTridiag, or Bordered with force-driven tools) of the step from the
    converged ``state`` to ``t_target`` in ``phase``, at the unknowns of ``state`` (for inspection,
    debugging and benchmarks; :func:`solve_step` iterates on it)."""
    args, _, _ = step_args(model, state, phase, t_target, StepContext.build(model))
    return linearize(unknowns(model, state.u, tool_positions(state)), args)


def _softenable(model: StripModel) -> bool:
    """Static: the model's contact formulation has a continuation (:class:`StepControl`)."""
    return bool(model.tools) and model.contact is not None and model.contact.continuation


def continuation_on(model: StripModel, control: StepControl) -> bool:
    """Static: the load loop carries (and compiles) the continuation's stages: asked for, and a
    formulation that has them."""
    return control.continuation and _softenable(model)


def continuation_stages(model: StripModel) -> jax.Array:
    """() int32: the number of continuation stages of the model's formulation (:class:`StepControl`);
    0 when it has none or the material gives no stiffness scale."""
    E = getattr(model.material, "E", None)   # the sheet's stiffness scale (a law without one: no stages)
    if not _softenable(model) or E is None:
        return jnp.array(0, jnp.int32)
    assert model.contact is not None
    return model.contact.continuation_stages(E)


def softened_args(args: StepArgs, m) -> StepArgs:
    """``args`` with the formulation of continuation stage m (m = 0: unchanged, bit for bit)."""
    assert args.contact is not None
    return eqx.tree_at(lambda a: a.contact.law, args, args.contact.law.softened(m))


def solve_step(model: StripModel, state: SimState, phase, t_target,
               newton: NewtonOptions = NewtonOptions(), ctx: StepContext | None = None, guess=None,
               search=True, soften=None, damping=None):
    """Solve one load step from the converged ``state`` to pseudo-time ``t_target`` in phase ``phase``.

    ``guess`` is Newton's initial point ``(u (n_nodes, 2), q (n_tools,))`` (default: the last state).
    ``search`` False switches Newton's line search off (penalty and augmented Lagrangian laws).
    ``soften`` (int, may be traced; formulations with a continuation only): a continuation stage of
    :class:`StepControl` when >= 0: the formulation's ``softened(soften)`` (penalty: eps_n and eps_t
    divided by 10^soften; 0: the model's law), and Newton's round-off floor
    relative to the positions (:mod:`jaxfric.numerics.newton`); None or < 0: a plain attempt.
    ``damping`` (may be traced): the stabilisation's eta (N/mm per mm) on the increment from ``state``
    (:class:`StepControl`, ``stabilize``); 0 or None: none.

    Returns the :class:`StepSolution` (iterations, code, residual history, AL augmentations) and the
    new :class:`SimState` (meaningful only when ``solution.code == Result.SUCCESS``).
    """
    ctx = StepContext.build(model) if ctx is None else ctx
    t_target = jnp.asarray(t_target, jnp.float64)
    phase = jnp.asarray(phase, jnp.int32)
    args, q_start, f_start = step_args(model, state, phase, t_target, ctx, damping)
    stage = jnp.array(False)
    if soften is not None and _softenable(model):
        stage = jnp.asarray(soften) >= 0
        args = softened_args(args, jnp.maximum(soften, 0))
    x_ref = unknowns(model, state.u, tool_positions(state))
    x0 = x_ref if guess is None else unknowns(model, *guess)
    if model.tools:
        sol = args.contact.law.solve_step(args, x0, x_ref, newton, search, stage)
    else:   # no contact: one Newton solve
        sol = newton_step(args, x0, x_ref, newton, search, stage)
    return sol, step_state(model, args, sol, t_target, phase, q_start, f_start)


def step_state(model: StripModel, args, sol, t_target, phase, q_start, f_start) -> SimState:
    """The state a step attempt's solution stands for (meaningful only if it converged)."""
    f_int, states, c_out = sol.aux
    new_contact = None
    if model.tools:
        n = model.mesh.n_dofs
        c_out = complete_geometry(args.contact, model.mesh.nodes, sol.x[:n].reshape(-1, 2), c_out["q"], c_out)
        kept = {k: v for k, v in c_out.items() if k != "slip"}  # slip is a per-attempt measure only
        # The stored status follows the spec's force thresholds (section 0) for every law, so that the
        # counts of closed and slipping pairs agree with the forces written out.
        kept["status"] = contact_status(kept["rn"], kept["rt"],
                                        pair_friction(model.tools, args.contact.mu, model.mesh.nodes, kept["rn"],
                                                      pair_speeds(args.contact)))
        kept["speed"] = sliding_speed(c_out["slip"], args.contact.dt, pair_speeds(args.contact),
                                      pair_speed_periods(model.tools))
        new_contact = ContactState(q_start=q_start, f_start=f_start, **kept)
    return SimState(u=sol.x[: model.mesh.n_dofs].reshape(-1, 2), material=states, f_int=f_int,
                    time=t_target, phase=phase, contact=new_contact)
