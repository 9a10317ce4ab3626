"""Newton-Raphson for one load step, differentiated by the implicit function theorem.

The problem is given as two pure functions of the unknowns x and of a pytree ``args`` of data
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
:class:`jaxfric.controller.StepControl`): it can exceed the residual tolerance, and an iteration that
merely converges slowly (a stick/slip 2-cycle) also fails to reduce ||R|| tenfold, so as the default
it would end such iterations early and change the load path of runs that converge without it (the
flat die at eps_N = 1e9, 24 x 1, mu = 0.04 then stopped in its draw). A quadratically converging iteration
never takes this exit. It never raises: it returns a :class:`~jaxfric.results.Result` code.

Derivatives. At a converged solution R(x*, args) = 0, so dx*/dargs = -J^-1 dR/dargs. The JVP rule
computes exactly that: one JVP of the residual with respect to ``args`` and one linear solve with the
converged Jacobian through :func:`jaxfric.linalg.linear_solve` (a ``lax.custom_linear_solve``, so reverse
mode transposes it with the transposed structured solve). The Newton iterations themselves are never
differentiated. The by-products ``aux`` (stresses, updated history, internal forces) get their tangents
by a JVP of ``residual`` at (x*, args) along (dx*, dargs).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
from jax.ad_checkpoint import checkpoint_name

from ._checks import check_int, check_nonnegative
from .linalg import linear_solve
from .results import Result

__all__ = ["NewtonOptions", "Linearization", "NewtonSolution", "newton_solve", "roundoff_floor", "SOLUTION_NAME"]

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


class NewtonCarry(NamedTuple):
    """State of the Newton loop between two passes (:func:`newton_pass`)."""

    k: jax.Array            # index of the point x_t to evaluate next (0: the initial guess)
    n_acc: jax.Array        # accepted Newton steps
    x: jax.Array            # last accepted iterate
    lin: Linearization      # its linearisation
    x_t: jax.Array          # the point to evaluate
    dx: jax.Array           # the Newton direction of the trial
    code: jax.Array         # Result (CONTINUE while iterating)
    alpha: jax.Array        # step length of the trial
    dx_norm: jax.Array
    r_hist: jax.Array       # (max_iterations + 1,) ||R||_inf of each evaluated point
    start_meets: jax.Array  # the initial guess meets the prescribed values


def newton_start(x0, lin_shape, options: NewtonOptions) -> NewtonCarry:
    """The carry of a Newton loop from the initial guess ``x0``; ``lin_shape``: the shapes of a
    :class:`Linearization` (``eqx.filter_eval_shape(linearize, x0, args)``)."""
    int0 = jnp.array(0, jnp.int32)
    lin0 = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), lin_shape)
    return NewtonCarry(int0, int0, x0, lin0, x0, jnp.zeros_like(x0), jnp.array(Result.CONTINUE, jnp.int32),
                       jnp.array(1.0), jnp.array(jnp.inf), jnp.full(options.max_iterations + 1, jnp.nan),
                       jnp.array(False))


def newton_pass(c: NewtonCarry, args, x_ref, linearize: Callable, options: NewtonOptions,
                search=True, positions=False) -> NewtonCarry:
    """One pass of the Newton loop: evaluate the pending point (the initial guess first, then each
    trial), decide (accept, reject, converged, failed), and set up the next trial. A loop of passes
    holds one linearisation and one linear solve in the traced program (each copy costs compile time:
    a linearisation of the Nine scene about 7 s), and a vmapped load loop can advance each member by
    one Newton iteration per pass (:func:`jaxfric.simulate.simulate_flat`)."""

    def classify(k, x, lin, dx_norm, same_status, r_prev):
        r_norm = jnp.max(jnp.abs(lin.residual))
        finite = _all_finite((lin.residual, lin.jacobian))
        tol = options.atol + options.rtol * jnp.maximum(lin.scale, 1e-6)
        res_ok = r_norm <= tol
        if options.roundoff > 0.0:   # static
            stagnant = r_norm > 0.1 * r_prev
            size = x if lin.magnitude is None else jnp.where(positions, lin.magnitude, jnp.abs(x))
            res_ok = res_ok | (stagnant & (r_norm <= tol + options.roundoff * roundoff_floor(lin.jacobian, size)))
        dx_ok = dx_norm <= options.du_atol + options.du_rtol * jnp.max(jnp.abs(x - x_ref))
        code = jnp.select(
            [~finite, ~lin.valid, (k >= 1) & res_ok & dx_ok & same_status, k >= options.max_iterations],
            [Result.NONFINITE, Result.INVERTED_ELEMENT, Result.SUCCESS, Result.MAX_ITERATIONS],
            Result.CONTINUE)
        return code.astype(jnp.int32), r_norm

    k, n_acc, x, lin, x_t, dx, _, alpha, dx_norm, r_hist, start_meets = c
    new = linearize(x_t, args)
    first = k == 0
    start_meets = jnp.where(first, jnp.array(False) if new.prescribed_error is None
                            else new.prescribed_error <= 1e-12, start_meets)
    # Reject a step that increases ||R||_2: retry with 1/4, then 1/16 of it, which is then kept.
    # (Quartering: on the Nine bead the overshoot is a stretch of open pairs driven into the
    # tool, whose residual is linear in the step, so only the short step helps; halving spent
    # two more linearisations per step to reach it.) Not the first step when it applies the
    # prescribed increments (it changes which rows carry the residual); when the start point
    # already meets them (a predictor), the first step is searched like the others.
    worse = ~(jnp.sum(new.residual**2) <= jnp.sum(lin.residual**2))
    # Contact: converged only if no pair changed status (open/stick/slip) in this iteration.
    same = jnp.array(True) if new.status is None else first | jnp.all(new.status == lin.status)
    step_norm = jnp.where(first, jnp.inf, jnp.max(jnp.abs(alpha * dx)))
    code_new, r_norm = classify(k, x_t, new, step_norm, same, jnp.max(jnp.abs(lin.residual)))
    # (A trial that passes the convergence test is never rejected: at round-off level the norm
    # may grow by noise.)
    reject = (~first & options.line_search & search & ((n_acc >= 1) | start_meets) & worse
              & (alpha > 1.0 / 16.0) & (code_new != Result.SUCCESS))
    # A rejected trial still counts as an iteration (it cost a linearisation).
    code = jnp.where(reject & (k < options.max_iterations), Result.CONTINUE, code_new).astype(jnp.int32)
    keep = lambda a, b: jnp.where(reject, a, b)  # noqa: E731
    x, lin = keep(x, x_t), jax.tree_util.tree_map(keep, lin, new)
    # The next trial: a new Newton direction from the last accepted iterate, or, after a rejected
    # trial, the same direction with a quarter of the last trial step (backtracking).
    fresh = (code == Result.CONTINUE) & ~reject
    dx = jax.lax.cond(fresh, lambda: linear_solve(lin.jacobian, -lin.residual), lambda: dx)
    alpha = jnp.where(reject, 0.25 * alpha, 1.0)
    return NewtonCarry(k + 1, n_acc + jnp.where(reject | first, 0, 1), x, lin, x + alpha * dx, dx, code,
                       alpha, keep(dx_norm, step_norm), r_hist.at[k].set(r_norm), start_meets)


def newton_result(c: NewtonCarry) -> NewtonSolution:
    """The solution of a finished loop (``c.code != CONTINUE``)."""
    return NewtonSolution(c.x, c.lin.aux, c.k - 1, c.code, c.r_hist[c.k - 1], c.r_hist)


def _newton(args, x0, x_ref, linearize: Callable, options: NewtonOptions, search=True, positions=False):
    """The Newton loop; returns the solution and the Jacobian at it (for the JVP rule).

    ``search`` (bool, may be traced): False switches the line search of ``options`` off.
    ``positions`` (bool, may be traced): the round-off floor is taken relative to the linearisation's
    ``magnitude`` (positions) instead of |x| (module doc).
    """
    start = newton_start(x0, eqx.filter_eval_shape(linearize, x0, args), options)
    c = jax.lax.while_loop(lambda c: c.code == Result.CONTINUE,
                           lambda c: newton_pass(c, args, x_ref, linearize, options, search, positions), start)
    return newton_result(c), c.lin.jacobian


@eqx.filter_custom_jvp
def newton_solve(args, x0, x_ref, *, linearize: Callable, residual: Callable,
                 options: NewtonOptions, search=True, positions=False) -> NewtonSolution:
    """Solve R(x, args) = 0 by Newton from the initial guess ``x0``; differentiable in ``args``.

    ``x_ref`` (the last converged state) is the reference of the increment test. Neither ``x0`` nor
    ``x_ref`` changes the solution, so neither carries a derivative. ``linearize`` and ``residual``
    must be pure, module-level functions of (x, args): all data they use travels in ``args`` so that
    derivatives reach it. ``search`` (bool, may be traced) False switches the line search off for this
    solve (the step controller's last attempt at the smallest increment).
    """
    return _newton(args, x0, x_ref, linearize, options, search, positions)[0]


@newton_solve.def_jvp
def _newton_solve_jvp(primals, tangents, *, linearize, residual, options, search=True, positions=False):
    args, x0, x_ref = primals
    args_dot = tangents[0]  # the initial guess and the reference do not change the solution
    solution, _ = _newton(args, x0, x_ref, linearize, options, search, positions)
    # The converged point is all the derivative needs: named, so that a checkpointed load loop can
    # keep it and, in the backward pass, rebuild the Jacobian at it by one linearisation instead of
    # re-running the Newton iterations (see SOLUTION_NAME).
    x_star = checkpoint_name(solution.x, SOLUTION_NAME)
    jacobian = linearize(x_star, args).jacobian
    solution = solution._replace(x=x_star)
    diff, static = eqx.partition(args, eqx.is_inexact_array)
    diff_dot = jtu.tree_map(
        lambda a, t: None if a is None else (jnp.zeros_like(a) if t is None else t),
        diff, args_dot, is_leaf=lambda v: v is None)

    def res(x, d):
        return residual(x, eqx.combine(d, static))

    # Implicit function theorem: J dx* = -(dR/dargs) dargs.
    _, r_dot = jax.jvp(lambda d: res(solution.x, d)[0], (diff,), (diff_dot,))
    x_dot = -linear_solve(jacobian, r_dot)
    _, aux_dot = jax.jvp(lambda x, d: res(x, d)[1], (solution.x, diff), (x_dot, diff_dot))
    return solution, NewtonSolution(x_dot, aux_dot, None, None, None, None)
