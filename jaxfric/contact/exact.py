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
  whose active set settled. A pass depends on its active set alone, so once a set repeats one of the
  last ``CYCLE_WINDOW`` the passes repeat with that period: the loop then solves the set the last of the
  ``ssn_max_iter`` passes would solve, and stops there (the same increment, bit for bit, without the
  passes in between: on the Nine's entry channel, cycles of period 5 between the channel's faces).
  (Solving such iterates the condensed way instead was tried: on the three-cylinder bench it cost 7.8 s
  against 4.6 s, for 84 against 88 steps.) The Newton step is
  line-searched on the semismooth residual (:func:`semismooth_merit`: the equilibrium rows with each candidate's
  rows replaced by its Alart-Curnier residual), quartering a step that raises it, at most twice. The
  trial is measured with the forces its direction predicts, which are the hint the next direction's
  merit starts from, so the merits of accepted iterates form one non-increasing sequence. (With each
  direction's own hint, a candidate node with a prescribed dof, such as the Nine's entry-guided tail,
  re-bases the merit at every iteration and the iterates drift along the strip's soft draw-in mode:
  ``test_line_search_merit_of_accepted_iterates_does_not_jump_up_between_directions``.) The step that
  brings a node to a tool or lifts it off can overshoot on a soft, slipping strip; the line search keeps
  the residual from growing until an element inverts.
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
   state fails the attempt (:attr:`~jaxfric.numerics.results.Result.CONTACT_BAND`), and the run widens the
   band and tries the step again (:func:`jaxfric.loadpath.controller.band_full`).
3. Condensation on the band dofs c (spec 1.7 step 2), with the block-tridiagonal structure kept:
   ``K_ff^-1`` is the block-Thomas solve of K with the band dofs decoupled (their rows and columns
   replaced by a scaled identity), applied to the 2 n_c + 1 columns ``[K_fc | b_f]`` in one sweep:

       K* = K_cc - K_cf K_ff^-1 K_fc,     r* = b_c - K_cf K_ff^-1 b_f,

   then rotated into each band pair's (n, t) frame.
4. The linearised contact problem ``K* du_c = r* + p`` with ``g_N = g^i + du_N - (e_q . n) dq``,
   ``s = s^i + du_T - (e_q . t) dq`` and Signorini-Coulomb, plus the force balance of the force-driven
   tool (:mod:`jaxfric.contact.lcp`), by Lemke's pivoting (:mod:`jaxfric.contact.lemke`, NumPy on the host
   through ``jax.pure_callback``), whose answer is solved again on its own piece and, where it lies on a
   piece boundary within its round-off, settled by a few semismooth Newton iterations on the same
   problem (:func:`jaxfric.contact.alart_curnier.polish`).
5. Back-substitution ``du_f = K_ff^-1 (b_f - K_fc du_c)``; x <- x + (du, dq).
6. The steps are line-searched on the semismooth residual as ``lcp_ssn``'s (the merit is the problem's,
   not the direction's, so it measures Lemke's trials as well), except the first of each load step
   (``Complementarity(search=True)``, the default; the scenes' ``lemke_search``). Full Lemke steps
   (``search=False``) invert elements or end on rays on steps that ``lcp_ssn`` takes: replaying
   ``lcp_ssn``'s steps at the scenes' defaults (``python experiments/studies.py common_steps``), full steps
   take 1345 and 1446 steps for the Nine's 823 and 815 (1112 and 1252 s) and 1 to 10 extra steps on the
   blankholder, searched steps exactly the plan's, at 252 and 221 s on the Nine and 1.07 to 1.36 times the
   full steps' time on the blankholder, with forces within 1.7e-7 of the force scale of ``lcp_ssn``'s and
   the same numbers of closed and slipping pairs at every step end. Searching the first step too doubles
   the flat die's Newton iterations (12,232 against 6,170 at 24 x 2 drawn 0.3 mm: that step starts from
   the last converged forces, which the condensed solve replaces at once).

The iterations are those of the one Newton loop (:func:`jaxfric.numerics.newton.newton_pass`): this module
provides the problem it solves, :class:`ExactContactProblem` (the point's evaluation, the semismooth
or condensed direction, the status test).

Convergence (spec 1.7 step 7): the bulk residual with the contact forces of the last solve,
``f_int - f_c(p)`` at the new iterate, passes the Newton test of :mod:`jaxfric.numerics.newton` (residual and
increment), and no pair changed its status (open / stick / slip from the forces, spec section 0).

Derivatives (forward and reverse mode): a converged step is differentiated by the implicit function
theorem on its final active set, with the matrix of the semismooth Newton pass
(:mod:`jaxfric.contact.exact_derivative`): exact wherever no pair sits on a status switch, the final
piece's one-sided derivative where one does, and non-finite (not wrong) where a closed candidate node has
a prescribed dof.
"""

from __future__ import annotations

from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.ad_checkpoint import checkpoint_name

from ..numerics.newton import (
    SOLUTION_NAME,
    AbstractNewtonProblem,
    Evaluation,
    NewtonOptions,
    NewtonSolution,
    Trial,
    carry_of,
    newton_loop,
    newton_result,
    with_carry,
    without_carry,
)
from .exact_active_set import active_set_step, compliance_of, contact_frames, frames_at_forces, semismooth_merit
from .exact_condensed import contact_newton_step
from .exact_derivative import exact_step_tangents
from .exact_iterate import Iterate, iterate_residual, linearize_iterate, pair_status
from .preselection import holds
from .rigid import pair_friction, pair_mu, pair_speeds

__all__ = ["ExactContactProblem", "exact_solve"]


def _contact_out(it: Iterate, p, tool_f, status):
    return dict(q=it.q, force=tool_f, rn=p[:, 0], rt=p[:, 1], zeta=it.zeta, gap=it.gap, normal=it.normal,
                status=status, slip=it.slip)


class Prediction(NamedTuple):
    """What an exact-contact direction predicts besides the step (:attr:`jaxfric.numerics.newton.Trial.data`)."""

    p: jax.Array         # (m, 2) the pairs' forces (R_N, R_T): the hint of the trial's merit
    in_band: jax.Array   # (m,) bool: the pair's node was in the solved problem
    frames: Any          # Frames at the direction's start (constants of the merit), or None without a search
    enhanced: Any = None  # the elements' enhanced predictor the trial is evaluated with (StepArgs.predictor)


class Point(NamedTuple):
    """An exact-contact iterate (:attr:`jaxfric.numerics.newton.Evaluation.state`)."""

    it: Iterate
    p: jax.Array             # (m, 2) the forces of the direction that reached it
    status: jax.Array        # (m,) their status (open / stick / slip)
    penetrating: jax.Array   # (m,) bool: the pair's node lies inside its tool beyond the tolerance


class ExactContactProblem(AbstractNewtonProblem):
    """One load step with exact contact as a Newton problem (module doc): the direction solves the
    linearised complementarity problem (``law.solver``), and a step converges only where no pair changed
    its status, no open pair of the solve penetrates, and (solver "ssn") the active set settled on a full
    step."""

    law: Any                                   # the Complementarity formulation (static fields only)
    options: NewtonOptions
    searches_first_step: ClassVar[bool] = True

    @property
    def searched(self) -> bool:   # static: "ssn" searches on the semismooth merit, "lemke" on request (step 6)
        return self.options.line_search and (self.law.solver == "ssn" or self.law.search)

    def start(self, x0, args) -> Trial:
        m = pair_mu(args.contact.tools, args.contact.mu).shape[0]
        frames = None
        if self.searched:
            it_shape = eqx.filter_eval_shape(linearize_iterate, x0, args)
            shapes = eqx.filter_eval_shape(lambda i, a: contact_frames(i, a)[0], it_shape, args)
            frames = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), shapes)
        return Trial(jnp.zeros_like(x0), jnp.array(1.0), jnp.array(jnp.inf), jnp.array(True), jnp.zeros(3, jnp.int32),
                     Prediction(jnp.zeros((m, 2)), jnp.zeros(m, bool), frames, carry_of(args)))

    def evaluate(self, x, trial, args) -> Evaluation:
        pred = trial.data
        it = linearize_iterate(x, with_carry(args, pred.enhanced))
        R, _ = iterate_residual(x, it, pred.p, args)
        c = args.contact
        status = pair_status(pred.p, pair_friction(c.tools, c.mu, args.mesh.nodes, pred.p[:, 0], pair_speeds(c)))
        penetrating = it.valid & (it.gap < -10.0 * self.options.du_atol)
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in (R, it.f_int, it.K.diag, it.gap)]))
        merit = semismooth_merit(x, it, args, pred.p, pred.frames, self.compliance(args)) if self.searched else None
        n = args.mesh.n_dofs
        return Evaluation(R, jnp.max(jnp.abs(it.f_int)), finite, ~(it.det_min <= 0.0),
                          Point(it, pred.p, status, penetrating), merit=merit,
                          in_band=~jnp.any(~pred.in_band & penetrating),
                          preselected=holds(c, x[:n].reshape(-1, 2), it.q), inner=it.enhanced_gap)

    def compliance(self, args):
        """The penalty law's compliance where the law is compliant (:class:`~.exact_active_set.Compliance`)."""
        return compliance_of(args) if self.law.compliant else None

    def settled(self, new, old, trial) -> jax.Array:
        pred = trial.data
        # An open pair of the solve that penetrates at the new iterate closes at the next one.
        settled = (jnp.all(new.state.status == old.state.status)
                   & ~jnp.any(pred.in_band & new.state.penetrating & (pred.p[:, 0] <= 0.0)))
        if self.law.solver == "ssn":   # static: not on an active set that did not settle
            settled = settled & (trial.stats[2] == 0)
        return settled & (trial.alpha == 1.0)   # nor on a shortened step

    def direction(self, x, point, args, first) -> Trial:
        it, p = point.state.it, point.state.p
        c = args.contact
        # The first direction's active set: the last converged forces (the step passes them as lam_n, lam_t).
        p_step = jnp.stack([jnp.concatenate(c.lam_n), jnp.concatenate(c.lam_t)], -1)
        hint = jnp.where(first, p_step, p)
        if not self.searched:
            step = active_set_step if self.law.solver == "ssn" else contact_newton_step
            dx, p_new, in_band, stats, solved = step(it, args, x, p, self.law, hint)
            return Trial(dx, jnp.array(1.0), jnp.array(jnp.inf), solved, stats,
                         Prediction(p_new, in_band, None, it.predictor))
        # The frames (nodes, constants, kappa rows) serve the direction and the merit alike.
        frames = contact_frames(it, args)
        frames = (frames_at_forces(frames[0], args, hint), frames[1])
        if self.law.solver == "ssn":   # static
            dx, p_new, in_band, stats, solved = active_set_step(it, args, x, p, self.law, hint, frames=frames)
        else:
            dx, p_new, in_band, stats, solved = contact_newton_step(it, args, x, p, self.law, hint)
        merit = semismooth_merit(x, it, args, hint, frames[0], self.compliance(args))
        return Trial(dx, jnp.array(1.0), merit, solved, stats, Prediction(p_new, in_band, frames[0], it.predictor))

    def aux(self, x, point, args):
        it, p = point.state.it, point.state.p
        _, tool_f = iterate_residual(x, it, p, args)
        return it.f_int, it.states, _contact_out(it, p, tool_f, point.state.status)


class LemkeContactProblem(ExactContactProblem):
    """:class:`ExactContactProblem` with Lemke's condensed direction, whose first step of a load step is
    not searched (module doc, step 6)."""

    searches_first_step: ClassVar[bool] = False


@eqx.filter_custom_jvp
def exact_solve(args, x0, x_ref, *, options: NewtonOptions, law):
    """Solve one load step with exact contact from the initial guess ``x0`` (``x_ref``: the last
    converged state, reference of the increment test).

    Returns ``(NewtonSolution, stats)`` with ``stats`` = (Lemke pivots, semismooth Newton iterations
    (with ``lcp_lemke``: those refining its answers), ``lcp_ssn`` iterations whose active set did not
    settle) summed over the step's iterations; the solution's ``aux`` has the layout of the penalty
    path: (f_int, material states, contact outputs).
    """
    problem = (ExactContactProblem if law.solver == "ssn" else LemkeContactProblem)(law, options)
    c = newton_loop(problem, args, x0, x_ref, options)
    solution: NewtonSolution = newton_result(c, problem, args)
    return solution, c.stats


@exact_solve.def_jvp
def _exact_solve_jvp(primals, tangents, *, options, law):
    if law.compliant:
        raise NotImplementedError("a compliant exact solve (the penalty law's start) has no derivative: "
                                  "differentiate the penalty law's own step")
    args, x0, x_ref = primals
    solution, stats = exact_solve(args, x0, x_ref, options=options, law=law)
    # The derivative's evaluations condense the elements exactly (no carried predictor).
    args, args_dot = without_carry(args), without_carry(tangents[0])
    # The converged point and its contact forces are all the derivative needs: named as the penalty
    # path's solution (SOLUTION_NAME), so that a checkpointed load loop keeps them and its backward pass
    # does not run the Newton loop again.
    x_star = checkpoint_name(solution.x, SOLUTION_NAME)
    _, _, c = solution.aux
    p_star = checkpoint_name(jnp.stack([c["rn"], c["rt"]], -1), SOLUTION_NAME)
    x_dot, aux_dot = exact_step_tangents(args, args_dot, x_star, p_star, _contact_out)
    solution = solution._replace(x=x_star)
    return (solution, stats), (NewtonSolution(x_dot, aux_dot, None, None, None, None), None)
