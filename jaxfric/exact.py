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
  whose active set settled. (Solving such iterates the condensed way instead was tried: on the
  three-cylinder bench it cost 7.8 s against 4.6 s, for 84 against 88 steps.) The Newton step is
  line-searched on the semismooth residual (:func:`semismooth_merit`: the equilibrium rows with each candidate's
  rows replaced by its Alart-Curnier residual), quartering a step that raises it, at most twice.
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
   state fails the attempt (:attr:`~jaxfric.results.Result.CONTACT_BAND`).
3. Condensation on the band dofs c (spec 1.7 step 2), with the block-tridiagonal structure kept:
   ``K_ff^-1`` is the block-Thomas solve of K with the band dofs decoupled (their rows and columns
   replaced by a scaled identity), applied to the 2 n_c + 1 columns ``[K_fc | b_f]`` in one sweep:

       K* = K_cc - K_cf K_ff^-1 K_fc,     r* = b_c - K_cf K_ff^-1 b_f,

   then rotated into each band pair's (n, t) frame.
4. The linearised contact problem ``K* du_c = r* + p`` with ``g_N = g^i + du_N - (e_q . n) dq``,
   ``s = s^i + du_T - (e_q . t) dq`` and Signorini-Coulomb, plus the force balance of the force-driven
   tool (:mod:`jaxfric.contact_lcp`), by Lemke's pivoting (:mod:`jaxfric.lemke`, NumPy on the host
   through ``jax.pure_callback``), whose answer is solved again on its own piece and, where it lies on a
   piece boundary within its round-off, settled by a few semismooth Newton iterations on the same
   problem (:func:`jaxfric.alart_curnier.polish`).
5. Back-substitution ``du_f = K_ff^-1 (b_f - K_fc du_c)``; x <- x + (du, dq).

Convergence (spec 1.7 step 7): the bulk residual with the contact forces of the last solve,
``f_int - f_c(p)`` at the new iterate, passes the Newton test of :mod:`jaxfric.newton` (residual and
increment), and no pair changed its status (open / stick / slip from the forces, spec section 0).

Not differentiable: exact complementarity has no derivative where a pair changes status, and the
derivative of the converged step on a fixed status would need the active-set Jacobian. Gradients use
the penalty or augmented Lagrangian laws (with their optional smoothing); differentiating a run with
:class:`~jaxfric.contact.Complementarity` raises.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp

from .contact import pair_mu
from .exact_active_set import active_set_step, contact_frames, semismooth_merit
from .exact_condensed import contact_newton_step
from .exact_iterate import Iterate, iterate_residual, linearize_iterate, pair_status
from .newton import NewtonOptions, NewtonSolution
from .results import Result

__all__ = ["exact_solve"]


def _contact_out(it: Iterate, p, tool_f, status):
    return dict(q=it.q, force=tool_f, rn=p[:, 0], rt=p[:, 1], zeta=it.zeta, gap=it.gap, normal=it.normal,
                status=status, slip=it.slip)


class _Trial(NamedTuple):
    """A Newton direction and the step length tried along it (the in-loop solver's line search)."""

    dx: jax.Array
    alpha: jax.Array     # () step length of the trial (1, 1/4 or 1/16 of dx)
    p_new: jax.Array     # (m, 2) forces the direction predicts (the hint of the trials' merit)
    in_band: jax.Array
    stats: jax.Array     # (3,) of the direction's solve
    lcp_ok: jax.Array
    merit: jax.Array     # () the merit at the point the direction starts from (with the direction's hint)
    frames: object       # Frames there (constants of the merit), or None without a search


def _exact_newton(args, x0, x_ref, options: NewtonOptions, law):
    c = args.contact
    mu_pairs = pair_mu(c.tools, c.mu)
    m = mu_pairs.shape[0]
    pen_tol = 10.0 * options.du_atol

    def classify(k, x, it, R, dx_norm, same, band_ok, lcp_ok):
        r_norm = jnp.max(jnp.abs(R))
        leaves = (R, it.f_int, it.K.diag, it.gap)
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in leaves]))
        scale = jnp.max(jnp.abs(it.f_int))
        res_ok = r_norm <= options.atol + options.rtol * jnp.maximum(scale, 1e-6)
        dx_ok = dx_norm <= options.du_atol + options.du_rtol * jnp.max(jnp.abs(x - x_ref))
        done = (k >= 1) & res_ok & dx_ok & same
        # A band too small shows as a converged state with a penetrating outsider, or as a Newton loop
        # that cannot settle because the outsiders enter and leave the band: both are reported as such.
        out_of_iterations = k >= options.max_iterations
        code = jnp.select(
            [~finite, ~lcp_ok, it.det_min <= 0.0, (done | out_of_iterations) & ~band_ok, done, out_of_iterations],
            [Result.NONFINITE, Result.LCP_FAILED, Result.INVERTED_ELEMENT, Result.CONTACT_BAND, Result.SUCCESS,
             Result.MAX_ITERATIONS], Result.CONTINUE)
        return code.astype(jnp.int32), r_norm

    search = law.solver == "ssn" and options.line_search   # static
    step = active_set_step if law.solver == "ssn" else contact_newton_step
    no_stats = jnp.zeros(3, jnp.int32)

    # The loop evaluates one point per pass (the initial guess first, then each trial), then takes the
    # next trial: a new direction, the same one shortened, or none once the step is decided. So the
    # traced program holds one linearisation and one direction solve (each copy costs compile time).
    def body(carry):
        k, x, it, p, status, x_t, tr, _, r_hist, stats = carry     # k: index of the point x_t
        it_t = linearize_iterate(x_t, args)
        R, _ = iterate_residual(x_t, it_t, tr.p_new, args)
        status_new = pair_status(tr.p_new, mu_pairs)
        penetrating = it_t.valid & (it_t.gap < -pen_tol)
        band_ok = ~jnp.any(~tr.in_band & penetrating) | (k == 0)
        # An open pair of the band that penetrates at the new iterate closes at the next one.
        settled = jnp.all(status_new == status) & ~jnp.any(tr.in_band & penetrating & (tr.p_new[:, 0] <= 0.0))
        if law.solver == "ssn":  # static: no step converges on an active set that did not settle,
            settled = settled & (tr.stats[2] == 0) & (tr.alpha == 1.0)   # nor on a shortened step
        step_norm = jnp.max(jnp.abs(tr.alpha * tr.dx))
        code, r_norm = classify(k, x_t, it_t, R, step_norm, settled, band_ok, tr.lcp_ok)
        reject = jnp.array(False)
        if search:
            # Line search on the semismooth residual (:func:`semismooth_merit`): a step that raises it is retried
            # at a quarter, then a sixteenth of its length, which is then kept. Where the active set
            # jumps (a node reaching or leaving a tool on a soft, slipping strip) the full step can
            # overshoot: on the Nine test the residual then grew tenfold per iteration until an element
            # inverted, and the step was cut three times (about 75 iterations lost per event, one event
            # per node spacing drawn).
            # The trial is measured with the forces the direction predicts (tr.p_new), which are the
            # hint the next direction's merit starts from, so the merits of accepted iterates form one
            # non-increasing sequence. Measured with the direction's own hint instead, each new
            # direction re-based the merit: where a candidate node has a prescribed dof (the Nine's
            # entry-guided tail reaching A), f~ there is hint-driven and the re-based merit of the same
            # point rose 5 to 20 times per iteration, so the iterates drifted along the strip's soft
            # draw-in mode (Nine 300 x 3 at 0.4 mm increments: residual 4.6e-3 -> 37 N/mm over 30
            # iterations of a 6.6e-4 mm step, and the run stopped at U = 43.7 mm).
            worse = ~(semismooth_merit(x_t, it_t, args, tr.p_new, tr.frames) <= tr.merit)
            reject = (k > 0) & worse & (tr.alpha > 1.0 / 16.0) & (code != Result.SUCCESS)
            code = jnp.where(reject & (k < options.max_iterations), Result.CONTINUE, code).astype(jnp.int32)
        keep = lambda a, b: jnp.where(reject, a, b)  # noqa: E731
        x, it = keep(x, x_t), jax.tree_util.tree_map(keep, it, it_t)
        p, status = keep(p, tr.p_new), keep(status, status_new)

        def fresh():
            hint = jnp.where(k == 0, p_step, p)
            if not search:
                dx, p_new, in_band, s, lcp_ok = step(it, args, x, p, law, hint)
                return _Trial(dx, jnp.array(1.0), p_new, in_band, s, lcp_ok, tr.merit, tr.frames), s
            # The frames (nodes, constants, kappa rows) serve the direction and the merit alike.
            frames = contact_frames(it, args)
            dx, p_new, in_band, s, lcp_ok = active_set_step(it, args, x, p, law, hint, frames=frames)
            merit = semismooth_merit(x, it, args, hint, frames[0])
            return _Trial(dx, jnp.array(1.0), p_new, in_band, s, lcp_ok, merit, frames[0]), s

        def shorter():
            return tr._replace(alpha=0.25 * tr.alpha), no_stats

        def stop():
            return tr, no_stats

        branch = jnp.where(code != Result.CONTINUE, 2, jnp.where(reject, 1, 0))
        tr, s = jax.lax.switch(branch, [fresh, shorter, stop])
        return (k + 1, x, it, p, status, x + tr.alpha * tr.dx, tr, code, r_hist.at[k].set(r_norm),
                stats + s)

    zeros = lambda tree: jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), tree)  # noqa: E731
    it_shape = eqx.filter_eval_shape(linearize_iterate, x0, args)
    frames0 = zeros(eqx.filter_eval_shape(lambda i, a: contact_frames(i, a)[0], it_shape, args)) if search else None
    p0 = jnp.zeros((m, 2))
    # The last converged forces (simulate passes them as lam_n, lam_t): the first active set.
    p_step = jnp.stack([jnp.concatenate(c.lam_n), jnp.concatenate(c.lam_t)], -1)
    tr0 = _Trial(jnp.zeros_like(x0), jnp.array(1.0), p0, jnp.zeros(m, bool), no_stats, jnp.array(True),
                 jnp.array(jnp.inf), frames0)
    r_hist = jnp.full(options.max_iterations + 1, jnp.nan)
    carry = (jnp.array(0, jnp.int32), x0, zeros(it_shape), p0, jnp.zeros(m, jnp.int8), x0, tr0,
             jnp.array(Result.CONTINUE, jnp.int32), r_hist, no_stats)
    k, x, it, p, status, _, _, code, r_hist, stats = jax.lax.while_loop(lambda c: c[7] == Result.CONTINUE, body,
                                                                        carry)
    _, tool_f = iterate_residual(x, it, p, args)
    aux = (it.f_int, it.states, _contact_out(it, p, tool_f, status))
    return NewtonSolution(x, aux, k - 1, code, r_hist[k - 1], r_hist), stats


@eqx.filter_custom_jvp
def exact_solve(args, x0, x_ref, *, options: NewtonOptions, law):
    """Solve one load step with exact contact from the initial guess ``x0`` (``x_ref``: the last
    converged state, reference of the increment test).

    Returns ``(NewtonSolution, stats)`` with ``stats`` = (Lemke pivots, semismooth Newton iterations
    (with ``lcp_lemke``: those refining its answers), ``lcp_ssn`` iterations whose active set did not
    settle) summed over the step's iterations; the solution's ``aux`` has the layout of the penalty
    path: (f_int, material states, contact outputs).
    """
    return _exact_newton(args, x0, x_ref, options, law)


@exact_solve.def_jvp
def _exact_solve_jvp(primals, tangents, *, options, law):
    raise NotImplementedError(
        "derivatives of a run with exact contact (Complementarity, algorithms lcp_lemke / lcp_ssn) are not "
        "defined; differentiate with Penalty or AugmentedLagrangian (optionally with smoothing) instead")
