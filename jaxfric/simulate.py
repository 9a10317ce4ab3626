"""The strip model and its load path, run entirely inside JAX.

A :class:`StripModel` is fixed data (mesh, material, phases). The evolving state (displacements,
plastic history, internal forces, pseudo-time, phase) is a :class:`SimState`, threaded through the
load steps explicitly. Two drivers share one step routine:

- :func:`simulate` (adaptive): a ``lax.while_loop`` over attempts with the step controller of the
  benchmark spec (section 1.9): halve the increment after a failed attempt, at most ``max_cuts`` times
  below the nominal one; grow it by ``growth`` after two consecutive easy steps; clip it to phase ends
  and schedule breakpoints. Differentiable in forward mode (``jax.jvp``).
- :func:`simulate_fixed`: a ``lax.scan`` over the nominal steps without cutting: a fixed-length loop,
  so reverse mode (``jax.grad``/``jax.vjp``) works too.

Each step is a Newton solve (:func:`jaxfric.newton.newton_solve`) differentiated by the implicit
function theorem, and the converged plastic history is carried to the next step, so derivatives follow
the loading path. Failures are result codes; :func:`jaxfric.run.run` turns them into exceptions.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._checks import check_int, check_nonnegative, is_concrete
from .assembly import internal_force, mesh_geometry
from .contact import (
    ContactState,
    ContactStep,
    Force,
    Move,
    initial_contact_state,
    max_penetration,
    pair_mu,
    pair_nodes,
    split_pairs,
)
from .element import FORMULATIONS, ElementGeometry
from .formulations import AbstractContactFormulation, StepSolution, newton_step
from .loading import Phase, constraint_masks, prescribed_values, schedule
from .material import J2Material
from .mesh import StripMesh
from .newton import SOLUTION_NAME, Linearization, NewtonOptions, newton_pass, newton_result, newton_start
from .progress import report
from .results import Result
from .status import SLIP, contact_status
from .system import StepArgs, linearize
from .tools import project

__all__ = ["StripModel", "SimState", "StepControl", "History", "Simulation", "initial_state",
           "default_observe", "stresses", "solve_step", "linearize_step", "reactions",
           "contact_force_field", "StepSolution", "simulate", "simulate_flat", "simulate_fixed"]


class StripModel(eqx.Module):
    """A strip of elasto-plastic material under a sequence of phases of prescribed displacements,
    optionally in contact with rigid tools.

    Attributes:
        mesh: the strip mesh.
        material: the material law (one quadrature point).
        phases: the load path, one :class:`~jaxfric.loading.Phase` per phase.
        formulation: "fbar" (default), "eas" (enhanced strain Q1/E4) or "q4" (plain Q4, for elastic
            checks only); static. See :mod:`jaxfric.element`.
        tools: rigid tools (:class:`~jaxfric.contact.RigidTool`), one control per phase each.
        contact: the contact formulation, needed with tools
            (:class:`~jaxfric.formulations.AbstractContactFormulation`: :class:`~jaxfric.formulations.Penalty`,
            :class:`~jaxfric.formulations.AugmentedLagrangian` or :class:`~jaxfric.formulations.Complementarity`).
    """

    mesh: StripMesh
    material: J2Material
    phases: tuple
    formulation: str = eqx.field(static=True, default="fbar")
    tools: tuple = ()
    contact: AbstractContactFormulation | None = None

    def __check_init__(self):
        if not isinstance(self.mesh, StripMesh):
            raise ValueError(f"field 'mesh' must be a StripMesh (jaxfric.strip_mesh), got {self.mesh!r}")
        if not (hasattr(self.material, "update") and hasattr(self.material, "init_state")):
            raise ValueError(f"field 'material' must be a material law such as J2Material, got {self.material!r}")
        if self.formulation not in FORMULATIONS:
            raise ValueError(f"field 'formulation' must be one of {FORMULATIONS}, got {self.formulation!r}")
        if len(self.phases) == 0 or not all(isinstance(p, Phase) for p in self.phases):
            raise ValueError("field 'phases' must be a non-empty tuple of Phase")
        names = [p.name for p in self.phases]
        if len(set(names)) != len(names):
            raise ValueError(f"field 'phases' has repeated phase names: {names}")
        constraint_masks(self.mesh.n_nodes, self.phases)  # validates node indices
        if self.tools and not isinstance(self.contact, AbstractContactFormulation):
            raise ValueError(f"field 'contact' must be a contact formulation (e.g. Penalty(eps_n, eps_t)) when "
                             f"there are tools, got {self.contact!r}")
        names = [t.name for t in self.tools]
        if len(set(names)) != len(names):
            raise ValueError(f"field 'tools' has repeated tool names: {names}")
        for tool in self.tools:
            if len(tool.controls) != len(self.phases):
                raise ValueError(f"tool {tool.name!r} has {len(tool.controls)} controls for "
                                 f"{len(self.phases)} phases")
            if max(tool.candidates) >= self.mesh.n_nodes or min(tool.candidates) < 0:
                raise ValueError(f"tool {tool.name!r}: field 'candidates' names nodes outside the mesh")
            if is_concrete((self.mesh.nodes, tool.geometry)):
                _check_tool_placement(tool, self.mesh.nodes)

    @property
    def n_phases(self) -> int:
        return len(self.phases)

    @property
    def force_tools(self) -> tuple:
        """Static indices of the tools that are force-driven in some phase (one unknown each)."""
        return tuple(k for k, t in enumerate(self.tools) if t.force_driven)


@eqx.filter_jit
def _project_all(geometry, points):
    # Compiled once per tool structure and size: building many scenes does not re-dispatch op by op.
    return jax.vmap(project, in_axes=(None, 0, None))(geometry, points, jnp.zeros(2))


def _check_tool_placement(tool, nodes) -> None:
    """Before any computation: a tool must not cut into the sheet at rest, and a force-driven tool
    must have a candidate node that projects on it (otherwise no force can ever balance it)."""
    idx = np.asarray(tool.candidates)
    proj = _project_all(tool.geometry, nodes[idx])
    gap, valid = np.asarray(proj.gap), np.asarray(proj.valid)
    scale = 1e-9 * max(1.0, float(np.max(np.abs(np.asarray(nodes)))))
    inside = valid & (gap < -scale)
    if inside.any():
        worst = int(np.argmin(np.where(inside, gap, np.inf)))
        raise ValueError(f"tool {tool.name!r} intersects the sheet at the start: node {int(idx[worst])} is "
                         f"{-gap[worst]:.3g} mm inside it; move the tool or the sheet so they at most touch")
    if tool.force_driven and not valid.any():
        raise ValueError(f"tool {tool.name!r} is force-driven but none of its candidate nodes projects on it, "
                         f"so it can never touch the sheet; check its geometry, 'candidates' and 'drive'")


class SimState(eqx.Module):
    """State after a converged step.

    Attributes:
        u: (n_nodes, 2) displacements (mm).
        material: material states at every Gauss point (leading axes (n_el, 4)).
        f_int: (n_nodes, 2) internal forces (N/mm); at prescribed dofs these are the reactions.
        time: () pseudo-time.
        phase: () int32 index of the phase of the last step.
        contact: contact history and outputs (:class:`~jaxfric.contact.ContactState`), or None.
    """

    u: jax.Array
    material: Any
    f_int: jax.Array
    time: jax.Array
    phase: jax.Array
    contact: ContactState | None = None


class StepControl(eqx.Module):
    """Step controller settings (static).

    Attributes:
        max_cuts: an attempt below nominal / 2**max_cuts stops the run. (At the smallest increment a
            failed first attempt, started from the secant prediction, is retried once from the
            converged state; then the increment gets one last attempt with Newton's line search off,
            before the run stops.)
        growth: increment growth factor after ``easy_steps`` consecutive easy steps.
        easy_iterations: a step is easy when each of its Newton solves (one per AL augmentation)
            needed at most this many iterations.
        max_steps: size of the history buffer (accepted steps); default 10x the nominal count + 100.
        continuation: for a formulation that has one (the penalty law: ``continuation_stages``,
            ``softened``). At the smallest increment, after the retry from the converged state and
            before the attempt without line search, the step is solved first with the penalties
            divided by 10^m, then by 10^(m-1), ..., each stage from the last one's solution, the last
            one at the true penalties (m = ceil(log10(eps_n / E)): the first stage's penalty is of
            the order of the sheet's modulus E; no stage when eps_n <= E). A stage's solution is only
            a starting point: the step is accepted when Newton converges at the true penalties. In
            the stages Newton's round-off floor is relative to the positions X + u, from which the
            gaps are computed (:mod:`jaxfric.newton`): a looser test, used only where the step would
            otherwise stop the run. The stages count as attempts in the step's ``cutbacks``.
            Reason: at a stiff penalty a pair touching a curved tool can 2-cycle between open (the
            free node driven into the tool) and closed at a spurious force whose geometric stiffness
            throws it out again; from the softer problem's solution it arrives closed with about its
            true force (``tests/test_extreme.py::test_nine_edges``, eps_n 1e9). The derivative of a step is
            that of its converged solution; a fixed-step replay (:func:`simulate_fixed`) has no
            stages, so it fails at a step the adaptive run accepted only after them.
    """

    max_cuts: int = eqx.field(static=True, default=10)
    growth: float = eqx.field(static=True, default=1.5)
    easy_iterations: int = eqx.field(static=True, default=6)
    easy_steps: int = eqx.field(static=True, default=2)
    max_steps: int | None = eqx.field(static=True, default=None)
    continuation: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        check_int("max_cuts", self.max_cuts, 0, 60)
        if not isinstance(self.continuation, bool):
            raise ValueError(f"field 'continuation' must be True or False, got {self.continuation!r}")
        check_int("easy_iterations", self.easy_iterations, 1)
        check_int("easy_steps", self.easy_steps, 1)
        check_int("max_steps", self.max_steps, 1, 10_000_000, optional=True)
        check_nonnegative("growth", self.growth)
        if not self.growth >= 1.0:
            raise ValueError(f"field 'growth' must be a finite number >= 1, got {self.growth!r}")


class History(eqx.Module):
    """Per-step records in preallocated buffers; rows 0..n_rows-1 are filled (row 0: initial state).

    Attributes:
        time, phase, newton_iters, cutbacks, augmentations: (S,) per row.
        solver_stats: (S, 3) exact contact: Lemke pivots, semismooth Newton iterations (active-set
            passes), fallbacks (condensed solver: Lemke after SSN; "ssn": iterations whose active set
            did not settle), summed over the step's attempts (zero for the other laws).
        observed: pytree of per-row observations, leading axis S.
        n_rows: () number of filled rows.
    """

    time: jax.Array
    phase: jax.Array
    newton_iters: jax.Array
    cutbacks: jax.Array
    augmentations: jax.Array
    solver_stats: jax.Array
    observed: Any
    n_rows: jax.Array


class Simulation(eqx.Module):
    """Outcome of a simulation: its history, final converged state and result code.

    ``failed_time`` is the pseudo-time the last failed attempt was aiming at (nan if none failed).
    ``pending_cuts`` counts the failed attempts after the last accepted step: the cutbacks of the step
    that stopped the run, which no history row records (0 when the run completed).
    """

    history: History
    final: SimState
    code: jax.Array
    failed_time: jax.Array
    residual_norm: jax.Array
    pending_cuts: jax.Array | int = 0


def initial_state(model: StripModel) -> SimState:
    """The state before the first step: zero displacements, virgin material at every Gauss point, the
    tools at their initial positions (with no force), pseudo-time 0 in phase 0."""
    n_el = model.mesh.n_elements
    one = model.material.init_state()
    states = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (n_el, 4) + a.shape), one)
    zeros = jnp.zeros((model.mesh.n_nodes, 2))
    contact = initial_contact_state(model.tools, model.mesh.nodes) if model.tools else None
    return SimState(u=zeros, material=states, f_int=zeros, time=jnp.array(0.0),
                    phase=jnp.array(0, jnp.int32), contact=contact)


def default_observe(model: StripModel, state: SimState) -> dict:
    """Reactions on the left and right ends (sums of f_int - f_c over their nodes), the largest eqps,
    and with tools: their positions and clamping forces, the largest penetration and the numbers of
    active (closed) and slipping pairs."""
    reaction = reactions(model, state)
    out = {
        "reaction_left": jnp.sum(reaction[model.mesh.left], axis=0),
        "reaction_right": jnp.sum(reaction[model.mesh.right], axis=0),
        "max_eqps": jnp.max(state.material.eqps),
    }
    if state.contact is not None:
        c = state.contact
        out.update(tool_position=c.q, tool_force=c.force,
                   max_penetration=max_penetration(c.status, c.gap),
                   n_active=jnp.sum(c.status > 0), n_slip=jnp.sum(c.status == SLIP))
    return out


def contact_force_field(model: StripModel, state: SimState) -> jax.Array:
    """(n_nodes, 2) contact forces on the sheet, f_c = R_N n + R_T t summed per node (N/mm)."""
    f_c = jnp.zeros_like(state.u)
    if state.contact is None:
        return f_c
    c = state.contact
    pair_f = c.rn[:, None] * c.normal + c.rt[:, None] * jnp.stack([-c.normal[:, 1], c.normal[:, 0]], 1)
    return f_c.at[pair_nodes(model.tools)].add(pair_f)


def reactions(model: StripModel, state: SimState) -> jax.Array:
    """(n_nodes, 2) reactions f_int - f_c: non-zero at prescribed dofs only, at convergence (N/mm)."""
    return state.f_int - contact_force_field(model, state)


def stresses(model: StripModel, state: SimState) -> jax.Array:
    """Kirchhoff stress (n_el, 4, 3, 3) (MPa) at every Gauss point of a converged state.

    Re-evaluating the update at the converged deformation from the converged history is exact: the
    trial state then lies on (or inside) the yield surface, so the return map is the identity.
    """
    return internal_force(model.mesh, model.material, model.formulation, mesh_geometry(model.mesh),
                          state.u, state.material).tau


# ---- one step -------------------------------------------------------------------------------------

class _Context(eqx.Module):
    """Loop-invariant data of a run, computed once before the loop."""

    model: StripModel
    geo: ElementGeometry
    masks: jax.Array

    @classmethod
    def build(cls, model: StripModel) -> _Context:
        masks = jnp.asarray(constraint_masks(model.mesh.n_nodes, model.phases))
        return cls(model, mesh_geometry(model.mesh), masks)


def _contact_step(model: StripModel, state: SimState, phase, tau, law) -> tuple:
    """The contact data of a step in ``phase`` at phase-local time ``tau``, from the last state."""
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
    step = ContactStep(tools=model.tools, law=law, mu=mu_now, lam_n=lam_n, lam_t=tuple(lam_t),
                       u_ref=_candidates(model, state.u), q_ref=c.q, q_presc=jnp.stack(q_table)[phase],
                       force=jnp.stack(f_table)[phase], force_mask=jnp.asarray(force_mask)[phase])
    return step, q_start, f_start


def _candidates(model: StripModel, u: jax.Array) -> tuple:
    """Per tool, the displacements (n_k, 2) of its candidate nodes."""
    return tuple(u[np.asarray(t.candidates)] for t in model.tools)


def _step_args(model: StripModel, state: SimState, phase, t_target, ctx: _Context):
    phase = jnp.asarray(phase, jnp.int32)
    t_target = jnp.asarray(t_target, jnp.float64)
    tau = t_target - phase.astype(t_target.dtype)
    values = prescribed_values(model.mesh.nodes, model.phases, phase, tau)
    contact, q_start, f_start = (None, None, None)
    if model.tools:
        contact, q_start, f_start = _contact_step(model, state, phase, tau, model.contact)
    args = StepArgs(model.mesh, model.material, ctx.geo, state.material, ctx.masks[phase], values,
                     contact, model.formulation, model.force_tools)
    return args, q_start, f_start


def _tool_q(state: SimState) -> jax.Array:
    return jnp.zeros(0) if state.contact is None else state.contact.q


def _unknowns(model: StripModel, u, q) -> jax.Array:
    """The Newton unknowns x = (u, q_f) from displacements u and all tool positions q."""
    q_f = q[np.asarray(model.force_tools)] if model.force_tools else jnp.zeros(0)
    return jnp.concatenate([u.reshape(-1), q_f])


def linearize_step(model: StripModel, state: SimState, phase, t_target) -> Linearization:
    """Residual and Jacobian (BlockTridiag, or Bordered with force-driven tools) of the step from the
    converged ``state`` to ``t_target`` in ``phase``, at the unknowns of ``state`` (for inspection,
    debugging and benchmarks; :func:`solve_step` iterates on it)."""
    args, _, _ = _step_args(model, state, phase, t_target, _Context.build(model))
    return linearize(_unknowns(model, state.u, _tool_q(state)), args)


def _softenable(model: StripModel) -> bool:
    """Static: the model's contact formulation has a continuation (:class:`StepControl`)."""
    return bool(model.tools) and model.contact is not None and model.contact.continuation


def _continuation_on(model: StripModel, control: StepControl) -> bool:
    """Static: the load loop carries (and compiles) the continuation's stages: asked for, and a
    formulation that has them."""
    return control.continuation and _softenable(model)


def _continuation_stages(model: StripModel) -> jax.Array:
    """() int32: the number of continuation stages of the model's formulation (:class:`StepControl`);
    0 when it has none or the material gives no stiffness scale."""
    E = getattr(model.material, "E", None)   # the sheet's stiffness scale (a law without one: no stages)
    if not _softenable(model) or E is None:
        return jnp.array(0, jnp.int32)
    assert model.contact is not None
    return model.contact.continuation_stages(E)


def _soften(args: StepArgs, m) -> StepArgs:
    """``args`` with the formulation of continuation stage m (m = 0: unchanged, bit for bit)."""
    assert args.contact is not None
    return eqx.tree_at(lambda a: a.contact.law, args, args.contact.law.softened(m))


def solve_step(model: StripModel, state: SimState, phase, t_target,
               newton: NewtonOptions = NewtonOptions(), ctx: _Context | None = None, guess=None,
               search=True, soften=None):
    """Solve one load step from the converged ``state`` to pseudo-time ``t_target`` in phase ``phase``.

    ``guess`` is Newton's initial point ``(u (n_nodes, 2), q (n_tools,))`` (default: the last state).
    ``search`` False switches Newton's line search off (penalty and augmented Lagrangian laws).
    ``soften`` (int, may be traced; formulations with a continuation only): a continuation stage of
    :class:`StepControl` when >= 0: the formulation's ``softened(soften)`` (penalty: eps_n and eps_t
    divided by 10^soften; 0: the model's law), and Newton's round-off floor
    relative to the positions (:mod:`jaxfric.newton`); None or < 0: a plain attempt.

    Returns the :class:`StepSolution` (iterations, code, residual history, AL augmentations) and the
    new :class:`SimState` (meaningful only when ``solution.code == Result.SUCCESS``).
    """
    ctx = _Context.build(model) if ctx is None else ctx
    t_target = jnp.asarray(t_target, jnp.float64)
    phase = jnp.asarray(phase, jnp.int32)
    args, q_start, f_start = _step_args(model, state, phase, t_target, ctx)
    stage = jnp.array(False)
    if soften is not None and _softenable(model):
        stage = jnp.asarray(soften) >= 0
        args = _soften(args, jnp.maximum(soften, 0))
    x_ref = _unknowns(model, state.u, _tool_q(state))
    x0 = x_ref if guess is None else _unknowns(model, *guess)
    if model.tools:
        sol = args.contact.law.solve_step(args, x0, x_ref, newton, search, stage)
    else:   # no contact: one Newton solve
        sol = newton_step(args, x0, x_ref, newton, search, stage)
    return sol, _step_state(model, args, sol, t_target, phase, q_start, f_start)


def _step_state(model: StripModel, args, sol, t_target, phase, q_start, f_start) -> SimState:
    """The state a step attempt's solution stands for (meaningful only if it converged)."""
    f_int, states, c_out = sol.aux
    new_contact = None
    if model.tools:
        kept = {k: v for k, v in c_out.items() if k != "slip"}  # slip is a per-attempt measure only
        # The stored status follows the spec's force thresholds (section 0) for every law, so that the
        # counts of closed and slipping pairs agree with the forces written out.
        kept["status"] = contact_status(kept["rn"], kept["rt"], pair_mu(model.tools, args.contact.mu))
        new_contact = ContactState(q_start=q_start, f_start=f_start, **kept)
    return SimState(u=sol.x[: model.mesh.n_dofs].reshape(-1, 2), material=states, f_int=f_int,
                    time=t_target, phase=phase, contact=new_contact)


def _select(pred, on_true, on_false):
    return jax.tree_util.tree_map(lambda a, b: jnp.where(pred, a, b), on_true, on_false)


def _empty_history(n: int, row0: dict) -> History:
    def buffer(a):
        a = jnp.asarray(a)
        return jnp.zeros((n,) + a.shape, a.dtype).at[0].set(a)

    return History(time=jnp.zeros(n), phase=jnp.zeros(n, jnp.int32),
                   newton_iters=jnp.zeros(n, jnp.int32), cutbacks=jnp.zeros(n, jnp.int32),
                   augmentations=jnp.zeros(n, jnp.int32), solver_stats=jnp.zeros((n, 3), jnp.int32),
                   observed=jax.tree_util.tree_map(buffer, row0), n_rows=jnp.array(1, jnp.int32))


def _record(h: History, row, pred, state: SimState, iters, cuts, augmentations, stats, observed) -> History:
    """Write row ``row`` when ``pred``; leave the buffers unchanged otherwise."""
    def put(buf, value):
        return buf.at[row].set(jnp.where(pred, value, buf[row]))

    return History(time=put(h.time, state.time), phase=put(h.phase, state.phase),
                   newton_iters=put(h.newton_iters, iters), cutbacks=put(h.cutbacks, cuts),
                   augmentations=put(h.augmentations, augmentations), solver_stats=put(h.solver_stats, stats),
                   observed=jax.tree_util.tree_map(put, h.observed, observed),
                   n_rows=jnp.where(pred, row + 1, h.n_rows))


def _report(row, t, iters, cuts, snapshot, model, state) -> None:
    extra = () if snapshot is None else (snapshot(model, state),)
    jax.debug.callback(report, row, t, iters, cuts, *extra)


# ---- drivers --------------------------------------------------------------------------------------

class _Predictor(eqx.Module):
    """Secant predictor: the last accepted increment of displacements and tool positions together
    (so that gaps are extrapolated consistently), scaled to the next step. Not used after a phase
    change, where the loading direction may reverse, nor on a retry after a failed attempt. It only
    moves Newton's starting point, never the solution."""

    du: jax.Array   # (n_nodes, 2) displacement increment of the last accepted step
    dq: jax.Array   # (n_tools,) tool position increment of the last accepted step
    dt: jax.Array   # () its pseudo-time increment (0: no prediction)

    @classmethod
    def empty(cls, state: SimState) -> _Predictor:
        return cls(jnp.zeros_like(state.u), jnp.zeros_like(_tool_q(state)), jnp.array(0.0))

    def guess(self, state: SimState, dt_next, phase_next, retry=False):
        use = (self.dt > 0) & (phase_next == state.phase) & ~jnp.asarray(retry, bool)
        scale = jnp.where(use, dt_next / jnp.where(use, self.dt, 1.0), 0.0)
        return state.u + scale * self.du, _tool_q(state) + scale * self.dq

    def after(self, ok, old: SimState, new: SimState) -> _Predictor:
        return _Predictor(du=jnp.where(ok, new.u - old.u, self.du),
                          dq=jnp.where(ok, _tool_q(new) - _tool_q(old), self.dq),
                          dt=jnp.where(ok, new.time - old.time, self.dt))


class _Loop(eqx.Module):
    """Carry of the adaptive load loop."""

    state: SimState
    predictor: _Predictor
    dt: jax.Array          # current increment (pseudo-time)
    seg: jax.Array         # current schedule segment
    n_easy: jax.Array      # consecutive easy steps
    cuts: jax.Array        # failed attempts since the last accepted step
    iters: jax.Array       # Newton iterations since the last accepted step
    stats: jax.Array       # (3,) exact-contact solver counts since the last accepted step
    history: History
    code: jax.Array
    failed_t: jax.Array    # target time of the last failed attempt
    r_norm: jax.Array      # residual norm of the last attempt
    plain: jax.Array       # this attempt runs Newton without the line search (last one at the floor)
    last_code: jax.Array   # result code of the last attempt
    soft: jax.Array        # continuation stage of this attempt: penalties / 10^soft; -1: none
    soft_tried: jax.Array  # the continuation has failed for the pending step
    stage_u: jax.Array     # (n_nodes, 2) the last stage's solution: the next stage's start ...
    stage_q: jax.Array     # (n_tools,) ... with these tool positions
    staged: jax.Array      # stage_u / stage_q hold a stage's solution


def simulate(model: StripModel, *, newton: NewtonOptions = NewtonOptions(),
             control: StepControl = StepControl(), observe: Callable = default_observe,
             progress: bool = False, snapshot: Callable | None = None) -> Simulation:
    """Run the whole load path with adaptive steps, inside one ``lax.while_loop``.

    Pure and jit-able (wrap with ``eqx.filter_jit``; :func:`jaxfric.run.run` does); ``observe(model,
    state) -> pytree`` is recorded at every accepted step and must be a static (hashable) function.
    With ``progress`` a host callback reports every accepted step (see :mod:`jaxfric.progress`);
    with ``snapshot(model, state) -> pytree`` (static) that pytree travels with the report, so the host
    can keep full states of chosen steps without a device buffer per step.
    """
    ctx = _Context.build(model)
    init, setup, finish = _controller(model, control, observe, progress, snapshot)

    def body(c: _Loop) -> _Loop:
        t_try, phase, guess = setup(c)
        sol, new_state = solve_step(model, c.state, phase, t_try, newton, ctx, guess=guess, search=~c.plain,
                                    soften=c.soft if _continuation_on(model, control) else None)
        return finish(c, sol, new_state, t_try)

    out = jax.lax.while_loop(lambda c: c.code == Result.CONTINUE, body, init)
    return Simulation(history=out.history, final=out.state, code=out.code, failed_time=out.failed_t,
                      residual_norm=out.r_norm, pending_cuts=out.cuts)


def _controller(model: StripModel, control: StepControl, observe: Callable, progress: bool,
                snapshot: Callable | None):
    """The adaptive step controller of the load loop: its initial carry, ``setup(c) -> (t_try, phase,
    guess)`` of the next attempt, and ``finish(c, sol, new_state, t_try) -> c`` after it."""
    sched = schedule(model.phases)
    n_seg = len(sched.seg_end)
    seg_end = jnp.asarray(sched.seg_end)
    seg_dt = jnp.asarray(sched.seg_dt)
    seg_phase = jnp.asarray(sched.seg_phase, jnp.int32)
    n_buf = control.max_steps or 10 * sched.n_nominal_steps + 100
    state0 = initial_state(model)
    int0 = jnp.array(0, jnp.int32)
    # Static: only a penalty model carries (and compiles) the continuation's state and logic; for the
    # other laws the loop is the one without it.
    soft_on = _continuation_on(model, control)
    n_stages = _continuation_stages(model) if soft_on else int0

    def setup(c: _Loop):
        t_start, dt_nom, end = c.state.time, seg_dt[c.seg], seg_end[c.seg]
        # Snap to the segment end when within round-off of it (steps end exactly on breakpoints).
        t_try = jnp.where(t_start + c.dt >= end - 1e-9 * dt_nom, end, t_start + c.dt)
        u, q = c.predictor.guess(c.state, t_try - t_start, seg_phase[c.seg], retry=c.cuts > 0)
        guess = (jnp.where(c.staged, c.stage_u, u), jnp.where(c.staged, c.stage_q, q)) if soft_on else (u, q)
        return t_try, seg_phase[c.seg], guess

    def finish(c: _Loop, sol, new_state, t_try) -> _Loop:
        t_start, dt_nom, end = c.state.time, seg_dt[c.seg], seg_end[c.seg]
        converged = sol.code == Result.SUCCESS
        ok = converged & (c.soft <= 0) if soft_on else converged
        iters = c.iters + sol.iterations
        stats = c.stats + sol.stats
        row = c.history.n_rows
        history = _record(c.history, row, ok, new_state, iters, c.cuts, sol.augmentations, stats,
                          observe(model, new_state))

        seg_done = ok & (t_try == end)
        next_seg = jnp.minimum(c.seg + seg_done.astype(jnp.int32), n_seg - 1)
        # "Easy" counts the iterations of one Newton solve, as the iteration limit does: an AL step
        # of several augmentations is easy when each of its solves is (with the step's total, every
        # AL step with more than one augmentation was hard, and the increment never grew back after
        # a cut: Nine mu000 AL eps_N 1e4, target 1e-5 mm took 6551 steps against 990 at 1e-3 mm).
        hardest = sol.iterations if sol.hardest is None else sol.hardest
        n_easy = jnp.where(ok & (hardest <= control.easy_iterations), c.n_easy + 1, 0)
        grow = n_easy >= control.easy_steps
        dt_ok = jnp.where(seg_done, seg_dt[next_seg],
                          jnp.where(grow, jnp.minimum(control.growth * c.dt, dt_nom), c.dt))
        dt_cut = 0.5 * (t_try - t_start)
        at_floor = ~ok & (dt_cut < dt_nom / 2.0**control.max_cuts * (1.0 - 1e-9))
        # A first attempt that fails at the smallest increment started from the secant prediction: try
        # the same increment once more from the converged state before giving up (the prediction can be
        # what fails: blankholder shape4, spec mesh, step 31 of 'close' failed from the prediction and
        # converges in 14 iterations from the converged state).
        again = at_floor & (c.cuts == 0)
        # Then one last attempt with Newton's line search off. The line search rejects every step that
        # raises the residual norm; when a front of pairs switches between stick and slip across a
        # clamp, each full step raises it a little on the way to convergence, and the backtracked steps
        # crawl (bead th045_mu000, augmented Lagrangian, step 71 of 'wind': no convergence in 25
        # iterations with the line search, plain Newton converges in 11).
        # If that fails too, the run stops with the code and residual of the attempt before it (the
        # last one with the line search): a plain Newton that strays ends in whatever it met first.
        # (A formulation without a line search to switch off has no such attempt.)
        # Before that, the formulation's continuation (StepControl.continuation): stages of softened
        # penalties, each from the last one's solution; a stage that fails ends it.
        searched = model.contact is None or not model.tools or model.contact.unsearched_retry
        plain = at_floor & ~again & ~c.plain & searched
        too_small = at_floor & ~again & ~plain
        repeat = again | plain
        if soft_on:
            # A converged continuation stage before the last gives the next stage's start, not a step.
            stage_done = converged & (c.soft > 0)
            start_soft = at_floor & ~again & ~c.plain & (c.soft < 0) & ~c.soft_tried & (n_stages > 0)
            soft_failed = (c.soft >= 0) & ~converged
            plain = plain & ~start_soft & ~stage_done
            too_small = at_floor & ~again & ~plain & ~start_soft & ~stage_done
            repeat = again | plain | start_soft | stage_done
            # A stage that does not end the step leaves r_norm and last_code: a run that stops after
            # the stages reports the attempt before them, not one of the softened problems.
            held = (c.soft >= 0) & ~ok
        finished = seg_done & (c.seg == n_seg - 1)
        full = ok & ~finished & (row + 1 >= n_buf + 1)
        code = jnp.select([too_small, finished, full], [jnp.where(c.plain, c.last_code, sol.code),
                                                        Result.SUCCESS, Result.MAX_STEPS],
                          Result.CONTINUE).astype(jnp.int32)
        if progress or snapshot is not None:
            jax.lax.cond(ok, lambda: _report(row, t_try, iters, c.cuts, snapshot, model, new_state),
                         lambda: None)
        keep_r = too_small & c.plain
        stages = dict(soft=c.soft, soft_tried=c.soft_tried, stage_u=c.stage_u, stage_q=c.stage_q, staged=c.staged)
        last_code = sol.code
        if soft_on:
            keep_r = keep_r | held
            last_code = jnp.where(held, c.last_code, sol.code)
            soft = jnp.where(start_soft, n_stages, jnp.where(stage_done, c.soft - 1, -1)).astype(jnp.int32)
            stages = dict(soft=soft,
                          soft_tried=~ok & (c.soft_tried | soft_failed),
                          stage_u=jnp.where(stage_done, new_state.u, c.stage_u),
                          stage_q=jnp.where(stage_done, _tool_q(new_state), c.stage_q), staged=stage_done)
        return _Loop(state=_select(ok, new_state, c.state),
                     predictor=c.predictor.after(ok, c.state, new_state),
                     dt=jnp.where(ok, dt_ok, jnp.where(repeat, t_try - t_start, dt_cut)), seg=next_seg,
                     n_easy=jnp.where(grow, 0, n_easy), cuts=jnp.where(ok, 0, c.cuts + 1),
                     iters=jnp.where(ok, 0, iters), stats=jnp.where(ok, 0, stats), history=history, code=code,
                     failed_t=jnp.where(ok, c.failed_t, t_try),
                     r_norm=jnp.where(keep_r, c.r_norm, sol.residual_norm),
                     plain=~ok & (c.plain | plain), last_code=last_code.astype(jnp.int32), **stages)

    init = _Loop(state=state0, predictor=_Predictor.empty(state0),
                 dt=seg_dt[0], seg=int0, n_easy=int0, cuts=int0, iters=int0, stats=jnp.zeros(3, jnp.int32),
                 history=_empty_history(n_buf + 1, observe(model, state0)),
                 code=jnp.array(Result.CONTINUE, jnp.int32), failed_t=jnp.array(jnp.nan),
                 r_norm=jnp.array(0.0), plain=jnp.array(False), last_code=int0,
                 soft=jnp.array(-1, jnp.int32), soft_tried=jnp.array(False),
                 stage_u=jnp.zeros_like(state0.u) if soft_on else jnp.zeros((0, 2)),
                 stage_q=jnp.zeros_like(_tool_q(state0)) if soft_on else jnp.zeros(0), staged=jnp.array(False))
    return init, setup, finish


def simulate_flat(model: StripModel, *, newton: NewtonOptions = NewtonOptions(),
                  control: StepControl = StepControl(), observe: Callable = default_observe) -> Simulation:
    """:func:`simulate` with one Newton iteration per pass of a single loop (penalty law only).

    The results are those of :func:`simulate` (the same attempts, iterations and step controller);
    only the loop structure differs: instead of a loop of attempts, each a Newton loop, one loop
    advances the current attempt by one Newton iteration and, when the attempt ends, runs the step
    controller and starts the next attempt. Under ``vmap`` (:func:`jaxfric.sweep.sweep`) a member then
    waits for no other member's attempt: the sweep takes as many passes as its largest member's total
    of Newton iterations and attempts, against the sum over attempts of the slowest member's
    iterations with the nested loops (a batched pass itself still costs more than a single one:
    ``docs/results.md``, batched sweeps). Forward only (derivatives: :func:`simulate`,
    whose steps are differentiated by the implicit function theorem); no progress reports.
    """
    if model.tools and model.contact is not None and not model.contact.one_newton_solve:
        raise ValueError(f"field 'contact': simulate_flat runs formulations whose step is one Newton solve "
                         f"(the penalty law), not {type(model.contact).__name__} (a loop of its own inside a step)")
    ctx = _Context.build(model)
    init, setup, finish = _controller(model, control, observe, False, None)
    soft_on = _continuation_on(model, control)

    def attempt(c: _Loop):
        """The next attempt of ``c``: its target time, phase and Newton start."""
        t_try, phase, guess = setup(c)
        return t_try, phase, newton_start(_unknowns(model, *guess), lin_shape, newton)

    def body(carry):
        c, t_try, phase, nc = carry
        args, q_start, f_start = _step_args(model, c.state, phase, t_try, ctx)
        if soft_on:
            args = _soften(args, jnp.maximum(c.soft, 0))
        x_ref = _unknowns(model, c.state.u, _tool_q(c.state))
        nc = newton_pass(nc, args, x_ref, linearize, newton, search=~c.plain,
                         positions=(c.soft >= 0) if soft_on else False)
        done = nc.code != Result.CONTINUE
        sol = StepSolution(*newton_result(nc), augmentations=jnp.array(0, jnp.int32),
                           stats=jnp.zeros(3, jnp.int32))
        c = _select(done, finish(c, sol, _step_state(model, args, sol, t_try, phase, q_start, f_start), t_try), c)
        return _select(done, (c,) + attempt(c), (c, t_try, phase, nc))

    t0, phase0, guess0 = setup(init)
    args0, _, _ = _step_args(model, init.state, phase0, t0, ctx)
    x0 = _unknowns(model, *guess0)
    lin_shape = eqx.filter_eval_shape(linearize, x0, args0)     # the same for every attempt
    carry = (init, t0, phase0, newton_start(x0, lin_shape, newton))
    out = jax.lax.while_loop(lambda carry: carry[0].code == Result.CONTINUE, body, carry)[0]
    return Simulation(history=out.history, final=out.state, code=out.code, failed_time=out.failed_t,
                      residual_norm=out.r_norm, pending_cuts=out.cuts)


def simulate_fixed(model: StripModel, *, newton: NewtonOptions = NewtonOptions(),
                   observe: Callable = default_observe, progress: bool = False,
                   snapshot: Callable | None = None, checkpoint: bool = True, fresh=None) -> Simulation:
    """Run the nominal steps of the load path in a fixed-length ``lax.scan`` (no step cutting).

    Reverse-mode differentiable. If a step fails the state stays at the last converged step, the
    remaining rows are not filled and ``code`` holds the failure.

    ``fresh``: optional (n_steps,) booleans, known at trace time: the steps whose Newton iterations
    start from the last converged state instead of the secant prediction. Replaying the accepted steps
    of an adaptive run (:func:`jaxfric.loading.with_steps`), the steps accepted after a cutback were
    retries, which start so; marking them reproduces the adaptive run's iterations exactly.

    Memory of reverse mode: the history rows are scan outputs, not a carried buffer, so a step's carry
    is the converged state alone (displacements, tool positions, material and contact state). With
    ``checkpoint`` (default) every step is rematerialised in the backward pass (``jax.checkpoint``):
    the forward pass keeps only the carry at each step and its converged solution (named
    ``SOLUTION_NAME``), and the backward pass rebuilds one step at a time from them by one
    linearisation, without re-running Newton, so the memory grows as n_steps x state size, whatever
    the cost of a step's linearisation and factorisation. Without it every step's Newton residuals and factors are
    kept (n_steps x step intermediates), several times more; the factor is measured by
    ``experiments/bench_grad_memory.py``. Forward mode (``jax.jvp``) is unaffected.
    """
    times, phases = schedule(model.phases).nominal_steps()
    ctx = _Context.build(model)
    state0 = initial_state(model)
    row0 = observe(model, state0)

    fresh = np.zeros(len(times), bool) if fresh is None else np.asarray(fresh, bool)
    if fresh.shape != times.shape:
        raise ValueError(f"field 'fresh' must have one entry per step ({len(times)}), got shape {fresh.shape}")

    def body(c, xs):
        state, predictor, code, failed_t, r_norm = c
        t, p, retry = xs
        sol, new_state = solve_step(model, state, p, t, newton, ctx,
                                    guess=predictor.guess(state, t - state.time, p, retry=retry))
        alive = code == Result.CONTINUE
        ok = alive & (sol.code == Result.SUCCESS)
        if progress or snapshot is not None:
            jax.lax.cond(ok, lambda: _report(jnp.sum(times <= t), t, sol.iterations, 0, snapshot, model,
                                             new_state), lambda: None)
        code = jnp.where(alive & ~ok, sol.code, code).astype(jnp.int32)
        failed_t = jnp.where(alive & ~ok, t, failed_t)
        row = (ok, new_state.time, new_state.phase, sol.iterations, sol.augmentations, sol.stats,
               observe(model, new_state))
        return (_select(ok, new_state, state), predictor.after(ok, state, new_state), code, failed_t,
                jnp.where(alive, sol.residual_norm, r_norm)), row

    policy = jax.checkpoint_policies.save_only_these_names(SOLUTION_NAME)
    step = jax.checkpoint(body, policy=policy) if checkpoint else body
    init = (state0, _Predictor.empty(state0), jnp.array(Result.CONTINUE, jnp.int32), jnp.array(jnp.nan),
            jnp.array(0.0))
    (state, _, code, failed_t, r_norm), rows = jax.lax.scan(
        step, init, (jnp.asarray(times), jnp.asarray(phases, jnp.int32), jnp.asarray(fresh)))
    ok, t, ph, iters, augs, stats, observed = rows
    n_ok = jnp.sum(ok).astype(jnp.int32)   # a failed step stops the run: the ok steps come first

    def column(first, values):
        first = jnp.asarray(first, values.dtype)
        filled = jnp.where(ok.reshape(ok.shape + (1,) * (values.ndim - 1)), values, jnp.zeros_like(values))
        return jnp.concatenate([first[None], filled])

    hist = History(time=column(0.0, t), phase=column(0, ph.astype(jnp.int32)),
                   newton_iters=column(0, iters.astype(jnp.int32)),
                   cutbacks=column(0, jnp.zeros_like(iters, jnp.int32)),
                   augmentations=column(0, augs.astype(jnp.int32)),
                   solver_stats=column(jnp.zeros(3, jnp.int32), stats.astype(jnp.int32)),
                   observed=jax.tree_util.tree_map(column, row0, observed), n_rows=1 + n_ok)
    code = jnp.where(code == Result.CONTINUE, Result.SUCCESS, code).astype(jnp.int32)
    return Simulation(history=hist, final=state, code=code, failed_time=failed_t, residual_norm=r_norm,
                      pending_cuts=jnp.where(code == Result.SUCCESS, 0, 1).astype(jnp.int32))
