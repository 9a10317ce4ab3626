"""Contact formulations: how a load step enforces the contact conditions (benchmarks spec 1.5 to 1.7).

One abstract interface, :class:`AbstractContactFormulation`, and three final strategies:

- :class:`Penalty` (``penalty``, spec 1.5): the regularised law, one Newton solve per step attempt;
- :class:`AugmentedLagrangian` (``auglag``, spec 1.6): the same law with multipliers, a Uzawa loop of
  Newton solves per attempt;
- :class:`Complementarity` (``lcp_lemke``, ``lcp_ssn``, spec 1.7): exact contact solved inside the
  Newton loop (:mod:`jaxfric.contact.exact`).

The load loop (:mod:`jaxfric.simulate`) never asks which one it holds: it asks the formulation to
solve a step attempt (:meth:`~AbstractContactFormulation.solve_step`) and reads the class's
declarations (whether the step's multipliers start from the last converged forces, whether a stiff
step may be softened by the continuation, whether an attempt without line search exists, which solver
counters are recorded). Adding a formulation is a subclass that answers the same questions.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import ClassVar, NamedTuple, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..fem.assembly import shared_trace
from ..numerics._checks import check_int, check_nonnegative, is_concrete
from ..numerics.newton import NewtonOptions, newton_solve
from ..numerics.results import Result
from .exact import exact_solve
from .rigid import max_penetration, pair_nodes, split_pairs
from .status import STICK
from .system import StepArgs, kept_predictor, linearize, residual

__all__ = ["ALGORITHMS", "DIFFERENTIABLE_ALGORITHMS", "AbstractContactFormulation", "Penalty",
           "AugmentedLagrangian", "Complementarity", "StepSolution", "formulation", "from_newton", "newton_step",
           "StiffPenalty", "ExactStartPenalty", "exact_start_point", "STIFF_PENALTY_RATIO"]


class StepSolution(NamedTuple):
    """Outcome of one load-step attempt: the Newton solution(s) summed over AL augmentations."""

    x: jax.Array
    aux: object
    iterations: jax.Array       # () Newton iterations, all augmentations included
    code: jax.Array             # () Result
    residual_norm: jax.Array
    residual_history: jax.Array  # of the last Newton solve
    augmentations: jax.Array    # () AL augmentations (0 for the penalty method)
    stats: jax.Array            # (3,) exact contact: Lemke pivots, SSN iterations, fallbacks
    hardest: jax.Array | None = None  # () the most iterations one Newton solve took (AL: of all the
    #                                    augmentations; None: ``iterations``)


def from_newton(sol, stats=None) -> StepSolution:
    """A single Newton solve as a step solution (no augmentation)."""
    stats = jnp.zeros(3, jnp.int32) if stats is None else stats
    return StepSolution(sol.x, sol.aux, sol.iterations, sol.code, sol.residual_norm, sol.residual_history,
                        augmentations=jnp.array(0, jnp.int32), stats=stats)


def newton_step(args: StepArgs, x0, x_ref, newton: NewtonOptions, search=True, stage=False) -> StepSolution:
    """A step attempt that is one Newton solve of :func:`jaxfric.contact.system.linearize` (the penalty law's,
    and a model's without tools)."""
    return from_newton(newton_solve(args, x0, x_ref, linearize=linearize, residual=residual, options=newton,
                               search=search, positions=stage))


class AbstractContactFormulation(eqx.Module):
    """What the load loop asks of a contact formulation.

    Class declarations (static):
        warm_start: a step's multipliers (``ContactStep.lam_n``) start from the last converged normal
            forces; otherwise they are zero (the penalty law: lambda_N = 0).
        continuation: a step that fails at the smallest increment may be solved through stages of
            softened penalties (:class:`jaxfric.loadpath.controller.StepControl`); the formulation then
            provides :meth:`continuation_stages` and :meth:`softened`.
        unsearched_retry: the step controller's last attempt at the smallest increment runs Newton
            without its line search (a formulation whose loop has no line search to switch off: no
            such attempt).
        one_newton_solve: an attempt is one Newton solve of :func:`jaxfric.contact.system.linearize`, so a
            driver may advance it one iteration at a time (:func:`jaxfric.loadpath.simulate.simulate_flat`).
        solver_stats: names of the history columns of ``History.solver_stats`` (empty: none kept).
        differentiable: steps carry derivatives (implicit function theorem).
    Every formulation's residual carries the damper of the step controller's stabilised attempt
    (``StepArgs.damping``: :func:`jaxfric.contact.system.linearize`, and the exact solvers' iterate).
    """

    warm_start: ClassVar[bool] = False
    continuation: ClassVar[bool] = False
    unsearched_retry: ClassVar[bool] = True
    one_newton_solve: ClassVar[bool] = False
    solver_stats: ClassVar[tuple] = ()
    differentiable: ClassVar[bool] = True

    @abc.abstractmethod
    def solve_step(self, args: StepArgs, x0, x_ref, newton: NewtonOptions, search=True,
                   stage=False) -> StepSolution:
        """Solve one load-step attempt from the initial guess ``x0``.

        ``x_ref``: the last converged unknowns (reference of Newton's increment test); ``search`` (may
        be traced) False switches Newton's line search off; ``stage`` (may be traced) True marks a
        continuation stage (Newton's round-off floor relative to the positions, :mod:`jaxfric.numerics.newton`).
        """

    @property
    def forces_at_any_gap(self) -> bool:
        """Static: an open pair carries a force however far it is from its tool (a smoothed law), so a
        step evaluates every pair (no pair pre-selection, :mod:`jaxfric.contact.preselection`)."""
        return False

    def continuation_stages(self, modulus) -> jax.Array:
        """() int32: the number m of softened stages for a sheet of modulus ``modulus`` (0: none)."""
        return jnp.array(0, jnp.int32)

    def softened(self, m) -> AbstractContactFormulation:
        """The formulation of continuation stage ``m`` (penalties / 10^m)."""
        raise NotImplementedError(f"{type(self).__name__} has no continuation")

    @property
    def proximity_band(self) -> int | None:
        """Static: the candidate nodes in exact contact's condensed problem (:class:`Complementarity`'s
        ``band``); None: every candidate, or no such problem."""
        return None

    def with_band(self, band: int | None) -> AbstractContactFormulation:
        """The formulation with proximity band ``band`` (:class:`Complementarity`).

        Raises:
            ValueError: the formulation has no proximity band, naming the field.
        """
        raise ValueError(f"field 'band': {type(self).__name__} has no proximity band")

    def widened(self, tools) -> AbstractContactFormulation | None:
        """The formulation with a wider proximity band (:class:`Complementarity`); None: no band to widen."""
        return None


class _Regularised(AbstractContactFormulation):
    """The penalty-regularised pair law (:mod:`jaxfric.contact.laws`) shared by :class:`Penalty` and
    :class:`AugmentedLagrangian`: eps_n, eps_t in N/mm per mm; ``smoothing`` (N/mm, 0: the exact
    law) smooths the normal and stick/slip kinks over a force band of that width, for gradient-based
    work. Whether the law is smoothed (``smooth``) is static: declared, or when not given, True
    unless ``smoothing`` is a concrete 0."""

    eps_n: jax.Array
    eps_t: jax.Array
    smoothing: jax.Array
    smooth: bool = eqx.field(static=True)

    def _set_penalties(self, eps_n, eps_t, smoothing, smooth):
        for name, v in (("eps_n", eps_n), ("eps_t", eps_t), ("smoothing", smoothing)):
            check_nonnegative(name, v)
        self.eps_n = jnp.asarray(eps_n, jnp.float64)
        self.eps_t = jnp.asarray(eps_t, jnp.float64)
        self.smoothing = jnp.asarray(smoothing, jnp.float64)
        # Undeclared: decided from the argument as given (inside jit, even a converted constant is a
        # tracer, and a traced smoothing must keep the smoothed law).
        if smooth is None:
            smooth = (not is_concrete(smoothing)) or float(np.asarray(smoothing)) > 0
        if not isinstance(smooth, bool):
            raise ValueError(f"field 'smooth' must be True, False or None, got {smooth!r}")
        self.smooth = smooth

    @property
    def forces_at_any_gap(self) -> bool:
        return self.smooth

    def __check_init__(self):
        if is_concrete(self.eps_n) and not float(self.eps_n) > 0:
            raise ValueError(f"field 'eps_n' must be > 0, got {float(self.eps_n)}")


class Penalty(_Regularised):
    """Penalty regularisation of contact and friction (spec 1.5, paper eq. 19): each attempt is one
    Newton solve with lambda_N = 0 and lambda_T = R_T,n (the last converged tangential force).

    Its stiff steps may be softened (:class:`jaxfric.loadpath.controller.StepControl`, ``continuation``): stage
    m solves with eps_n and eps_t divided by 10^m, from m = ceil(log10(eps_n / E)) down to 0.
    """

    continuation: ClassVar[bool] = True
    one_newton_solve: ClassVar[bool] = True

    def __init__(self, eps_n, eps_t, smoothing=0.0, smooth: bool | None = None):
        self._set_penalties(eps_n, eps_t, smoothing, smooth)

    def solve_step(self, args, x0, x_ref, newton, search=True, stage=False) -> StepSolution:
        return newton_step(args, x0, x_ref, newton, search, stage)

    def continuation_stages(self, modulus) -> jax.Array:
        """m = ceil(log10(eps_n / E)) clipped to [0, 12]: the first stage's penalty is of the order of
        the sheet's modulus E (none when eps_n <= E)."""
        m = jnp.ceil(jnp.log10(self.eps_n / modulus))
        return jnp.clip(jnp.nan_to_num(m), 0, 12).astype(jnp.int32)

    def softened(self, m) -> Penalty:
        """eps_n and eps_t divided by 10^m (m = 0: unchanged, bit for bit)."""
        scale = 10.0 ** (-jnp.asarray(m, jnp.float64))
        return eqx.tree_at(lambda law: (law.eps_n, law.eps_t), self, (self.eps_n * scale, self.eps_t * scale))


def _penalty_from_exact(law: Penalty, args: StepArgs, x0, x_ref, newton: NewtonOptions, search=True,
                        stage=False) -> StepSolution:
    """The penalty law's step attempt started from its own solution by exact contact's solver: the step
    solved by semismooth Newton on the Alart-Curnier equations with the penalty's compliance
    (:class:`Complementarity` with ``compliant``, :func:`exact_start_point`) from ``x0``, then the penalty's
    Newton solve from there (from ``x0`` where the compliant solve fails). The solution is the penalty law's;
    only Newton's starting point changes, and from the compliant solution the penalty's Newton solve
    converges on its first iteration (the unsmoothed law's: the smoothed law starts from the unsmoothed one's
    solution). No tangent reaches the compliant solve, which has no derivative: the step is
    differentiated at its converged solution, as :class:`Penalty`'s. ``iterations`` counts both solves'
    Newton iterations, ``hardest`` the larger of the two.

    ``args.contact.lam_n`` is the compliant solve's guess of its first active set (the last converged normal
    forces where the formulation's ``warm_start`` puts them there); the penalty solve takes lambda_N = 0."""
    start, penalty, compliant = exact_start_point(law, args, x0, x_ref, newton)
    sol = newton_step(penalty, start, x_ref, newton, search, stage)
    return sol._replace(iterations=compliant.iterations + sol.iterations,
                        hardest=jnp.maximum(compliant.iterations, sol.iterations))


def exact_start_point(law: Penalty, args: StepArgs, x0, x_ref, newton: NewtonOptions):
    """``(start, penalty_args, compliant)``: the penalty law's Newton start of :func:`_penalty_from_exact` (the
    solution of the compliant semismooth Newton solve for ``law``, or ``x0`` where that solve failed), the
    step's data with the penalty law's lambda_N = 0, and the compliant solve's :class:`StepSolution`. No
    tangent reaches the compliant solve."""
    contact = args.contact
    assert contact is not None   # a step with tools
    frozen = jax.tree_util.tree_map(lambda a: jax.lax.stop_gradient(a) if eqx.is_array(a) else a,
                                    (eqx.tree_at(lambda a: a.contact.law, args, law), x0, x_ref))
    solved = from_newton(*exact_solve(*frozen, options=newton, law=Complementarity("ssn", compliant=True)))
    ok = solved.code == Result.SUCCESS
    start = jnp.where(ok, solved.x, jax.lax.stop_gradient(x0))
    penalty = eqx.tree_at(lambda a: a.contact.lam_n, args, jax.tree_util.tree_map(jnp.zeros_like, contact.lam_n))
    return start, _continuing(penalty, solved, ok), solved


def _continuing(args: StepArgs, sol: StepSolution, ok) -> StepArgs:
    """``args`` for a Newton solve started at the converged point of ``sol`` where ``ok``: with the enhanced
    predictor of that point (:func:`~jaxfric.contact.system.kept_predictor`; no tangent reaches it, a
    starting value), as the load loop's next step starts from its last one's; ``args`` elsewhere."""
    if args.predictor is None:
        return args
    kept = jax.lax.stop_gradient(kept_predictor(cast(tuple, sol.aux)[1]))
    return args.with_carry(jnp.where(ok, kept, args.predictor))


class StiffPenalty(Penalty):
    """The penalty law for penalties far stiffer than a scene's own (:func:`formulation` picks it above
    ``stiff_above``: the scenes give ``STIFF_PENALTY_RATIO`` times their spec penalty). An attempt is
    the plain law's Newton solve; where that fails, the attempt is solved again by exact contact's
    semismooth Newton with the penalty's compliance (:func:`_penalty_from_exact`). Steps the plain law
    takes cost what they cost with it.

    Reason: at eps_n >> E a Newton iterate that moves a node by the sheet's compliance across a tool
    surface meets a force eps_n times the overshoot; on a curved tool a pair then 2-cycles between open
    and a spurious force, and steps are cut down to nothing (the Nine at eps_n = 1e9: thousands of cut
    steps, the history buffer full in the clamp). The semismooth Newton settles the active set on the
    linearised problem, where no iterate meets that overshoot, and its solution is the penalty law's, so
    the penalty's Newton solve converges on its first iteration.
    """

    one_newton_solve: ClassVar[bool] = False

    # Penalty's __init__, repeated: equinox would give this subclass Penalty's at run time, but type checkers
    # read the dataclass fields' signature (smooth required) for a Module without an __init__ of its own.
    def __init__(self, eps_n, eps_t, smoothing=0.0, smooth: bool | None = None):
        self._set_penalties(eps_n, eps_t, smoothing, smooth)

    def solve_step(self, args, x0, x_ref, newton, search=True, stage=False) -> StepSolution:
        plain = newton_step(args, x0, x_ref, newton, search, stage)

        def from_exact():
            sol = _penalty_from_exact(self, args, x0, x_ref, newton, search, stage)
            return sol._replace(iterations=plain.iterations + sol.iterations)

        def as_is():
            return plain._replace(hardest=plain.iterations)

        return jax.lax.cond(plain.code == Result.SUCCESS, as_is, from_exact)


class ExactStartPenalty(Penalty):
    """The penalty law with every step attempt solved first by exact contact's semismooth Newton with the
    penalty's compliance, then by the penalty's own Newton from that solution (:func:`_penalty_from_exact`;
    :func:`formulation` with ``exact_start``). The solution, its load path and its derivatives are the
    penalty law's; only where Newton starts changes, so the steps the plain law cuts are taken.

    Reason: from the load loop's guess the plain law spends most of its iterations and cut steps on
    pairs that open, close, stick and slip from one iterate to the next (docs/results.md, penalty
    iterations on the blankholder), which the active-set solve settles on each linearised problem; its
    solution is the penalty law's own, so the penalty's Newton solve then converges on its first iteration,
    which also gives the step its derivative. Measured in docs/results.md, "The penalty law and the
    augmented Lagrangian started from exact contact" (``python experiments/bench_exact_start.py``).

    Its multipliers start from the last converged normal forces (``warm_start``): they are the compliant
    solve's guess of its first active set, not the penalty law's lambda_N (0).
    """

    one_newton_solve: ClassVar[bool] = False
    warm_start: ClassVar[bool] = True

    def __init__(self, eps_n, eps_t, smoothing=0.0, smooth: bool | None = None):   # as StiffPenalty's
        self._set_penalties(eps_n, eps_t, smoothing, smooth)

    def solve_step(self, args, x0, x_ref, newton, search=True, stage=False) -> StepSolution:
        return _penalty_from_exact(self, args, x0, x_ref, newton, search, stage)


class AugmentedLagrangian(_Regularised):
    """Augmented Lagrangian (spec 1.6, paper eq. 20): the penalty law with multipliers, updated
    between converged Newton solves (lambda <- R, an Uzawa iteration) until the largest penetration
    AND the largest slip of a sticking pair over the step (the tangential stick error, which the
    tangential penalty alone leaves at R_T / eps_t) are at most ``target_gap`` (mm), at most
    ``max_augmentations`` times per step. The spec's test checks the normal gap only; without the
    tangential part, eps_t = mu eps_n = 1.5e4 N/mm leaves elastic slips of 1e-5 mm where the flat die's
    early stroke is 2.5e-5 mm per step, and its drawing curve is 3 % (of mu P) off the exact one.

    Multipliers start each step from the converged forces of the last one (warm start), so a step that
    already meets the target needs no augmentation.

    ``exact_start`` (static): the step is first solved with exact contact (:class:`Complementarity`,
    semismooth Newton), and the Uzawa iteration starts from that solution (and its elements' enhanced
    predictor) with its forces as the multipliers (where the exact solve fails: as without). The exact
    solution is a fixed point of the iteration (of the exact law; a smoothed law's lies near it): with
    lambda = its forces, every closed pair at zero gap and every sticking pair without slip gives back
    lambda, so the first Newton solve meets the target without an augmentation (measured: a step takes one
    Newton iteration more than ``lcp_ssn``'s on the Nine and on the blankholder, docs/results.md). Its
    derivative: the exact solve's (:mod:`jaxfric.contact.exact_derivative`) carried by the multipliers into
    the implicit function theorem of the AL's solve, which at the fixed point gives the exact step's
    derivative. ``iterations`` counts both solves' Newton iterations.
    """

    target_gap: jax.Array
    max_augmentations: int = eqx.field(static=True)
    exact_start: bool = eqx.field(static=True)
    warm_start: ClassVar[bool] = True

    def __init__(self, eps_n, eps_t, target_gap=1e-5, max_augmentations: int = 20, smoothing=0.0,
                 smooth: bool | None = None, exact_start: bool = False):
        self._set_penalties(eps_n, eps_t, smoothing, smooth)
        if not isinstance(exact_start, bool):
            raise ValueError(f"field 'exact_start' must be True or False, got {exact_start!r}")
        self.exact_start = exact_start
        check_nonnegative("target_gap", target_gap)
        if is_concrete(target_gap) and not float(target_gap) > 0:
            raise ValueError(f"field 'target_gap' must be > 0, got {float(target_gap)}")
        self.target_gap = jnp.asarray(target_gap, jnp.float64)
        checked = check_int("max_augmentations", max_augmentations, 1, 10_000)
        assert checked is not None
        self.max_augmentations = checked

    def solve_step(self, args, x0, x_ref, newton, search=True, stage=False) -> StepSolution:
        """Uzawa iteration: solve with the step's multipliers, then, while the step's largest
        penetration or stick slip exceeds the target, set lambda <- R and solve again. The first solve
        is the loop's first pass, so that the traced program holds one Newton solve (each copy costs
        compile time).

        The slip reference stays at the start of the step. Resetting it at each augmentation, as the
        spec words it, makes the tangential update telescope: R_T^(K) = lambda_T^(0) - eps_T (sum of
        the slips of all augmentations) = R_T,n - eps_T (slip since the step start), which is the
        penalty law itself, so the stick error could never fall below R_T / eps_t. With a fixed
        reference, a converged sticking pair has exactly zero slip over the step and the multiplier
        carries the whole stick force.
        """
        tools = args.contact.tools

        @shared_trace     # one trace for the loop's shapes (below) and its body
        def solve(a, lam_n, lam_t, x_start):
            step = eqx.tree_at(lambda c: (c.lam_n, c.lam_t), a.contact, (lam_n, lam_t))
            return newton_solve(eqx.tree_at(lambda b: b.contact, a, step), x_start, x_ref,
                                linearize=linearize, residual=residual, options=newton, search=search)

        lam_n0, lam_t0, x_first, iters0 = args.contact.lam_n, args.contact.lam_t, x0, jnp.array(0, jnp.int32)
        first_args = args
        if self.exact_start:   # static
            exact, _ = exact_solve(args, x0, x_ref, options=newton, law=Complementarity("ssn"))
            ok = exact.code == Result.SUCCESS
            out = exact.aux[2]
            on_exact = lambda e, a: jnp.where(ok, e, a)  # noqa: E731
            lam_n0 = jax.tree_util.tree_map(on_exact, split_pairs(tools, out["rn"]), lam_n0)
            lam_t0 = jax.tree_util.tree_map(on_exact, split_pairs(tools, out["rt"]), lam_t0)
            x_first, iters0 = jnp.where(ok, jax.lax.stop_gradient(exact.x), x0), exact.iterations
            first_args = _continuing(args, from_newton(exact), ok)

        def pending(c):
            sol, n_aug = c[:2]
            return (n_aug < 0) | ((sol.code == Result.SUCCESS) & (_constraint_error(sol.aux[2]) > self.target_gap))

        def body(c):
            sol, n_aug, iters, hardest = c
            out = sol.aux[2]
            first = n_aug < 0     # the step's own multipliers (the last converged forces) and start
            pick = lambda a, b: jnp.where(first, a, b)  # noqa: E731
            lam_n = jax.tree_util.tree_map(pick, lam_n0, split_pairs(tools, out["rn"]))
            lam_t = jax.tree_util.tree_map(pick, lam_t0, split_pairs(tools, out["rt"]))
            # With exact_start, the first solve continues from the exact solution's predictor; the later ones,
            # and every solve without it, from the step's.
            a = args
            if self.exact_start and args.predictor is not None:   # static
                a = args.with_carry(pick(first_args.predictor, args.predictor))
            new = solve(a, lam_n, lam_t, pick(x_first, sol.x))
            # After the last allowed augmentation the target must be met, or the attempt fails.
            exhausted = (n_aug + 1 >= self.max_augmentations) & (new.code == Result.SUCCESS) & (
                _constraint_error(new.aux[2]) > self.target_gap)
            code = jnp.where(exhausted, Result.AUGMENTATIONS, new.code).astype(jnp.int32)
            return new._replace(code=code), n_aug + 1, iters + new.iterations, jnp.maximum(hardest, new.iterations)

        def bounded(c, _):
            return jax.lax.cond(pending(c), body, lambda c: c, c), None

        shape = eqx.filter_eval_shape(solve, args, args.contact.lam_n, args.contact.lam_t, x0)
        sol0 = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), shape)
        # A scan of the first solve and every allowed augmentation, the passes after the last needed one
        # skipped, rather than a while_loop: the same passes, and reverse mode (jax.grad through
        # simulate_fixed) can differentiate a loop of known length.
        (sol, n_aug, iters, hardest), _ = jax.lax.scan(bounded, (sol0, jnp.array(-1, jnp.int32), iters0, iters0),
                                                       length=self.max_augmentations + 1)
        return StepSolution(sol.x, sol.aux, iters, sol.code, sol.residual_norm, sol.residual_history, n_aug,
                            jnp.zeros(3, jnp.int32), hardest)


def _constraint_error(contact_out: dict) -> jax.Array:
    """AL acceptance measure: largest penetration, and largest slip of a sticking pair (mm)."""
    stick_slip = jnp.where(contact_out["status"] == STICK, jnp.abs(contact_out["slip"]), 0.0)
    return jnp.maximum(max_penetration(contact_out["status"], contact_out["gap"]), jnp.max(stick_slip))


SOLVERS = ("ssn", "lemke")


class Complementarity(AbstractContactFormulation):
    """Exact contact (spec 1.7, algorithms ``lcp_lemke`` and ``lcp_ssn``): at every Newton iterate the
    contact conditions of the linearised problem are solved exactly; no penalty, no penetration beyond
    the Newton tolerance (:mod:`jaxfric.contact.exact`). Its multipliers (the last converged forces) only
    guess the first active set. Its steps are differentiated on their converged active set
    (:mod:`jaxfric.contact.exact_derivative`).

    Attributes:
        solver (static):
            "ssn" (``lcp_ssn``): semismooth Newton on the Alart-Curnier equations of every candidate
            inside the global Newton loop, on the block-tridiagonal system itself.
            "lemke" (``lcp_lemke``): Lemke's pivoting on the condensed problem, on the host through
            ``jax.pure_callback``.
        band: static number of candidate nodes in the condensed problem (the proximity band: the
            nodes nearest to a tool). None: every candidate node. Too small a band is detected (a node
            outside it penetrates) and fails the attempt. Not used by "ssn" (every candidate).
        ssn_max_iter: semismooth Newton iterations on one linearised problem (static): "ssn" then
            takes its last active set. Not used by "lemke".
        search: static, "lemke" only: line-search its Newton steps on the semismooth merit as "ssn"'s
            are (:mod:`jaxfric.contact.exact`, step 6), so that Lemke takes the steps "ssn" takes. False:
            full Newton steps.
        compliant: static, "ssn" only: solve the penalty law of the step's ``contact.law`` instead of exact
            contact, its compliance written into the Alart-Curnier equations
            (:class:`~jaxfric.contact.exact_active_set.Compliance`): the start of
            :class:`ExactStartPenalty`'s attempts, which is not differentiated.
    """

    solver: str = eqx.field(static=True, default="ssn")
    band: int | None = eqx.field(static=True, default=None)
    ssn_max_iter: int = eqx.field(static=True, default=50)
    search: bool = eqx.field(static=True, default=True)
    compliant: bool = eqx.field(static=True, default=False)
    warm_start: ClassVar[bool] = True
    unsearched_retry: ClassVar[bool] = False
    solver_stats: ClassVar[tuple] = ("lcp_pivots", "ssn_iters", "ssn_fallbacks")
    differentiable: ClassVar[bool] = True

    def __check_init__(self):
        if self.solver not in SOLVERS:
            raise ValueError(f"field 'solver' must be one of {', '.join(map(repr, SOLVERS))}, got {self.solver!r}")
        check_int("band", self.band, optional=True)
        check_int("ssn_max_iter", self.ssn_max_iter, 1, 10_000)
        if self.compliant and self.solver != "ssn":
            raise ValueError(f"field 'compliant' needs solver 'ssn', got {self.solver!r}")

    def solve_step(self, args, x0, x_ref, newton, search=True, stage=False) -> StepSolution:
        sol, stats = exact_solve(args, x0, x_ref, options=newton, law=self)
        return from_newton(sol, stats)

    @property
    def proximity_band(self) -> int | None:
        return self.band

    def with_band(self, band: int | None) -> Complementarity:
        return dataclasses.replace(self, band=band)

    def widened(self, tools) -> Complementarity | None:
        """This formulation with twice the proximity band, or every candidate node of ``tools`` where
        that reaches their number; None where the band cannot grow ("ssn", or every candidate already
        in it). The chunked driver widens a band that ends a run with ``Result.BAND_FULL``
        (:func:`jaxfric.loadpath.controller.band_full`)."""
        n = np.unique(pair_nodes(tools)).size
        if self.solver != "lemke" or self.band is None or self.band >= n:
            return None
        return self.with_band(None if 2 * self.band >= n else 2 * self.band)


#: A scene's penalty law is :class:`StiffPenalty` above this many times its spec penalty: the Nine's,
#: the bead's and the blankholder's 1e5 N/mm (0.5 E) then from 1e7, the flat die's 1e9 (whose straight
#: die the plain law holds at 1e9 and 1e12 with eps_T = eps_N) from 1e11.
STIFF_PENALTY_RATIO = 100.0

# The algorithm identifiers (outputs spec section 1) and the formulation class of each.
_CLASSES: dict[str, type[AbstractContactFormulation]] = {
    "penalty": Penalty, "auglag": AugmentedLagrangian, "lcp_lemke": Complementarity, "lcp_ssn": Complementarity}
ALGORITHMS = tuple(_CLASSES)
DIFFERENTIABLE_ALGORITHMS = tuple(name for name, cls in _CLASSES.items() if cls.differentiable)


def formulation(algorithm: str, eps_n, eps_t, target_gap, band: int | None = None, smoothing=0.0,
                max_augmentations: int = 20, stiff_above=None, search: bool = True,
                exact_start: bool = False) -> AbstractContactFormulation:
    """The contact formulation of an algorithm identifier (outputs spec section 1); ``smoothing`` > 0
    (N/mm) smooths the penalty and AL laws (:mod:`jaxfric.contact.laws`); exact contact has none.
    ``max_augmentations`` is the AL's limit per step attempt (spec 1.6: 20). A concrete penalty eps_n
    above ``stiff_above`` (N/mm per mm; None: never) gets :class:`StiffPenalty`. ``search``: ``lcp_lemke``'s
    line search (:class:`Complementarity`); the other algorithms ignore it. ``exact_start``: the penalty law's
    attempts start from the compliant semismooth solve (:class:`ExactStartPenalty`, whatever eps_n), the
    augmented Lagrangian's from exact contact (:class:`AugmentedLagrangian`'s ``exact_start``); exact contact
    ignores it."""
    if algorithm in ("lcp_lemke", "lcp_ssn") and smoothing != 0:
        raise ValueError(f"field 'smoothing' = {smoothing!r} applies to algorithms penalty and auglag only; "
                         f"exact contact ({algorithm}) has no smoothed law")
    if algorithm == "penalty":
        if exact_start:
            return ExactStartPenalty(eps_n, eps_t, smoothing)
        stiff = stiff_above is not None and is_concrete(eps_n) and float(eps_n) > float(stiff_above)
        return (StiffPenalty if stiff else Penalty)(eps_n, eps_t, smoothing)
    if algorithm == "auglag":
        return AugmentedLagrangian(eps_n, eps_t, target_gap, max_augmentations, smoothing=smoothing,
                                   exact_start=bool(exact_start))
    if algorithm == "lcp_lemke":
        return Complementarity("lemke", band, search=bool(search))
    if algorithm == "lcp_ssn":
        return Complementarity("ssn", band)
    raise ValueError(f"unknown algorithm {algorithm!r}; choose one of {', '.join(ALGORITHMS)}")
