"""The drivers of the load path, run entirely inside JAX.

A load path is a sequence of step attempts (:mod:`jaxfric.loadpath.step`) from the model's initial state
(:mod:`jaxfric.loadpath.model`), each converged step recorded in the history buffers. Three drivers:

- :func:`simulate` (adaptive): a ``lax.while_loop`` over attempts, the step controller of the
  benchmark spec (section 1.9, :mod:`jaxfric.loadpath.controller`) choosing each increment. Differentiable in
  forward mode (``jax.jvp``). :func:`begin` and :func:`advance` run the same loop in chunks of a bounded
  number of accepted steps, returning to the host between them (:func:`jaxfric.loadpath.run.run` does, to
  write results as they come, serve a stop request and save a state to resume from).
- :func:`simulate_flat`: the same attempts and controller, one Newton iteration per loop pass (for
  vmapped sweeps; penalty formulation).
- :func:`simulate_fixed`: a ``lax.scan`` over the nominal steps without cutting: a fixed-length loop,
  so reverse mode (``jax.grad``/``jax.vjp``) works too.

Each step is a Newton solve differentiated by the implicit function theorem, and the converged plastic
history is carried to the next step, so derivatives follow the loading path. Failures are result
codes; :func:`jaxfric.loadpath.run.run` turns them into exceptions. No driver calls the host.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..contact.formulations import StepSolution, from_newton
from ..contact.system import linearize
from ..fem.loading import schedule
from ..numerics.newton import (
    SOLUTION_NAME,
    LinearizedProblem,
    NewtonOptions,
    newton_pass,
    newton_result,
    newton_start,
    with_carry,
)
from ..numerics.results import Result
from .controller import STABILIZE_RISE, Controller, ControllerState, Outcome, StepControl
from .model import SimState, StripModel, default_observe, initial_state, tool_positions
from .step import (
    StepContext,
    continuation_on,
    continuation_stages,
    enhanced_carry,
    softened_args,
    solve_step,
    step_args,
    step_state,
    unknowns,
)
from .step_error import FlowMemory

__all__ = ["History", "Simulation", "LoadPathState", "Chunk", "begin", "advance", "restart", "simulate",
           "simulate_flat", "simulate_fixed", "tangent_anchor"]


class History(eqx.Module):
    """Per-step records in preallocated buffers; rows 0..n_rows-1 are filled (row 0: initial state).

    Attributes:
        time, phase, newton_iters, cutbacks, augmentations: (S,) per row.
        cut_codes: (S,) the result codes of the step's failed attempts as a bit mask: bit k set where
            one ended with Result k (:func:`jaxfric.numerics.results.causes` names them); 0 without cutbacks.
        predicted: (S,) 1 where the step's accepted attempt started from the secant prediction, else 0
            (a retry, a phase's first step, or the prediction withheld: :class:`_Predictor`); a replay of
            the steps (:func:`simulate_fixed`'s ``fresh``) starts the others from the converged state.
        damping_energy: (S,) the energy the stabilisation's damper took in the step (N mm per mm; 0 for
            every step but a stabilised one: :class:`jaxfric.loadpath.controller.StepControl`).
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
    cut_codes: jax.Array
    augmentations: jax.Array
    solver_stats: jax.Array
    predicted: jax.Array
    damping_energy: jax.Array
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


def _select(pred, on_true, on_false):
    return jax.tree_util.tree_map(lambda a, b: jnp.where(pred, a, b), on_true, on_false)


def _buffer(n: int, like):
    """``n`` rows shaped like the pytree ``like``, zero."""
    return jax.tree_util.tree_map(lambda a: jnp.zeros((n,) + jnp.shape(a), jnp.asarray(a).dtype), like)


def _empty_history(n: int, row0: dict, filled: bool = True) -> History:
    """History buffers of ``n`` rows; row 0 holds the initial state's observation ``row0`` when ``filled``
    (a whole run's history), else no row is filled (a chunk's; ``row0`` gives the shapes only)."""
    observed = _buffer(n, row0)
    if filled:
        observed = jax.tree_util.tree_map(lambda b, a: b.at[0].set(a), observed, row0)
    return History(time=jnp.zeros(n), phase=jnp.zeros(n, jnp.int32),
                   newton_iters=jnp.zeros(n, jnp.int32), cutbacks=jnp.zeros(n, jnp.int32),
                   cut_codes=jnp.zeros(n, jnp.int32),
                   augmentations=jnp.zeros(n, jnp.int32), solver_stats=jnp.zeros((n, 3), jnp.int32),
                   predicted=jnp.zeros(n, jnp.int32), damping_energy=jnp.zeros(n), observed=observed,
                   n_rows=jnp.array(1 if filled else 0, jnp.int32))


def _put(buf, row, pred, value):
    """``buf`` with row ``row`` set to ``value`` when ``pred``."""
    return buf.at[row].set(jnp.where(pred, value, buf[row]))


def _record(h: History, row, pred, state: SimState, iters, cuts, cut_codes, augmentations, stats, predicted,
            observed, damping_energy=0.0) -> History:
    """Write row ``row`` when ``pred``; leave the buffers unchanged otherwise."""
    def put(buf, value):
        return _put(buf, row, pred, value)

    return History(time=put(h.time, state.time), phase=put(h.phase, state.phase),
                   newton_iters=put(h.newton_iters, iters), cutbacks=put(h.cutbacks, cuts),
                   cut_codes=put(h.cut_codes, cut_codes),
                   augmentations=put(h.augmentations, augmentations), solver_stats=put(h.solver_stats, stats),
                   predicted=put(h.predicted, jnp.asarray(predicted, jnp.int32)),
                   damping_energy=put(h.damping_energy, jnp.asarray(damping_energy, h.damping_energy.dtype)),
                   observed=jax.tree_util.tree_map(put, h.observed, observed),
                   n_rows=jnp.where(pred, row + 1, h.n_rows))


def tangent_anchor(p) -> jax.Array:
    """-0.0, computed from the parameters ``p`` so that it carries their tangents under ``jax.jvp``:
    added to a loop's initial carry (``anchor`` of :func:`simulate` and :func:`simulate_fixed`), it changes
    no value (x + -0.0 is x for every x, signed zeros included) and makes every floating-point leaf of
    the carry a tangent from the start.

    Why: JAX differentiates a ``while_loop`` or ``scan`` by tracing its body's JVP for the carry leaves
    whose tangents are nonzero, and traces it again, with more of them, until that set no longer
    grows. A load path's initial state does not depend on the parameters (zero displacements, the
    virgin material), its first step makes it depend on them: without the anchor the whole step, its
    exact contact derivative included, is traced twice. With it, once: the Nine's curve program at
    100 x 2 traces in 5.1 to 6.3 s against 8.3 to 9.4 s as a JVP, 7.8 to 8.3 against 14.0 to 14.8 s with
    ``jax.jacfwd``, its Jacobian unchanged (``python experiments/bench_curve_program.py``, docs/results.md,
    identification: the curve's program)."""
    p = jnp.asarray(p)
    return -(0.0 * jnp.sum(jnp.abs(p)))


def _anchored(carry, anchor):
    """``carry`` with ``anchor`` (:func:`tangent_anchor`, or None: unchanged) added to its floating-point
    leaves."""
    if anchor is None:
        return carry
    return jax.tree_util.tree_map(
        lambda a: a + anchor.astype(a.dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, carry)


# ---- drivers --------------------------------------------------------------------------------------

class _Predictor(eqx.Module):
    """Secant predictor: the last accepted increment of displacements and tool positions together
    (so that gaps are extrapolated consistently), scaled to the next step. Not used after a phase
    change, where the loading direction may reverse, nor on a retry after a failed attempt. It only
    moves Newton's starting point, never the solution.

    Where the prediction keeps failing (a thin sheet over a large roller, whose predicted attempts throw
    nodes through the tools), it is withheld: a failed predicted attempt withholds it from the next
    ``span`` accepted steps after its own, ``span`` doubling with every further failure (1, 2, 4, ...,
    ``MAX_HOLD``) and starting again at 1 once a predicted attempt converges. Where prediction works it
    is kept (the ``make run`` case: 811 of its 815 steps predicted); where it never works, one attempt
    in ``MAX_HOLD`` steps fails (docs/results.md, "Extreme cases")."""

    MAX_HOLD = 32

    du: jax.Array      # (n_nodes, 2) displacement increment of the last accepted step
    dq: jax.Array      # (n_tools,) tool position increment of the last accepted step
    dt: jax.Array      # () its pseudo-time increment (0: no prediction)
    hold: jax.Array    # () int32 accepted steps still to start from the converged state
    span: jax.Array    # () int32 the last hold set (0: the last predicted attempt converged)

    @classmethod
    def empty(cls, state: SimState) -> _Predictor:
        return cls(jnp.zeros_like(state.u), jnp.zeros_like(tool_positions(state)), jnp.array(0.0),
                   jnp.array(0, jnp.int32), jnp.array(0, jnp.int32))

    def used(self, state: SimState, phase_next, retry=False) -> jax.Array:
        """Whether an attempt in ``phase_next`` from ``state`` starts from the prediction."""
        return (self.dt > 0) & (phase_next == state.phase) & ~jnp.asarray(retry, bool) & (self.hold == 0)

    def guess(self, state: SimState, dt_next, phase_next, retry=False):
        use = self.used(state, phase_next, retry)
        scale = jnp.where(use, dt_next / jnp.where(use, self.dt, 1.0), 0.0)
        return state.u + scale * self.du, tool_positions(state) + scale * self.dq

    def after(self, ok, old: SimState, new: SimState, predicted=False) -> _Predictor:
        """The predictor after an attempt from ``old`` to ``new``, accepted if ``ok``, that started from
        the prediction if ``predicted``."""
        ok, predicted = jnp.asarray(ok, bool), jnp.asarray(predicted, bool)
        missed = predicted & ~ok
        span = jnp.where(missed, jnp.clip(2 * self.span, 1, self.MAX_HOLD),
                         jnp.where(ok & predicted, 0, self.span)).astype(jnp.int32)
        # The failed step's own acceptance (its retry is not predicted anyway) counts too: hence + 1.
        hold = jnp.where(missed, span + 1, jnp.where(ok, jnp.maximum(self.hold - 1, 0), self.hold))
        return _Predictor(du=jnp.where(ok, new.u - old.u, self.du),
                          dq=jnp.where(ok, tool_positions(new) - tool_positions(old), self.dq),
                          dt=jnp.where(ok, new.time - old.time, self.dt), hold=hold.astype(jnp.int32), span=span)


class LoadPathState(eqx.Module):
    """Where an adaptive load path stands after an accepted step or a failed attempt: everything the
    loop carries from one attempt to the next, so that a run continued from it (:func:`advance`) is the
    run that never stopped, bit for bit.

    Attributes:
        state: the last converged state.
        predictor: the secant predictor (the last accepted increment).
        ctrl: the step controller's state (increment, cuts, result code: ``Result.CONTINUE`` while the
            load path goes on).
        rows: () int32 history rows so far (1 + accepted steps).
        flow: the last accepted step's plastic flow, for the step error estimate
            (:class:`~jaxfric.loadpath.step_error.FlowMemory`; empty unless ``StepControl.step_error``).
    """

    state: SimState
    predictor: _Predictor
    ctrl: ControllerState
    rows: jax.Array
    flow: FlowMemory


class Chunk(eqx.Module):
    """The rows that one :func:`advance` (or :func:`begin`) accepted, in buffers of a fixed size.

    Attributes:
        history: rows 0..history.n_rows-1 are filled; they are the run's history rows
            ``first, first + 1, ...``.
        snapshots: ``snapshot(model, state)`` per filled row (leading axis: buffer row), or None.
        first: () int32 the run's history row of the chunk's row 0.
    """

    history: History
    snapshots: Any
    first: jax.Array


class _Loop(eqx.Module):
    """Carry of the adaptive load loop: where the load path stands, and the buffers of the rows it
    records (a whole run's from row 0, or one chunk's), with the snapshots of a chunk's rows."""

    path: LoadPathState
    history: History
    snapshots: Any = None


def _controller(model: StripModel, control: StepControl, max_rows=None) -> Controller:
    """The step controller of ``model``'s load path, with the continuation where the formulation has
    one and ``control`` asks for it; ``max_rows``: :meth:`Controller.build`'s."""
    on = continuation_on(model, control)
    has_line_search = model.contact is None or not model.tools or model.contact.unsearched_retry
    n_stages = continuation_stages(model) if on else jnp.array(0, jnp.int32)
    # The stabilised attempt (every formulation's residual carries the damper): a sheet modulus scales it.
    modulus = getattr(model.material, "E", None)
    widenable = bool(model.tools) and model.contact is not None and model.contact.widened(model.tools) is not None
    return Controller.build(model.phases, control, on, has_line_search, n_stages, modulus, max_rows, widenable)


def _start(model: StripModel, ctrl: Controller) -> LoadPathState:
    state0 = initial_state(model)
    return LoadPathState(state=state0, predictor=_Predictor.empty(state0),
                         ctrl=ctrl.init(state0.u, tool_positions(state0)), rows=jnp.array(1, jnp.int32),
                         flow=FlowMemory.empty(state0.material, ctrl.control.step_error > 0))


def _init_loop(model: StripModel, ctrl: Controller, observe: Callable) -> _Loop:
    path = _start(model, ctrl)
    return _Loop(path=path, history=_empty_history(ctrl.n_buffer + 1, observe(model, path.state)))


def _next_attempt(ctrl: Controller, p: LoadPathState):
    """The next attempt's target time, phase and Newton starting point (u, q)."""
    t_try, phase = ctrl.target(p.ctrl, p.state.time)
    guess = p.predictor.guess(p.state, t_try - p.state.time, phase, retry=p.ctrl.cuts > 0)
    return t_try, phase, ctrl.start(p.ctrl, guess)


def _damping(ctrl: Controller, p: LoadPathState):
    """The next attempt's damper (:class:`StepControl`, ``stabilize``): eta or STABILIZE_RISE eta in the
    stabilised attempts, 0 in the others; None where the run has none (no such term in the program)."""
    if not ctrl.stabilized:
        return None
    return jnp.select([p.ctrl.damped == 1, p.ctrl.damped == 2], [ctrl.eta, STABILIZE_RISE * ctrl.eta], 0.0)


def _after_attempt(model: StripModel, ctrl: Controller, c: _Loop, sol: StepSolution, new_state: SimState, t_try,
                   observe: Callable, fixed, weight, snapshot: Callable | None = None) -> _Loop:
    """The loop after an attempt: the step recorded (with its snapshot, in a chunk) if accepted, the
    controller adapted. ``fixed``: the prescribed dofs of the attempt's phase (the damper's energy is
    taken over the others); ``weight``: (n_el, gp) the points' reference areas (the step error's)."""
    p = c.path
    energy = jnp.zeros(())
    if ctrl.stabilized:
        du = (new_state.u - p.state.u).reshape(-1)
        energy = _damping(ctrl, p) * jnp.sum(jnp.where(fixed, 0.0, du**2))
    predicted = p.predictor.used(p.state, new_state.phase, retry=p.ctrl.cuts > 0)
    error, flow = jnp.array(-1.0), p.flow
    if p.flow.on:
        error, increment = p.flow.estimate(weight, model.material, p.state, new_state)
    out = Outcome(sol.code, sol.iterations, sol.hardest, sol.stats, sol.residual_norm, new_state.u,
                  tool_positions(new_state), predicted, error)
    ok, iters, stats = ctrl.tally(p.ctrl, out)
    if p.flow.on:
        flow = p.flow.after(ok, p.state, new_state, increment)
    slot = c.history.n_rows
    history = _record(c.history, slot, ok, new_state, iters, p.ctrl.cuts, p.ctrl.cut_codes, sol.augmentations, stats,
                      predicted, observe(model, new_state), energy)
    snapshots = c.snapshots
    if snapshot is not None:
        snapshots = jax.tree_util.tree_map(lambda b, v: _put(b, slot, ok, v), snapshots, snapshot(model, new_state))
    path = LoadPathState(state=_select(ok, new_state, p.state),
                         predictor=p.predictor.after(ok, p.state, new_state, predicted),
                         ctrl=ctrl.adapt(p.ctrl, p.state.time, t_try, out, p.rows),
                         rows=p.rows + ok.astype(jnp.int32), flow=flow)
    return _Loop(path=path, history=history, snapshots=snapshots)


def _simulation(out: _Loop) -> Simulation:
    p = out.path
    return Simulation(history=out.history, final=p.state, code=p.ctrl.code, failed_time=p.ctrl.failed_t,
                      residual_norm=p.ctrl.r_norm, pending_cuts=p.ctrl.cuts)


def _attempt_body(model: StripModel, ctrl: Controller, newton: NewtonOptions, ctx: StepContext, observe: Callable,
                  snapshot: Callable | None):
    """One pass of the adaptive loop: an attempt from where the load path stands, then its outcome."""
    def body(c: _Loop) -> _Loop:
        p = c.path
        t_try, phase, guess = _next_attempt(ctrl, p)
        sol, new_state = solve_step(model, p.state, phase, t_try, newton, ctx, guess=guess, search=~p.ctrl.plain,
                                    soften=p.ctrl.stages.soft if ctrl.continuation else None,
                                    damping=_damping(ctrl, p))
        return _after_attempt(model, ctrl, c, sol, new_state, t_try, observe, ctx.masks[phase], ctx.geo.weight,
                              snapshot)

    return body


def simulate(model: StripModel, *, newton: NewtonOptions = NewtonOptions(),
             control: StepControl = StepControl(), observe: Callable = default_observe,
             anchor: jax.Array | None = None) -> Simulation:
    """Run the whole load path with adaptive steps, inside one ``lax.while_loop``.

    Pure and jit-able (wrap with ``eqx.filter_jit``); ``observe(model, state) -> pytree`` is recorded at
    every accepted step and must be a static (hashable) function. :func:`begin` and :func:`advance` run
    the same attempts in chunks. The history buffer holds ``control.max_steps`` rows; with the model an
    argument of the compiled function (its increments then traced), give ``max_steps``: its default
    counts the nominal steps, which needs their values. ``anchor``: :func:`tangent_anchor` of the
    parameters that forward mode differentiates, or None (no effect on the values).
    """
    ctx = StepContext.build(model)
    ctrl = _controller(model, control)
    body = _attempt_body(model, ctrl, newton, ctx, observe, None)
    init = _anchored(_init_loop(model, ctrl, observe), anchor)
    out = jax.lax.while_loop(lambda c: c.path.ctrl.code == Result.CONTINUE, body, init)
    return _simulation(out)


def begin(model: StripModel, *, control: StepControl = StepControl(), observe: Callable = default_observe,
          snapshot: Callable | None = None, max_steps=None) -> tuple[LoadPathState, Chunk]:
    """The start of ``model``'s adaptive load path, and its history row 0 (the initial state's
    observation and, with ``snapshot``, its snapshot) as a chunk of one row. Jit-able; ``max_steps``:
    as for :func:`advance`."""
    ctrl = _controller(model, control, max_steps)
    path = _start(model, ctrl)
    history = _empty_history(1, observe(model, path.state))
    snapshots = None if snapshot is None else jax.tree_util.tree_map(lambda a: a[None], snapshot(model, path.state))
    return path, Chunk(history=history, snapshots=snapshots, first=jnp.array(0, jnp.int32))


def advance(model: StripModel, path: LoadPathState, limit, *, size: int, newton: NewtonOptions = NewtonOptions(),
            control: StepControl = StepControl(), observe: Callable = default_observe,
            snapshot: Callable | None = None, max_steps=None) -> tuple[LoadPathState, Chunk]:
    """Continue the adaptive load path from ``path`` by at most ``limit`` accepted steps.

    The attempts are those of :func:`simulate`, whatever the chunks: a load path advanced in chunks
    from :func:`begin` ends where :func:`simulate` ends, and one continued from a saved
    :class:`LoadPathState` where the uninterrupted one does. Jit-able, with ``limit`` a traced () int
    (1 <= limit <= size) so that chunks of any length share one program.

    Args:
        model: the model whose load path ``path`` is.
        path: where the load path stands (from :func:`begin` or a previous :func:`advance`).
        limit: the most accepted steps in this chunk.
        size: static, rows of the chunk's buffers (the largest ``limit``).
        newton, control, observe: as for :func:`simulate`.
        snapshot: static ``snapshot(model, state) -> pytree`` kept per accepted step, or None.
        max_steps: the run's most accepted steps, may be traced (:func:`jaxfric.loadpath.run.run`
            passes it as data, so that one program serves every ``StepControl.max_steps`` and every
            nominal increment); None: ``control``'s
            (:func:`~jaxfric.loadpath.controller.max_steps`).

    Returns:
        ``(path, chunk)``: where the load path stands after the chunk (``path.ctrl.code`` is
        ``Result.CONTINUE`` until the load path ends or fails) and the rows it accepted.
    """
    ctx = StepContext.build(model)
    ctrl = _controller(model, control, max_steps)
    body = _attempt_body(model, ctrl, newton, ctx, observe, snapshot)
    history = _empty_history(size, observe(model, path.state), filled=False)
    snapshots = None if snapshot is None else _buffer(size, snapshot(model, path.state))
    limit = jnp.clip(jnp.asarray(limit, jnp.int32), 1, size)

    def more(c: _Loop):
        return (c.path.ctrl.code == Result.CONTINUE) & (c.history.n_rows < limit)

    out = jax.lax.while_loop(more, body, _Loop(path=path, history=history, snapshots=snapshots))
    return out.path, Chunk(history=out.history, snapshots=out.snapshots, first=path.rows)


def restart(model: StripModel, path: LoadPathState, time, *, control: StepControl = StepControl()) -> LoadPathState:
    """``path``'s converged state at pseudo-time ``time`` of ``model``'s load path, with the step controller
    started afresh there: the nominal increment of the schedule segment that ``time`` opens or lies in, no
    cut, no secant prediction. This is how a run continues on a changed schedule (a longer last phase:
    :func:`jaxfric.loadpath.run.extend_stroke`), where the controller's increments of the old one mean
    other displacements. Jit-able."""
    ctrl = _controller(model, control)
    state = path.state
    time = jnp.asarray(time, state.time.dtype)
    seg = jnp.minimum(jnp.searchsorted(ctrl.seg_end, time, side="right"), ctrl.seg_end.shape[0] - 1)
    fresh = ctrl.init(state.u, tool_positions(state))
    fresh = eqx.tree_at(lambda c: (c.seg, c.dt), fresh, (seg.astype(jnp.int32), ctrl.seg_dt[seg]))
    state = eqx.tree_at(lambda s: s.time, state, time)
    return LoadPathState(state=state, predictor=_Predictor.empty(state), ctrl=fresh, rows=path.rows,
                         flow=FlowMemory.empty(state.material, ctrl.control.step_error > 0))


def simulate_flat(model: StripModel, *, newton: NewtonOptions = NewtonOptions(),
                  control: StepControl = StepControl(), observe: Callable = default_observe) -> Simulation:
    """:func:`simulate` with one Newton iteration per pass of a single loop (penalty law only).

    The results are those of :func:`simulate` (the same attempts, iterations and step controller);
    only the loop structure differs: instead of a loop of attempts, each a Newton loop, one loop
    advances the current attempt by one Newton iteration and, when the attempt ends, runs the step
    controller and starts the next attempt. Under ``vmap`` (:func:`jaxfric.loadpath.sweep.sweep`) a member then
    waits for no other member's attempt: the sweep takes as many passes as its largest member's total
    of Newton iterations and attempts, against the sum over attempts of the slowest member's
    iterations with the nested loops (a batched pass itself still costs more than a single one:
    ``docs/results.md``, batched sweeps). Forward only (derivatives: :func:`simulate`,
    whose steps are differentiated by the implicit function theorem).
    """
    if model.tools and model.contact is not None and not model.contact.one_newton_solve:
        raise ValueError(f"field 'contact': simulate_flat runs formulations whose step is one Newton solve "
                         f"(the penalty law), not {type(model.contact).__name__} (a loop of its own inside a step)")
    ctx = StepContext.build(model)
    ctrl = _controller(model, control)
    init = _init_loop(model, ctrl, observe)

    def attempt(c: _Loop):
        """The next attempt of ``c``: its target time, phase and Newton start."""
        t_try, phase, guess = _next_attempt(ctrl, c.path)
        start = with_carry(args0, enhanced_carry(model, c.path.state))   # args0: shapes only, and the carry
        return t_try, phase, newton_start(problem0, unknowns(model, *guess), start, newton)

    def body(carry):
        c, t_try, phase, nc = carry
        p = c.path
        args, q_start, f_start = step_args(model, p.state, phase, t_try, ctx, _damping(ctrl, p))
        soft = p.ctrl.stages.soft
        if ctrl.continuation:
            args = softened_args(args, jnp.maximum(soft, 0))
        x_ref = unknowns(model, p.state.u, tool_positions(p.state))
        problem = LinearizedProblem(linearize, positions=(soft >= 0) if ctrl.continuation else False)
        nc = newton_pass(nc, args, x_ref, problem, newton, search=~p.ctrl.plain)
        done = nc.code != Result.CONTINUE
        sol = from_newton(newton_result(nc, problem, args))
        new_state = step_state(model, args, sol, t_try, phase, q_start, f_start)
        c = _select(done, _after_attempt(model, ctrl, c, sol, new_state, t_try, observe, ctx.masks[phase],
                                         ctx.geo.weight), c)
        return _select(done, (c,) + attempt(c), (c, t_try, phase, nc))

    t0, phase0, guess0 = _next_attempt(ctrl, init.path)
    args0, _, _ = step_args(model, init.path.state, phase0, t0, ctx, _damping(ctrl, init.path))
    problem0 = LinearizedProblem(linearize)
    carry = (init, t0, phase0, newton_start(problem0, unknowns(model, *guess0), args0, newton))
    out = jax.lax.while_loop(lambda carry: carry[0].path.ctrl.code == Result.CONTINUE, body, carry)[0]
    return _simulation(out)


def simulate_fixed(model: StripModel, *, newton: NewtonOptions = NewtonOptions(),
                   observe: Callable = default_observe, checkpoint: bool = True, fresh=None,
                   anchor: jax.Array | None = None) -> Simulation:
    """Run the nominal steps of the load path in a fixed-length ``lax.scan`` (no step cutting).

    Reverse-mode differentiable. If a step fails the state stays at the last converged step, the
    remaining rows are not filled and ``code`` holds the failure.

    ``fresh``: optional (n_steps,) booleans, known at trace time: the steps whose Newton iterations
    start from the last converged state instead of the secant prediction. Replaying the accepted steps
    of an adaptive run (:func:`jaxfric.fem.loading.with_steps`), the steps whose history row has
    ``predicted`` 0 (retries, steps whose prediction was withheld) started so; marking them reproduces
    the adaptive run's iterations exactly.

    Memory of reverse mode: the history rows are scan outputs, not a carried buffer, so a step's carry
    is the converged state alone (displacements, tool positions, material and contact state). With
    ``checkpoint`` (default) every step is rematerialised in the backward pass (``jax.checkpoint``):
    the forward pass keeps only the carry at each step and its converged solution (named
    ``SOLUTION_NAME``), and the backward pass rebuilds one step at a time from them by one
    linearisation, without re-running Newton, so the memory grows as n_steps x state size, whatever
    the cost of a step's linearisation and factorisation. Without it every step's Newton residuals and factors are
    kept (n_steps x step intermediates), several times more; the factor is measured by
    ``experiments/bench_grad_memory.py``. Forward mode (``jax.jvp``) is unaffected. ``anchor``: as for
    :func:`simulate`.
    """
    times, phases = schedule(model.phases).nominal_steps()
    ctx = StepContext.build(model)
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
        code = jnp.where(alive & ~ok, sol.code, code).astype(jnp.int32)
        failed_t = jnp.where(alive & ~ok, t, failed_t)
        row = (ok, new_state.time, new_state.phase, sol.iterations, sol.augmentations, sol.stats,
               predictor.used(state, p, retry), observe(model, new_state))
        return (_select(ok, new_state, state), predictor.after(ok, state, new_state), code, failed_t,
                jnp.where(alive, sol.residual_norm, r_norm)), row

    policy = jax.checkpoint_policies.save_only_these_names(SOLUTION_NAME)
    step = jax.checkpoint(body, policy=policy) if checkpoint else body
    init = _anchored((state0, _Predictor.empty(state0), jnp.array(Result.CONTINUE, jnp.int32), jnp.array(jnp.nan),
                      jnp.array(0.0)), anchor)
    (state, _, code, failed_t, r_norm), rows = jax.lax.scan(
        step, init, (jnp.asarray(times), jnp.asarray(phases, jnp.int32), jnp.asarray(fresh)))
    ok, t, ph, iters, augs, stats, predicted, observed = rows
    n_ok = jnp.sum(ok).astype(jnp.int32)   # a failed step stops the run: the ok steps come first

    def column(first, values):
        first = jnp.asarray(first, values.dtype)
        filled = jnp.where(ok.reshape(ok.shape + (1,) * (values.ndim - 1)), values, jnp.zeros_like(values))
        return jnp.concatenate([first[None], filled])

    hist = History(time=column(0.0, t), phase=column(0, ph.astype(jnp.int32)),
                   newton_iters=column(0, iters.astype(jnp.int32)),
                   cutbacks=column(0, jnp.zeros_like(iters, jnp.int32)),
                   cut_codes=column(0, jnp.zeros_like(iters, jnp.int32)),
                   augmentations=column(0, augs.astype(jnp.int32)),
                   solver_stats=column(jnp.zeros(3, jnp.int32), stats.astype(jnp.int32)),
                   predicted=column(0, predicted.astype(jnp.int32)),
                   damping_energy=column(0.0, jnp.zeros_like(t)),
                   observed=jax.tree_util.tree_map(column, row0, observed), n_rows=1 + n_ok)
    code = jnp.where(code == Result.CONTINUE, Result.SUCCESS, code).astype(jnp.int32)
    return Simulation(history=hist, final=state, code=code, failed_time=failed_t, residual_norm=r_norm,
                      pending_cuts=jnp.where(code == Result.SUCCESS, 0, 1).astype(jnp.int32))
