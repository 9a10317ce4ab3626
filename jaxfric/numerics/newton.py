"""Newton-Raphson for one load step, differentiated by the implicit function theorem.

One loop serves every contact formulation: :func:`newton_pass` owns the convergence test, the line
search, the result codes and the iteration count, and asks an :class:`AbstractNewtonProblem` to evaluate
a point and to give a direction from it. :class:`LinearizedProblem` is Newton on a linearisation (the
penalty and augmented-Lagrangian laws, and models without tools); exact contact plugs in its own
evaluation and direction (:class:`jaxfric.contact.exact.ExactContactProblem`).

A linearised problem is given as two pure functions of the unknowns x and of a pytree ``args`` of data
(parameters, converged history, prescribed values):

    linearize(x, args) -> Linearization(residual R, jacobian dR/dx, scale, valid, aux)
    residual(x, args)  -> (R, aux)

``newton_solve`` iterates x <- x - J^-1 R inside a ``lax.while_loop`` until

    ||R||_inf <= atol + rtol * max(scale, 1e-6)       (scale: ||f_int||_inf, N/mm)
    ||dx_last||_inf <= du_atol + du_rtol * ||x - x_ref||_inf   (x_ref: the last converged state)

after at least one iteration (so prescribed increments are always applied); or, where the residual
test cannot be met in float64, with the round-off floor ``roundoff * eps * max_i (|J| |x|)_i`` added
to the residual tolerance once an iteration fails to reduce ||R|| tenfold. The unknowns are
represented to eps |x| only (and the residual is evaluated from them with an error of that order),
so Newton's iterates stagnate within about eps |J| |x| of zero: late in a long draw on a fine mesh
(displacements of 65 mm, stiffness entries of 1e6 N/mm^2) that is 1e-6 N/mm while the relative
tolerance has fallen to 2e-7 (docs/results.md, mesh convergence). Where the residual is computed from
positions X + u rather than from u (the contact gaps), its round-off is relative to |X + u|, which
the linearisation then passes as ``magnitude``: a penalty of 1e9 N/mm at a node 13 mm from the origin
resolves forces to 1e9 x ulp(13 mm) = 1.8e-6 N/mm, however small u is. That floor is used only where
the caller asks (``positions``: the step controller's continuation stages at the smallest increment,
:class:`jaxfric.loadpath.controller.StepControl`): it can exceed the residual tolerance, and an iteration that
merely converges slowly (a stick/slip 2-cycle) also fails to reduce ||R|| tenfold, so as the default
it would end such iterations early and change the load path of runs that converge without it (the
flat die at eps_N = 1e9, 24 x 1, mu = 0.04 then stopped in its draw). A quadratically converging iteration
never takes this exit. It never raises: it returns a :class:`~jaxfric.numerics.results.Result` code.

Carried data. An evaluation may hand data to the next one besides x (``Linearization.carry``, passed on
in ``Trial.data``): the enhanced parameters of the ``anst`` and ``eas`` elements, carried with the
iterate in the enhanced-strain update of Simo and Armero (:mod:`jaxfric.fem.element`). ``args`` then has
``carry`` (what the step's first evaluation starts from) and ``with_carry(data)``. Such unknowns are
updated from each Newton step's linearisation, so the residual test also asks that what they still move
(``Linearization.inner``) meets the residual tolerance. The solution's derivatives evaluate without the
carried data, where the elements condense exactly.

Derivatives. At a converged solution R(x*, args) = 0, so dx*/dargs = -J^-1 dR/dargs. The JVP rule
computes exactly that: one JVP of the residual with respect to ``args`` and one linear solve with the
converged Jacobian through :func:`jaxfric.numerics.linalg.linear_solve` (a ``lax.custom_linear_solve``, so reverse
mode transposes it with the transposed structured solve). The Newton iterations themselves are never
differentiated. The by-products ``aux`` (stresses, updated history, internal forces) get their tangents
by a JVP of ``residual`` at (x*, args) along (dx*, dargs).
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jax.ad_checkpoint import checkpoint_name

from ._checks import check_int, check_nonnegative
from .linalg import linear_solve
from .results import Result

__all__ = ["NewtonOptions", "Linearization", "NewtonSolution", "Evaluation", "Trial", "AbstractNewtonProblem",
           "LinearizedProblem", "NewtonCarry", "newton_start", "newton_pass", "newton_result", "newton_loop",
           "newton_solve", "roundoff_floor", "moving_part", "SOLUTION_NAME"]

# ``jax.ad_checkpoint.checkpoint_name`` of a converged step solution, for a rematerialisation policy
# that saves it (``jax.checkpoint_policies.save_only_these_names(SOLUTION_NAME)``).
SOLUTION_NAME = "jaxfric_step_solution"


class NewtonOptions(eqx.Module):
    """Newton tolerances (static: changing them recompiles).

    Attributes:
        rtol, atol: residual test ||R||_inf <= atol + rtol max(scale, 1e-6) (N/mm).
        du_rtol, du_atol: increment test on the last correction, relative to the step's total
            increment ||x - x0||_inf, and absolute (mm).
        max_iterations: linearisations allowed per attempt (Newton steps and rejected trials).
        roundoff: multiple of the round-off floor eps max(|J| |x|) that a stagnating iteration may
            stop at (module doc); 0 switches the floor off.
        line_search: backtrack (quarter the step, at most twice) when a Newton step increases the
            residual norm. It breaks the 2-cycles of penalty friction, where pairs at the Coulomb
            limit reverse their slip direction every iteration (a slipping pair has no tangential
            stiffness, so the full step overshoots the slip), and of pairs flipping open/closed.
    """

    rtol: float = eqx.field(static=True, default=1e-8)
    atol: float = eqx.field(static=True, default=1e-10)
    du_rtol: float = eqx.field(static=True, default=1e-3)
    du_atol: float = eqx.field(static=True, default=1e-9)
    max_iterations: int = eqx.field(static=True, default=25)
    line_search: bool = eqx.field(static=True, default=True)
    roundoff: float = eqx.field(static=True, default=1.0)

    def __check_init__(self):
        for name in ("rtol", "atol", "du_rtol", "du_atol", "roundoff"):
            check_nonnegative(name, getattr(self, name))
        check_int("max_iterations", self.max_iterations, 1, 10_000)


class Linearization(NamedTuple):
    residual: jax.Array      # (N,)
    jacobian: Any            # BlockTridiag or Bordered, dR/dx
    scale: jax.Array         # () force scale of the relative residual test
    valid: jax.Array         # () bool: False for an inadmissible configuration (inverted element)
    aux: Any                 # by-products at x
    status: Any = None       # optional int array (contact status): must not change in the last iteration
    prescribed_error: Any = None  # optional () max |x - x_presc| over prescribed dofs (mm)
    magnitude: Any = None    # optional (N,) size of what each unknown's round-off is relative to (|x|
                             # by default): positions |X + u| where the residual uses them (contact gaps)
    preselected: Any = None  # optional () bool: False where a pair the step left out could have reached
                             # its tool (jaxfric.contact.preselection)
    carry: Any = None        # optional: what the next evaluation continues from besides x (the elements'
                             # enhanced predictor; module doc, "Carried data")
    inner: Any = None        # optional () the part of the residual that the carried unknowns still move
                             # (N/mm): it must meet the residual tolerance too


class NewtonSolution(NamedTuple):
    x: jax.Array
    aux: Any
    iterations: jax.Array      # () int: linearisations performed (Newton steps and rejected trials)
    code: jax.Array            # () int: Result
    residual_norm: jax.Array   # () ||R||_inf at x
    residual_history: jax.Array  # (max_iterations+1,) ||R||_inf after each iteration (nan beyond)


def roundoff_floor(jacobian, x: jax.Array) -> jax.Array:
    """``eps * max_i (|J| |x|)_i``: the residual's size at the float64 neighbours of a root (module doc).

    ``jacobian``: a BlockTridiag or Bordered (anything with ``matvec`` whose leaves are its entries)."""
    absolute = jtu.tree_map(jnp.abs, jacobian)
    return jnp.finfo(x.dtype).eps * jnp.max(absolute.matvec(jnp.abs(x)))


def _all_finite(tree) -> jax.Array:
    leaves = [jnp.all(jnp.isfinite(leaf)) for leaf in jtu.tree_leaves(tree) if eqx.is_inexact_array(leaf)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.array(True)


# ---- the problem a Newton loop solves ---------------------------------------------------------------

def carry_of(args):
    """What the step's first evaluation continues from besides x (``args.carry``; None: nothing)."""
    return getattr(args, "carry", None)


def with_carry(args, carry):
    """``args`` for an evaluation that continues from ``carry`` (module doc, "Carried data")."""
    return args if carry is None else args.with_carry(carry)


def without_carry(args):
    """``args`` whose evaluations carry nothing: those of the solution itself (its derivatives)."""
    return args.with_carry(None) if carry_of(args) is not None else args


class Evaluation(NamedTuple):
    """One point of the Newton loop, evaluated by its problem (:meth:`AbstractNewtonProblem.evaluate`)."""

    residual: jax.Array      # (N,) what the residual test measures
    scale: jax.Array         # () force scale of the relative residual test
    finite: jax.Array        # () bool: everything the point's test and next direction use is finite
    valid: jax.Array         # () bool: False for an inadmissible configuration (inverted element)
    state: Any               # the problem's own data at the point (kept while the point is the accepted one)
    merit: Any = None        # () what the line search compares; None: the problem is not line-searched
    in_band: Any = None      # () False: the solve left out a contact it needed (CONTACT_BAND); None: no band
    prescribed_error: Any = None  # () max |x - x_presc| over prescribed unknowns (mm), where there are any
    preselected: Any = None  # () False: a pair the step's pre-selection left out could have reached its
                             # tool (PRESELECTION); None: no pre-selection
    inner: Any = None        # () the residual the carried unknowns still move (Linearization.inner); None: none


class Trial(NamedTuple):
    """A Newton direction from the accepted point and the step length tried along it."""

    dx: jax.Array
    alpha: jax.Array     # () 1, then 1/4 and 1/16 of the direction after rejected trials
    merit: jax.Array     # () the merit the trial point must not exceed (the line search's reference)
    solved: jax.Array    # () bool: the direction's own solver succeeded (False: LCP_FAILED)
    stats: jax.Array     # counts of the direction's solver (summed over the step's directions)
    data: Any = None     # the problem's own (exact contact: the forces the direction predicts)


class AbstractNewtonProblem(eqx.Module):
    """What :func:`newton_pass` asks of the problem it solves: how to evaluate a point and which
    direction to take from it. The loop owns the rest: the convergence test, the line search, the
    result codes and the iteration count.

    ``searches_first_step`` (static): whether the first Newton step may be shortened. The step that
    applies the prescribed increments is not, where the problem's merit is the residual that these
    increments change row by row (:class:`LinearizedProblem`); it is when the initial guess already meets
    them (a predictor).
    """

    searches_first_step: eqx.AbstractClassVar[bool]

    @abc.abstractmethod
    def start(self, x0, args) -> Trial:
        """The trial that evaluates the initial guess (no direction yet)."""

    @abc.abstractmethod
    def evaluate(self, x, trial: Trial, args) -> Evaluation:
        """The point ``x`` reached by ``trial``."""

    @abc.abstractmethod
    def settled(self, new: Evaluation, old: Evaluation, trial: Trial) -> jax.Array:
        """Whether the step may converge at ``new`` reached from the accepted ``old`` (contact: no pair
        changed its status)."""

    @abc.abstractmethod
    def direction(self, x, point: Evaluation, args, first) -> Trial:
        """A Newton direction from the accepted point ``x``; ``first``: ``x`` is the initial guess."""

    @abc.abstractmethod
    def aux(self, x, point: Evaluation, args):
        """The by-products of the solution at the accepted point."""

    def roundoff_floor(self, x, point: Evaluation):
        """The residual's round-off floor at ``point`` (module doc), or None where it is not used."""
        return None


class LinearizedProblem(AbstractNewtonProblem):
    """Newton on ``linearize(x, args)`` (a :class:`Linearization`): the direction solves with its
    Jacobian, the merit is ||R||_2^2, and a step converges only where the contact status (if any) did
    not change. ``positions`` (bool, may be traced): the round-off floor is taken relative to the
    linearisation's ``magnitude`` (positions) instead of |x| (module doc)."""

    linearize: Callable = eqx.field(static=True)
    positions: Any = False
    searches_first_step: ClassVar[bool] = False

    def start(self, x0, args) -> Trial:
        return Trial(jnp.zeros_like(x0), jnp.array(1.0), jnp.array(jnp.inf), jnp.array(True),
                     jnp.zeros(0, jnp.int32), carry_of(args))

    def evaluate(self, x, trial, args) -> Evaluation:
        lin = self.linearize(x, with_carry(args, trial.data))
        return Evaluation(lin.residual, lin.scale, _all_finite((lin.residual, lin.jacobian)), lin.valid, lin,
                          merit=jnp.sum(lin.residual**2), prescribed_error=lin.prescribed_error,
                          preselected=lin.preselected, inner=lin.inner)

    def settled(self, new, old, trial) -> jax.Array:
        if new.state.status is None:
            return jnp.array(True)
        return jnp.all(new.state.status == old.state.status)

    def direction(self, x, point, args, first) -> Trial:
        lin = point.state
        return Trial(linear_solve(lin.jacobian, -lin.residual), jnp.array(1.0), point.merit, jnp.array(True),
                     jnp.zeros(0, jnp.int32), lin.carry)

    def aux(self, x, point, args):
        return point.state.aux

    def roundoff_floor(self, x, point):
        lin = point.state
        size = x if lin.magnitude is None else jnp.where(self.positions, lin.magnitude, jnp.abs(x))
        return roundoff_floor(lin.jacobian, size)


# ---- the loop -------------------------------------------------------------------------------------

class NewtonCarry(NamedTuple):
    """State of the Newton loop between two passes (:func:`newton_pass`)."""

    k: jax.Array            # index of the point x_t to evaluate next (0: the initial guess)
    n_acc: jax.Array        # accepted Newton steps
    x: jax.Array            # last accepted iterate
    point: Evaluation       # its evaluation
    x_t: jax.Array          # the point to evaluate
    trial: Trial            # the trial that reaches x_t
    code: jax.Array         # Result (CONTINUE while iterating)
    r_hist: jax.Array       # (max_iterations + 1,) ||R||_inf of each evaluated point
    start_meets: jax.Array  # the initial guess meets the prescribed values
    stats: jax.Array        # the directions' solver counts, summed


def newton_start(problem: AbstractNewtonProblem, x0, args, options: NewtonOptions) -> NewtonCarry:
    """The carry of a Newton loop from the initial guess ``x0``."""
    trial = problem.start(x0, args)
    shape = eqx.filter_eval_shape(problem.evaluate, x0, trial, args)
    point = jtu.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), shape)
    int0 = jnp.array(0, jnp.int32)
    return NewtonCarry(int0, int0, x0, point, x0, trial, jnp.array(Result.CONTINUE, jnp.int32),
                       jnp.full(options.max_iterations + 1, jnp.nan), jnp.array(False), jnp.zeros_like(trial.stats))


def _code(k, x, x_ref, new: Evaluation, trial: Trial, step_norm, settled, r_prev, floor, options: NewtonOptions):
    """The result code of the point ``x`` (CONTINUE: iterate on) and its ||R||_inf."""
    r_norm = jnp.max(jnp.abs(new.residual))
    tol = options.atol + options.rtol * jnp.maximum(new.scale, 1e-6)
    res_ok = r_norm <= tol
    if new.inner is not None:   # static
        res_ok = res_ok & (new.inner <= tol)
    if options.roundoff > 0.0 and floor is not None:   # static
        stagnant = r_norm > 0.1 * r_prev
        res_ok = res_ok | (stagnant & (r_norm <= tol + options.roundoff * floor))
    dx_ok = step_norm <= options.du_atol + options.du_rtol * jnp.max(jnp.abs(x - x_ref))
    done = (k >= 1) & res_ok & dx_ok & settled
    out_of_iterations = k >= options.max_iterations
    # A contact left out of the solve shows as a converged state with a penetrating outsider, or as a
    # loop that cannot settle because the outsiders enter and leave the band: both report the band.
    outside_band = jnp.array(False) if new.in_band is None else (done | out_of_iterations) & ~new.in_band
    # Likewise a pair the step's pre-selection left out: checked where the loop ends.
    missed = jnp.array(False) if new.preselected is None else (done | out_of_iterations) & ~new.preselected
    code = jnp.select(
        [~new.finite, ~trial.solved, ~new.valid, outside_band, missed, done, out_of_iterations],
        [Result.NONFINITE, Result.LCP_FAILED, Result.INVERTED_ELEMENT, Result.CONTACT_BAND, Result.PRESELECTION,
         Result.SUCCESS, Result.MAX_ITERATIONS], Result.CONTINUE)
    return code.astype(jnp.int32), r_norm


def newton_pass(c: NewtonCarry, args, x_ref, problem: AbstractNewtonProblem, options: NewtonOptions,
                search=True) -> NewtonCarry:
    """One pass of the Newton loop: evaluate the pending point (the initial guess first, then each
    trial), decide (accept, reject, converged, failed), and set up the next trial. A loop of passes
    holds one evaluation and one direction solve in the traced program (each copy costs compile time:
    a linearisation of the Nine scene about 7 s), and a vmapped load loop can advance each member by
    one Newton iteration per pass (:func:`jaxfric.loadpath.simulate.simulate_flat`).

    ``search`` (bool, may be traced): False switches the line search of ``options`` off."""
    first = c.k == 0
    new = problem.evaluate(c.x_t, c.trial, args)
    start_meets = jnp.where(first, jnp.array(False) if new.prescribed_error is None
                            else new.prescribed_error <= 1e-12, c.start_meets)
    step_norm = jnp.where(first, jnp.inf, jnp.max(jnp.abs(c.trial.alpha * c.trial.dx)))
    floor = problem.roundoff_floor(c.x_t, new) if options.roundoff > 0.0 else None
    code_new, r_norm = _code(c.k, c.x_t, x_ref, new, c.trial, step_norm, problem.settled(new, c.point, c.trial),
                             jnp.max(jnp.abs(c.point.residual)), floor, options)
    # Line search: a trial that raises the merit is retried at a quarter, then a sixteenth of its
    # length, which is then kept (quartering, not halving: the overshoots met are linear in the step,
    # such as open pairs driven into a tool, so only the short step helps). A trial that passes the
    # convergence test is never rejected: at round-off level the merit may grow by noise.
    reject = jnp.array(False)
    if options.line_search and new.merit is not None:   # static
        worse = ~(new.merit <= c.trial.merit)
        allowed = jnp.array(problem.searches_first_step) | (c.n_acc >= 1) | start_meets
        reject = (~first & search & allowed & worse & (c.trial.alpha > 1.0 / 16.0) & (code_new != Result.SUCCESS))
    # A rejected trial still counts as an iteration (it cost an evaluation).
    code = jnp.where(reject & (c.k < options.max_iterations), Result.CONTINUE, code_new).astype(jnp.int32)
    keep = lambda a, b: jnp.where(reject, a, b)  # noqa: E731
    x, point = keep(c.x, c.x_t), jtu.tree_map(keep, c.point, new)

    # The next trial: a new direction from the accepted point, the same one shortened, or none.
    no_stats = jnp.zeros_like(c.stats)

    def fresh():
        trial = problem.direction(x, point, args, first)
        return trial, trial.stats

    def shorter():
        return c.trial._replace(alpha=0.25 * c.trial.alpha), no_stats

    def stop():
        return c.trial, no_stats

    branch = jnp.where(code != Result.CONTINUE, 2, jnp.where(reject, 1, 0))
    trial, stats = jax.lax.switch(branch, [fresh, shorter, stop])
    return NewtonCarry(c.k + 1, c.n_acc + jnp.where(reject | first, 0, 1), x, point, x + trial.alpha * trial.dx,
                       trial, code, c.r_hist.at[c.k].set(r_norm), start_meets, c.stats + stats)


def newton_result(c: NewtonCarry, problem: AbstractNewtonProblem, args) -> NewtonSolution:
    """The solution of a finished loop (``c.code != CONTINUE``)."""
    return NewtonSolution(c.x, problem.aux(c.x, c.point, args), c.k - 1, c.code, c.r_hist[c.k - 1], c.r_hist)


def newton_loop(problem: AbstractNewtonProblem, args, x0, x_ref, options: NewtonOptions,
                search=True) -> NewtonCarry:
    """The Newton loop from ``x0`` to its end (``x_ref``: the last converged state, reference of the
    increment test); the finished carry (:func:`newton_result`)."""
    return jax.lax.while_loop(lambda c: c.code == Result.CONTINUE,
                              lambda c: newton_pass(c, args, x_ref, problem, options, search),
                              newton_start(problem, x0, args, options))


def _newton(args, x0, x_ref, linearize: Callable, options: NewtonOptions, search=True, positions=False):
    problem = LinearizedProblem(linearize, positions)
    return newton_result(newton_loop(problem, args, x0, x_ref, options, search), problem, args)


def moving_part(args, args_dot):
    """``(moving, moving_dot, held)``: the floating-point leaves of ``args`` that carry a tangent in
    ``args_dot`` (``None``: a symbolic zero, as :func:`equinox.filter_custom_jvp` passes it), their
    tangents, and the rest of ``args``, with ``eqx.combine(moving, held) == args``.

    A JVP rule differentiates its evaluations with respect to ``moving`` only: the leaves that hold
    still (the mesh, the material, the tools' data that no differentiated parameter moves) stay
    constants of the traced program, so neither tracing nor the compiled derivative works through
    their zero tangents."""
    diff, static = eqx.partition(args, eqx.is_inexact_array)
    mask = jtu.tree_map(lambda a, t: a is not None and t is not None, diff, args_dot, is_leaf=lambda v: v is None)
    moving, held = eqx.partition(diff, mask)
    moving_dot = jtu.tree_map(lambda t, m: t if m else None, args_dot, mask, is_leaf=lambda v: v is None)
    return moving, moving_dot, eqx.combine(held, static)


@eqx.filter_custom_jvp
def newton_solve(args, x0, x_ref, *, linearize: Callable, residual: Callable,
                 options: NewtonOptions, search=True, positions=False) -> NewtonSolution:
    """Solve R(x, args) = 0 by Newton from the initial guess ``x0``; differentiable in ``args``.

    ``x_ref`` (the last converged state) is the reference of the increment test. Neither ``x0`` nor
    ``x_ref`` changes the solution, so neither carries a derivative. ``linearize`` and ``residual``
    must be pure, module-level functions of (x, args): all data they use travels in ``args`` so that
    derivatives reach it. ``search`` (bool, may be traced) False switches the line search off for this
    solve (the step controller's last attempt at the smallest increment); ``positions``: see
    :class:`LinearizedProblem`.
    """
    return _newton(args, x0, x_ref, linearize, options, search, positions)


@newton_solve.def_jvp
def _newton_solve_jvp(primals, tangents, *, linearize, residual, options, search=True, positions=False):
    args, x0, x_ref = primals
    args_dot = tangents[0]  # the initial guess and the reference do not change the solution
    solution = _newton(args, x0, x_ref, linearize, options, search, positions)
    # The carried data does not change the solution either; at the solution the evaluations condense
    # exactly (the elements' local solve), so the derivative's do.
    args, args_dot = without_carry(args), without_carry(args_dot)
    # The converged point is all the derivative needs: named, so that a checkpointed load loop can
    # keep it and, in the backward pass, rebuild the Jacobian at it by one linearisation instead of
    # re-running the Newton iterations (see SOLUTION_NAME).
    x_star = checkpoint_name(solution.x, SOLUTION_NAME)
    jacobian = linearize(x_star, args).jacobian
    solution = solution._replace(x=x_star)
    diff, diff_dot, static = moving_part(args, args_dot)

    def res(x, d):
        return residual(x, eqx.combine(d, static))

    # Implicit function theorem: J dx* = -(dR/dargs) dargs.
    _, r_dot = jax.jvp(lambda d: res(solution.x, d)[0], (diff,), (diff_dot,))
    x_dot = -linear_solve(jacobian, r_dot)
    _, aux_dot = jax.jvp(lambda x, d: res(x, d)[1], (solution.x, diff), (x_dot, diff_dot))
    return solution, NewtonSolution(x_dot, aux_dot, None, None, None, None)
