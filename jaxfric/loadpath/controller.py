"""The adaptive step controller of the load loop (benchmarks spec section 1.9).

The controller decides, from the outcome of each step attempt, the next attempt's increment and how it
is made. :class:`StepControl` holds its settings; :class:`Controller` is built once per run from the
model's schedule and applies them: :meth:`Controller.init` gives the first :class:`ControllerState`,
:meth:`Controller.target` the next attempt's pseudo-time and phase, :meth:`Controller.adapt` the state
after an attempt. The rules it applies, in order, each a function below:

- an accepted step keeps its increment, grows it by ``growth`` after ``easy_steps`` easy steps, or
  takes the next schedule segment's (:func:`increment_after_acceptance`); with ``step_error`` the
  increment follows the step's error estimate instead (:func:`increment_from_error`);
- a failed first attempt that started from the secant prediction is tried once more at the same
  increment from the converged state, and so is any failed first attempt at the floor below
  (:func:`retry_from_converged`);
- a failed attempt halves the increment, down to nominal / 2**max_cuts;
- then, for a formulation that has one, the continuation's stages of softened penalties
  (:func:`continuation_rule`);
- then one last attempt with Newton's line search off, for a formulation whose Newton loop has one
  (:func:`unsearched_attempt`);
- then, for a formulation that has one, the stabilised attempt (:func:`stabilised_attempt`);
- then the run stops with the code of the last attempt made with the line search (:func:`stop_code`);
- apart from these, an attempt that ends outside exact contact's proximity band ends the program with
  ``Result.BAND_FULL``, for the chunked driver to widen the band (:func:`band_full`).
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from ..fem.loading import schedule
from ..numerics._checks import check_int, check_nonnegative, is_concrete
from ..numerics.results import Result

__all__ = ["StepControl", "Controller", "ControllerState", "ContinuationState", "Outcome", "Tally",
           "increment_after_acceptance", "increment_from_error", "retry_from_converged", "unsearched_attempt",
           "continuation_rule", "max_steps", "band_full",
           "stabilised_attempt", "stop_code", "STABILIZE", "STABILIZE_RISE"]


#: The default first damper of the stabilised attempts, in multiples of the sheet's Young's modulus
#: (:class:`StepControl`, ``stabilize``).
STABILIZE = 1e-5

#: The second stabilised attempt's damper, in multiples of the first's (:class:`StepControl`, ``stabilize``).
STABILIZE_RISE = 100.0

#: Consecutive steps accepted at the smallest increment after failed attempts, after which a run stops as
#: stalled (:class:`StepControl`, ``stall_steps``).
STALL_STEPS = 200

#: Increments chosen by the error estimate (:func:`increment_from_error`): the largest, in multiples of the
#: segment's nominal increment (beyond it a step of the benchmarks' drawing passes several element lengths
#: of strip over a tool and Newton's iterations grow: docs/results.md, iterations against increments), the
#: safety factor on tol / eta, and the range of one change of the increment.
ERROR_MAX_INCREMENT = 4.0
ERROR_SAFETY = 0.9
ERROR_FACTORS = (0.5, 2.0)


class StepControl(eqx.Module):
    """Step controller settings (static).

    Attributes:
        max_cuts: an attempt below nominal / 2**max_cuts stops the run. (A failed first attempt
            that started from the secant prediction, and any at the smallest increment, is retried once
            at its increment from the converged state; at the smallest increment the increment then gets
            one last attempt with Newton's line search off, before the run stops.)
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
            gaps are computed (:mod:`jaxfric.numerics.newton`): a looser test, used only where the step would
            otherwise stop the run. The stages count as attempts in the step's ``cutbacks``.
            Reason: at a stiff penalty a pair touching a curved tool can 2-cycle between open (the
            free node driven into the tool) and closed at a spurious force whose geometric stiffness
            throws it out again; from the softer problem's solution it arrives closed with about its
            true force (``tests/test_extreme.py::test_nine_edges``, eps_n 1e9). The derivative of a step is
            that of its converged solution; a fixed-step replay (:func:`jaxfric.loadpath.simulate.simulate_fixed`)
            has no stages, so it fails at a step the adaptive run accepted only after them.
        stabilize: the stabilised attempts' first damper, eta = stabilize E (E: the sheet's Young's
            modulus; 0: no such attempt). A step that the unsearched attempt did not take either is
            solved once more at the smallest increment with R_u = f_int - f_c + eta (u - u_n) on the
            free dofs (u_n: the converged displacements), a damper on every node that resists the
            step's increment, and accepted when that converges; where it does not, once more with
            ``STABILIZE_RISE`` times that eta. The damper gives a near-mechanism (the slipping pairs
            and plastic hinges of a sheet leaving a mode without stiffness, a thin sheet without
            tension in a free span) stiffness in that mode. The accepted step is the damped problem's
            solution, off equilibrium by eta |u - u_n| at each free dof; the energy the damper takes,
            eta |u - u_n|^2 over the free dofs (a backward-Euler dashpot), is recorded per step
            (history ``damping_energy``) and reported beside the drawing force's work. Reason: the
            bead with mu = 1.0 on its roller and clamp dies (penalty law) stopped in draw on a step no
            increment took, its Newton iterations crawling while the 16 slipping pairs at the clamp's
            exit switch together between stick and slip; with eta = 1 N/mm per mm (5e-6 E) that step
            converges in 5 iterations, the damper's largest force 3e-4 N/mm. Later steps need more:
            with 1e-5 E alone the run stops again 2 steps on, with 1e-3 E it finishes. The smaller damper is
            tried first because the damped step is off equilibrium by eta |u - u_n|: on a sheet drawn at
            almost no force a damper of 1e-3 E from the start carries the drawing force itself
            (``tests/test_extreme.py::test_bead_edges``). Exact contact solves the damped equilibrium
            likewise (:mod:`jaxfric.contact.exact_iterate`): without it the blankholder's 12 mm bead (shape6)
            held at half depth stops at U = 50.2 mm, where a node of the sheet pressed into the groove has a
            negative stiffness along its tool's normal once its neighbours' statuses are fixed, so that
            closed it pulls (-2.3e-3 N/mm) and open it penetrates (1.6e-5 mm): the linearised
            complementarity problem has no solution there, the semismooth active set cycles through four
            states in every iteration, and Newton with Lemke's pivoting stalls at a residual of 1.6e-4
            N/mm (60 iterations at the smallest increment, either solver). With eta = 1e-5 E (0.71 N/mm per
            mm) the first active set settles at once; restarted from its last converged step the run finishes
            its 58 mm with 13 steps stabilised,
            the damper taking 5e-5 N mm/mm. A fixed-step replay
            (:func:`jaxfric.loadpath.simulate.simulate_fixed`) has no damper.
        stall_steps: a run whose last ``stall_steps`` accepted steps each took the smallest increment
            (nominal / 2**max_cuts) after failed attempts stops with ``Result.STALLED``, its results kept.
            Reason: where no increment converges but the stabilised attempt does, every step takes the
            smallest increment, and it never grows back (a step is easy only in few iterations): the
            blankholder's shape1 bead held at 4.5 mm with a pressure-dependent friction law whose
            bound mu(p) p falls with the pressure (exact contact, F-bar 2 x 2) drew at 1/1024 of the
            nominal increment, 2.8e-6 of pseudo-time per step at 129 to 133 Newton iterations and 0.4 s
            each, and would have filled its history buffer (5,000 rows) after about half an hour; it now
            stops after step 346, in 80 s. The runs that need the stabilised attempt but get through
            finish as before (``tests/test_extreme.py``: the bead with mu = 1 on roller and clamp dies,
            53 of 153 steps stabilised). A stalled run
            says so at once, so that a caller can take another algorithm (the bead card falls back to the
            penalty law).
        step_error: 0 (default): the nominal increments, cut and grown as above. > 0: the increments
            follow the estimate of each step's time-discretisation error (:mod:`jaxfric.loadpath.step_error`:
            eta, the relative error of the step's plastic work) with this target: the next increment is
            the last one times 0.9 step_error / eta, within 1/2 and 2 times it (growing only after
            ``easy_steps`` easy steps, as with ``growth``), at most ``ERROR_MAX_INCREMENT`` times the
            nominal one. Converged steps are never rejected for their estimate (a predictive controller:
            the direction's change is known only once the step has converged, and a rejected step would
            cost its iterations again); Newton's failures still cut the increment. On the Nine's draw the
            increments it chooses cost 1.0 to 1.35 times the Newton iterations of fixed increments of the
            same error (``experiments/step_error_control.py``): there the step error per millimetre drawn
            is the same at every step, so uniform increments are already the best spread; what it adds is
            the choice of their size from a tolerance.
    """

    max_cuts: int = eqx.field(static=True, default=10)
    growth: float = eqx.field(static=True, default=1.5)
    easy_iterations: int = eqx.field(static=True, default=6)
    easy_steps: int = eqx.field(static=True, default=2)
    max_steps: int | None = eqx.field(static=True, default=None)
    continuation: bool = eqx.field(static=True, default=True)
    stabilize: float = eqx.field(static=True, default=STABILIZE)
    step_error: float = eqx.field(static=True, default=0.0)
    stall_steps: int = eqx.field(static=True, default=STALL_STEPS)

    def __check_init__(self):
        check_int("max_cuts", self.max_cuts, 0, 60)
        check_int("stall_steps", self.stall_steps, 1)
        check_nonnegative("stabilize", self.stabilize)
        check_nonnegative("step_error", self.step_error)
        if not isinstance(self.continuation, bool):
            raise ValueError(f"field 'continuation' must be True or False, got {self.continuation!r}")
        check_int("easy_iterations", self.easy_iterations, 1)
        check_int("easy_steps", self.easy_steps, 1)
        check_int("max_steps", self.max_steps, 1, 10_000_000, optional=True)
        check_nonnegative("growth", self.growth)
        if not self.growth >= 1.0:
            raise ValueError(f"field 'growth' must be a finite number >= 1, got {self.growth!r}")


class ContinuationState(eqx.Module):
    """The continuation's progress on the pending step (placeholders when the run has none)."""

    soft: jax.Array    # () int32: continuation stage of the next attempt (penalties / 10^soft); -1: none
    tried: jax.Array   # () the continuation has failed for the pending step
    u: jax.Array       # (n_nodes, 2) the last stage's solution: the next stage's start ...
    q: jax.Array       # (n_tools,) ... with these tool positions
    staged: jax.Array  # () u / q hold a stage's solution


class ControllerState(eqx.Module):
    """What the controller carries between attempts."""

    dt: jax.Array          # () current increment (pseudo-time)
    seg: jax.Array         # () current schedule segment
    n_easy: jax.Array      # () consecutive easy steps
    cuts: jax.Array        # () failed attempts since the last accepted step
    cut_codes: jax.Array   # () int32, their result codes: bit k set where one ended with Result k (cause_mask)
    iters: jax.Array       # () Newton iterations since the last accepted step
    stats: jax.Array       # (3,) exact-contact solver counts since the last accepted step
    code: jax.Array        # () Result: CONTINUE while the run goes on
    failed_t: jax.Array    # () target time of the last failed attempt
    r_norm: jax.Array      # () residual norm of the last attempt
    plain: jax.Array       # () the next attempt runs Newton without the line search
    last_code: jax.Array   # () result code of the last attempt
    stages: ContinuationState
    damped: jax.Array      # () int32: the next attempt's damper, 0 (none), 1 (eta), 2 (STABILIZE_RISE eta)
    n_crawl: jax.Array     # () int32: consecutive accepted steps at the smallest increment after failed attempts


def cause_mask(code):
    """The bit of result ``code`` in ``ControllerState.cut_codes`` and the history's ``cut_codes``: 1 << code
    (0 for the internal codes below 0); :func:`jaxfric.numerics.results.causes` reads a mask back."""
    code = jnp.asarray(code, jnp.int32)
    return jnp.where(code >= 0, jnp.left_shift(jnp.int32(1), jnp.maximum(code, 0)), 0)


class Outcome(NamedTuple):
    """What the controller reads of a step attempt (a :class:`jaxfric.contact.formulations.StepSolution` and
    the state it stands for)."""

    code: jax.Array
    iterations: jax.Array
    hardest: jax.Array | None
    stats: jax.Array
    residual_norm: jax.Array
    u: jax.Array            # the attempt's displacements (a continuation stage's start)
    q: jax.Array            # and tool positions
    predicted: jax.Array | bool = False   # () the attempt started from the secant prediction
    error: jax.Array | float = -1.0       # () the step's error estimate eta (StepControl.step_error); -1: none


class Tally(NamedTuple):
    """An attempt as the step's history row counts it (:meth:`Controller.tally`)."""

    accepted: jax.Array
    iterations: jax.Array   # Newton iterations of the step's attempts so far, this one included
    stats: jax.Array        # the formulation's solver counts, likewise


def increment_after_acceptance(control: StepControl, ok, n_easy, hardest, dt, dt_nominal, dt_next_segment,
                               segment_done):
    """Rule: an accepted step's successor keeps its increment, grows it by ``growth`` (at most to the
    nominal one) after ``easy_steps`` consecutive easy steps, or takes the next segment's nominal
    increment when the step ended its segment. "Easy" counts the iterations of one Newton solve, as
    the iteration limit does (``hardest``: an AL step of several augmentations is easy when each of its
    solves is; with the step's total, the increment would never grow back after a cut).

    Returns (n_easy, grow, dt) of the successor."""
    n_easy = jnp.where(ok & (hardest <= control.easy_iterations), n_easy + 1, 0)
    grow = n_easy >= control.easy_steps
    dt_ok = jnp.where(segment_done, dt_next_segment,
                      jnp.where(grow, jnp.minimum(control.growth * dt, dt_nominal), dt))
    return n_easy, grow, dt_ok


def increment_from_error(control: StepControl, error, grow, dt, dt_nominal):
    """Rule (``step_error`` > 0): an accepted step's successor takes dt 0.9 tol / eta, within 1/2 and 2
    times dt, at most ``ERROR_MAX_INCREMENT`` times the nominal increment and at least the smallest
    (nominal / 2**max_cuts). It grows only where :func:`increment_after_acceptance` would grow it
    (``grow``: ``easy_steps`` easy steps), so that an increment cut by Newton's failures does not double
    back at once into the same failure. Where ``error`` < 0 (no estimate) the caller keeps
    :func:`increment_after_acceptance`'s increment. eta is about proportional to dt (the flow
    direction's change over the step), so the correction aims it at tol; where eta jumps (on the Nine,
    each time a node reaches a tool) the increments swing by factors of 2 to 4."""
    low, high = ERROR_FACTORS
    factor = jnp.clip(ERROR_SAFETY * control.step_error / jnp.maximum(error, 1e-300), low, high)
    factor = jnp.where(grow, factor, jnp.minimum(factor, 1.0))
    floor = dt_nominal / 2.0**control.max_cuts
    return jnp.clip(factor * dt, floor, ERROR_MAX_INCREMENT * dt_nominal)


def retry_from_converged(failed, at_floor, cuts, predicted):
    """Rule: a step's first attempt that failed is tried once more at the same increment from the
    converged state where it started from the secant prediction, and at the smallest increment in any
    case. Reason: the prediction can be what fails. It extrapolates every node's last increment, so a
    node moving towards a tool is carried into it; where the sheet around it is compliant (a thin sheet,
    a free span) Newton's first correction from there throws nodes millimetres into the tools, while
    the same increment from the converged state converges in a few iterations (the bead with a 0.7 mm
    strip over a 35 mm roller: 25 iterations and a failure against 4, at 0.036 degrees of wind; halving
    instead kept its steps at 1/100 of the nominal increment until the history buffer was full). The
    spec's controller (benchmarks spec 1.9) starts every attempt from the converged state: the retry is
    its attempt, and the predicted one comes before it."""
    return failed & (cuts == 0) & (at_floor | predicted)


def unsearched_attempt(at_floor, again, plain, has_line_search: bool):
    """Rule: after the retry, the increment gets one last attempt with Newton's line search off. The
    line search rejects every step that raises the residual norm; where a front of pairs switches
    between stick and slip each full step raises it a little on the way to convergence, and the
    backtracked steps crawl. A formulation without a line search to switch off has no such attempt."""
    return at_floor & ~again & ~plain & has_line_search


def continuation_rule(stages: ContinuationState, n_stages, at_floor, again, plain, converged, ok, u, q):
    """Rule: before the unsearched attempt, the continuation's stages (:class:`StepControl`), each from
    the last one's solution; a converged stage before the last gives the next stage's start, not a step;
    a stage that fails ends the continuation for this step.

    Returns (the next attempt's stages, start (a first stage begins), stage_done, held: the attempt was
    a stage that does not end the step, whose residual and code are not reported)."""
    stage_done = converged & (stages.soft > 0)
    start = at_floor & ~again & ~plain & (stages.soft < 0) & ~stages.tried & (n_stages > 0)
    failed = (stages.soft >= 0) & ~converged
    held = (stages.soft >= 0) & ~ok
    soft = jnp.where(start, n_stages, jnp.where(stage_done, stages.soft - 1, -1)).astype(jnp.int32)
    new = ContinuationState(soft=soft, tried=~ok & (stages.tried | failed),
                            u=jnp.where(stage_done, u, stages.u), q=jnp.where(stage_done, q, stages.q),
                            staged=stage_done)
    return new, start, stage_done, held


def stabilised_attempt(stopping, damped, has_damper: bool):
    """Rule: where the run would stop (the increment at its floor, every attempt above made), the step
    gets an attempt with the damper of :class:`StepControl` (``stabilize``), where the formulation has one
    and it is switched on; where that fails, one with ``STABILIZE_RISE`` times the damper; after it,
    nothing. ``damped``: the failed attempt's damper level (0: none). Returns the next attempt's level
    (0: the run stops)."""
    more = stopping & (damped < 2) & has_damper
    return jnp.where(more, damped + 1, 0).astype(jnp.int32)


def crawl_count(control: StepControl, ok, cuts, n_crawl, dt, dt_nominal):
    """Rule: the consecutive accepted steps taken at the smallest increment (nominal / 2**max_cuts) after
    failed attempts (``cuts``), counted up to this attempt (``dt``: its increment), which a failed attempt
    leaves as it is. ``stall_steps`` of them stop the run (:class:`StepControl`)."""
    crawl = (cuts > 0) & (dt <= dt_nominal / 2.0**control.max_cuts * (1.0 + 1e-9))
    return jnp.where(ok, jnp.where(crawl, n_crawl + 1, 0), n_crawl).astype(jnp.int32)


def band_full(failed_code, widenable: bool):
    """Rule: a step's attempt that ends with ``Result.CONTACT_BAND`` (a candidate node outside exact
    contact's proximity band penetrates its tool at the converged iterate) ends the program with
    ``Result.BAND_FULL``, the step still pending at that attempt's increment, where the band can grow
    (``widenable``: static, a band smaller than the candidates). The chunked driver
    (:func:`jaxfric.loadpath.run.run`) then widens the band and the step is tried again.
    Reason: such an attempt shows the contact zone at a converged state reaching beyond the band, and a
    band too narrow costs more than a wide one. On the blankholder's long lands (``python
    experiments/lemke_band.py``, a 3 mm pull) about 200 pairs close in the draw against 256 band nodes:
    the open nodes outside the band enter a tool at Newton iterates and join the band at the next, 22
    iterations a step. Widened at the first such attempt, shape2 and shape4 take ``lcp_ssn``'s steps and
    end within 4.2e-9 of its force; widened at a second attempt of one step, shape2's band never grew (the
    retry took each step) and it took 76 steps for 30, 0.18 % off at the end. Cutting the increment
    does not shrink the zone."""
    return widenable & (failed_code == Result.CONTACT_BAND)


def stop_code(too_small, finished, full, plain, last_code, code, stalled=False):
    """The run's code after an attempt: the failure when no rule gives another attempt (that of the
    last attempt made with the line search, when the unsearched one failed too: a plain Newton that
    strays ends in whatever it met first), SUCCESS at the end of the load path, MAX_STEPS when the
    history buffer is full, STALLED after ``stall_steps`` crawling steps (:func:`crawl_count`), CONTINUE
    otherwise."""
    return jnp.select([too_small, finished, full, stalled],
                      [jnp.where(plain, last_code, code), Result.SUCCESS, Result.MAX_STEPS, Result.STALLED],
                      Result.CONTINUE).astype(jnp.int32)


def max_steps(control: StepControl, phases) -> int:
    """The most accepted steps of a run: ``control.max_steps``, by default 10x the phases' nominal steps
    + 100, which needs the increments' values.

    Raises:
        ValueError: no ``max_steps`` and the increments traced (the model an argument of a compiled
            function): naming the field.
    """
    if control.max_steps:
        return control.max_steps
    if not is_concrete([phase.n_steps for phase in phases]):
        raise ValueError("field 'max_steps': give StepControl(max_steps=...) when the model is an argument of "
                         "the compiled function (its nominal increments are data there, and the default counts them)")
    return 10 * schedule(phases).n_nominal_steps + 100


class Controller(eqx.Module):
    """The adaptive step controller of one run: its schedule (segments of nominal increments ending on
    the phases' breakpoints) and its static choices.

    Attributes:
        control: the settings.
        seg_end, seg_dt, seg_phase, seg_steps: per schedule segment, its end (pseudo-time), nominal
            increment, phase and number of nominal steps (0: an empty segment that pads a phase's
            increments, which the controller passes over: :func:`jaxfric.fem.loading.with_steps`).
        n_buffer: history rows of accepted steps in a whole run's buffer (static; 0 in a chunk's
            program, whose buffers are its own).
        max_rows: () int32, accepted steps after which the run stops with ``Result.MAX_STEPS`` (data:
            the chunked driver's programs serve every ``max_steps``).
        continuation: the run carries the continuation's stages (static: asked for, and a
            formulation that has them).
        has_line_search: a last attempt without line search exists (static).
        n_stages: () int32 number of continuation stages (0: none).
        stabilized: the stabilised attempt exists (static: a formulation that has one, and ``stabilize``
            > 0 with a sheet modulus).
        eta: () the first damper (N/mm per mm).
        widenable: exact contact's proximity band is smaller than the candidates (static:
            :func:`band_full`).
    """

    control: StepControl = eqx.field(static=True)
    seg_end: jax.Array
    seg_dt: jax.Array
    seg_phase: jax.Array
    seg_steps: jax.Array
    n_buffer: int = eqx.field(static=True)
    max_rows: jax.Array
    continuation: bool = eqx.field(static=True)
    has_line_search: bool = eqx.field(static=True)
    n_stages: jax.Array
    stabilized: bool = eqx.field(static=True)
    eta: jax.Array
    widenable: bool = eqx.field(static=True, default=False)

    @classmethod
    def build(cls, phases, control: StepControl, continuation: bool, has_line_search: bool,
              n_stages, modulus=None, max_rows=None, widenable: bool = False) -> Controller:
        """``modulus``: the sheet's Young's modulus (the stabilisation's scale; None: no stabilisation).
        ``max_rows``: the run's most accepted steps as data, for a chunk's program (no buffer of its own
        here); None: ``control``'s :func:`max_steps`, and a whole run's buffer of that many rows.
        ``widenable``: :attr:`widenable`."""
        sched = schedule(phases)
        stabilized = modulus is not None and control.stabilize > 0
        eta = jnp.asarray(control.stabilize * modulus if stabilized else 0.0, jnp.float64)
        n_buffer = 0 if max_rows is not None else max_steps(control, phases)
        rows = jnp.asarray(n_buffer if max_rows is None else max_rows, jnp.int32)
        return cls(control, jnp.asarray(sched.seg_end), jnp.asarray(sched.seg_dt),
                   jnp.asarray(sched.seg_phase, jnp.int32), jnp.asarray(sched.seg_steps, jnp.int32), n_buffer, rows,
                   continuation, has_line_search, n_stages, stabilized, eta, widenable)

    def init(self, u, q) -> ControllerState:
        """The state before the first step (``u``, ``q``: shapes of the displacements and tool
        positions, for the continuation's stage solution)."""
        int0 = jnp.array(0, jnp.int32)
        stages = ContinuationState(soft=jnp.array(-1, jnp.int32), tried=jnp.array(False),
                                   u=jnp.zeros_like(u) if self.continuation else jnp.zeros((0, 2)),
                                   q=jnp.zeros_like(q) if self.continuation else jnp.zeros(0),
                                   staged=jnp.array(False))
        return ControllerState(dt=self.seg_dt[0], seg=int0, n_easy=int0, cuts=int0, cut_codes=int0, iters=int0,
                               stats=jnp.zeros(3, jnp.int32), code=jnp.array(Result.CONTINUE, jnp.int32),
                               failed_t=jnp.array(jnp.nan), r_norm=jnp.array(0.0), plain=jnp.array(False),
                               last_code=int0, stages=stages, damped=int0, n_crawl=int0)

    def target(self, cs: ControllerState, t_start):
        """The next attempt's pseudo-time (snapped to the segment's end when within round-off of it:
        steps end exactly on breakpoints) and phase."""
        dt_nom, end = self.seg_dt[cs.seg], self.seg_end[cs.seg]
        t_try = jnp.where(t_start + cs.dt >= end - 1e-9 * dt_nom, end, t_start + cs.dt)
        return t_try, self.seg_phase[cs.seg]

    def start(self, cs: ControllerState, guess):
        """Newton's starting point: ``guess`` (u, q), or the last continuation stage's solution."""
        if not self.continuation:
            return guess
        st = cs.stages
        return jnp.where(st.staged, st.u, guess[0]), jnp.where(st.staged, st.q, guess[1])

    def tally(self, cs: ControllerState, out: Outcome) -> Tally:
        """Whether an attempt with outcome ``out`` is an accepted step (a continuation stage before the
        last is not), and the step's iterations and solver counts over its attempts so far."""
        converged = out.code == Result.SUCCESS
        ok = converged & (cs.stages.soft <= 0) if self.continuation else converged
        return Tally(ok, cs.iters + out.iterations, cs.stats + out.stats)

    def adapt(self, cs: ControllerState, t_start, t_try, out: Outcome, row) -> ControllerState:
        """The state after an attempt from ``t_start`` to ``t_try`` with outcome ``out``; ``row``: the
        history rows filled before it."""
        dt_nom, end = self.seg_dt[cs.seg], self.seg_end[cs.seg]
        converged = out.code == Result.SUCCESS
        ok, iters, stats = self.tally(cs, out)
        seg_done = ok & (t_try == end)
        # The next segment with steps (empty ones pad a replay's phases); none: the load path's end.
        later = (jnp.arange(self.seg_end.shape[0], dtype=jnp.int32) > cs.seg) & (self.seg_steps > 0)
        last_seg = ~jnp.any(later)
        next_seg = jnp.where(seg_done & ~last_seg, jnp.argmax(later).astype(jnp.int32), cs.seg)
        hardest = out.iterations if out.hardest is None else out.hardest
        n_easy, grow, dt_ok = increment_after_acceptance(self.control, ok, cs.n_easy, hardest, cs.dt, dt_nom,
                                                         self.seg_dt[next_seg], seg_done)
        if self.control.step_error > 0:
            dt_err = increment_from_error(self.control, out.error, grow, t_try - t_start, dt_nom)
            dt_ok = jnp.where(seg_done | (out.error < 0), dt_ok, dt_err)
        dt_cut = 0.5 * (t_try - t_start)
        at_floor = ~ok & (dt_cut < dt_nom / 2.0**self.control.max_cuts * (1.0 - 1e-9))
        again = retry_from_converged(~ok, at_floor, cs.cuts, out.predicted)
        # After a stabilised attempt the unsearched one does not come back.
        plain = unsearched_attempt(at_floor, again, cs.plain, self.has_line_search) & (cs.damped == 0)
        stages, held = cs.stages, jnp.array(False)
        if self.continuation:
            stages, start, stage_done, held = continuation_rule(cs.stages, self.n_stages, at_floor, again,
                                                                cs.plain, converged, ok, out.u, out.q)
            plain = plain & ~start & ~stage_done
            too_small = at_floor & ~again & ~plain & ~start & ~stage_done
            repeat = again | plain | start | stage_done
        else:
            too_small = at_floor & ~again & ~plain
            repeat = again | plain
        level = stabilised_attempt(too_small, cs.damped, self.stabilized)
        damp = level > 0
        too_small, repeat = too_small & ~damp, repeat | damp
        finished = seg_done & last_seg
        full = ok & ~finished & (row + 1 >= self.max_rows + 1)
        n_crawl = crawl_count(self.control, ok, cs.cuts, cs.n_crawl, t_try - t_start, dt_nom)
        stalled = ok & ~finished & (n_crawl >= self.control.stall_steps)
        # The band too small: the step stays pending as it was attempted, for the driver to widen the band.
        widen = band_full(out.code, self.widenable)
        too_small, repeat, level = too_small & ~widen, repeat | widen, jnp.where(widen, cs.damped, level)
        keep_r = (too_small & cs.plain) | held
        return ControllerState(
            dt=jnp.where(ok, dt_ok, jnp.where(repeat, t_try - t_start, dt_cut)), seg=next_seg,
            n_easy=jnp.where(grow, 0, n_easy), cuts=jnp.where(ok, 0, cs.cuts + 1),
            cut_codes=jnp.where(ok, 0, cs.cut_codes | cause_mask(out.code)).astype(jnp.int32),
            iters=jnp.where(ok, 0, iters), stats=jnp.where(ok, 0, stats),
            code=jnp.where(widen, Result.BAND_FULL,
                           stop_code(too_small, finished, full, cs.plain, cs.last_code, out.code, stalled)),
            failed_t=jnp.where(ok, cs.failed_t, t_try), r_norm=jnp.where(keep_r, cs.r_norm, out.residual_norm),
            plain=jnp.where(widen, cs.plain, ~ok & (cs.plain | plain) & ~damp),
            last_code=jnp.where(held, cs.last_code, out.code).astype(jnp.int32), stages=stages,
            damped=jnp.where(ok, 0, level).astype(jnp.int32), n_crawl=n_crawl)
