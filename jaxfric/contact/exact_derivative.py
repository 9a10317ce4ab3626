"""Derivatives of a converged exact-contact step by the implicit function theorem on its active set.

A step converged by :mod:`jaxfric.contact.exact` (``lcp_ssn`` or ``lcp_lemke``) solves, on its final
active set, the semismooth system of :func:`jaxfric.contact.exact_active_set.piece_system`:

    Phi(x, args) = 0:  the equilibrium rows f_int(x) = 0 of the free dofs, kappa (u - u_presc) = 0 on the
    prescribed ones, each candidate node's two rows replaced by its Alart-Curnier piece
    C_a = W_F (n, t)^T f~_a + W_K (g_N, s) (open: the node's force is zero; stick: g_N = s = 0; slip:
    g_N = 0 and R_T = mu xi R_N), and the force-driven tool's balance.

On that piece Phi is smooth, so where no pair sits on a status switch the converged x*(args) is
differentiable and ``dPhi/dx dx* = -dPhi/dargs dargs``; dPhi/dx is the matrix the semismooth Newton
pass assembles (the block-tridiagonal tangent with the candidates' rows combined, bordered by the
driven tool's row), so the derivative costs one linearisation and one structured solve per step, as
the penalty path's (:func:`jaxfric.numerics.newton.newton_solve`). The contact forces, tool forces,
stresses and history follow by a forward derivative of the step's outputs along (dx*, dargs).

Held constant (their derivatives multiply zeros at the solution): the Alart-Curnier constants c_N, c_T
(they scale g_N and s, which vanish on closed pieces), the kappa of the prescribed rows (which scales
u - u_presc = 0), and each candidate node's pair. Friction coefficients, tool positions and dimensions,
material parameters and the prescribed values carry their derivatives.

With a friction law of the pressure (:mod:`jaxfric.contact.friction`) the slip row is
C_T = R_T - mu(R_N) xi (R_N - c_N g_N): the solver converges mu as a fixed point (each iteration's
coefficients at the last forces), and the derivative takes the row as a function of R_N, mu(R_N) from
the node's equilibrium force, so that dPhi/dx holds mu + mu'(R_N) R_N where Coulomb's has mu, and
dPhi/dargs the law's parameters and the last step's sliding speeds (its speed terms).

A candidate node with one prescribed dof (the flat die's corner D) carries, in the semismooth rows, the
previous iterate's contact force as the constraint's reaction, a fixed point the piece alone does not
differentiate. Slipping, its rows are taken apart: g_N = 0, and the prescribed dof's own row; its
contact force then follows from the equilibrium of its free dof with R_T = mu xi R_N (with a friction
law, by one Newton step on that equation from the converged force, exact to first order). Sticking, or
with both dofs prescribed, the reaction and the contact force are not separable: the derivative is
reported as non-finite instead of wrong. Where a pair sits on a status switch the derivative is that of
the final piece (one-sided).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..numerics.linalg import linear_solve
from ..numerics.newton import moving_part
from .alart_curnier import OPEN, SLIP_NEG, SLIP_POS, STICK
from .exact_active_set import Frames, PieceData, classify, contact_frames, piece_data, piece_system
from .exact_iterate import Iterate, iterate_residual, iterate_values, linearize_iterate, pair_status, tangents
from .rigid import has_friction_law, pair_friction, pair_mu, pair_speeds

__all__ = ["exact_step_tangents"]


def _frames_with_friction(fr: Frames, args) -> Frames:
    """``fr`` with its friction coefficients read from ``args`` (so that they carry derivatives)."""
    return fr._replace(mu=jnp.where(fr.valid, pair_mu(args.contact.tools, args.contact.mu)[fr.pairs], 0.0))


def _law_mu(args, fr: Frames, R_N) -> jax.Array:
    """(n_u,) each candidate's friction coefficient through its tool's friction law at the normal forces
    ``R_N`` (n_u,) and the last step's sliding speeds (0 where the candidate projects on nothing)."""
    c = args.contact
    rn = jnp.zeros(pair_mu(c.tools, c.mu).shape[0]).at[fr.pairs].set(R_N)
    mu = pair_friction(c.tools, c.mu, args.mesh.nodes, rn, pair_speeds(c))
    return jnp.where(fr.valid, mu[fr.pairs], 0.0)


def _law_slope(args, fr: Frames, R_N) -> tuple[jax.Array, jax.Array]:
    """:func:`_law_mu` at ``R_N`` and its derivative in each candidate's own R_N (a pair's law reads its
    own force only)."""
    return jax.jvp(lambda r: _law_mu(args, fr, r), (R_N,), (jnp.ones_like(R_N),))


def _with_law(d: PieceData, args) -> PieceData:
    """``d`` with the friction coefficients of the tools' friction laws at its equilibrium forces."""
    if not has_friction_law(args.contact.tools):   # static
        return d
    return d._replace(fr=d.fr._replace(mu=_law_mu(args, d.fr, d.R_N)))


def _prescribed_dofs(args, fr: Frames) -> jax.Array:
    """(n_u,) how many of each candidate node's dofs are prescribed in this step."""
    n = args.mesh.n_dofs
    return jnp.sum(args.mask[:n].reshape(-1, 2)[fr.nodes], axis=1)


def _constrained(args, fr: Frames, state) -> jax.Array:
    """(n_u,) the slipping candidates with one prescribed dof (module docstring)."""
    return (_prescribed_dofs(args, fr) == 1) & ((state == SLIP_POS) | (state == SLIP_NEG))


def _piece_residual(x, args, hint, frames, K, state):
    """Phi(x, args) on the active set ``state`` (module docstring)."""
    fr = _frames_with_friction(frames, args)
    d = _with_law(piece_data(iterate_values(x, args), args, x, hint, (fr, K)), args)
    return piece_system(d, args, state, _constrained(args, fr, state), x)[1]


def _outputs(x, args, hint, frames, K, state, contact_out):
    """The step's outputs (:meth:`jaxfric.contact.exact.ExactContactProblem.aux`) as functions of (x, args) on
    the active set ``state``: each closed candidate's force is its equilibrium force in its frame (with
    one prescribed dof: from its free dof's equilibrium and the slip law)."""
    fr = _frames_with_friction(frames, args)
    it = iterate_values(x, args)
    d = piece_data(it, args, x, hint, (fr, K))
    m = it.gap.shape[0]
    closed = (state != OPEN)[:, None]
    p_nodes = jnp.stack([d.R_N, d.R_T], -1)
    n = args.mesh.n_dofs
    free = 1.0 - args.mask[:n].reshape(-1, 2)[fr.nodes].astype(x.dtype)          # the free dof of each node
    xi = jnp.where(state == SLIP_NEG, -1.0, 1.0)
    normal = jnp.where(fr.valid[:, None], it.normal[fr.pairs], fr.normal)
    f_free = jnp.sum(free * d.f_tilde.reshape(-1, 2)[fr.nodes], -1)
    if has_friction_law(args.contact.tools):   # static
        # r (free . (n + mu(r) xi t)) = f_free by one Newton step from the converged force r_0, with
        # mu(r) = mu(r_0) + mu'(r_0) (r - r_0): the force's value and first derivative.
        r_0 = jnp.where(fr.valid, hint[fr.pairs, 0], 0.0)
        mu_0, slope = _law_slope(args, fr, r_0)
        along = jnp.sum(free * (normal + (mu_0 * xi)[:, None] * tangents(normal)), -1)
        pivot = along + r_0 * slope * xi * jnp.sum(free * tangents(normal), -1)
        r_n = r_0 - (r_0 * along - f_free) / jnp.where(pivot == 0.0, 1.0, pivot)
        mu_n = mu_0 + slope * (r_n - r_0)
    else:
        along = jnp.sum(free * (normal + (fr.mu * xi)[:, None] * tangents(normal)), -1)
        r_n, mu_n = f_free / jnp.where(along == 0.0, 1.0, along), fr.mu
    p_nodes = jnp.where(_constrained(args, fr, state)[:, None], jnp.stack([r_n, mu_n * xi * r_n], -1), p_nodes)
    p = jnp.zeros((m, 2)).at[fr.pairs].set(jnp.where(closed, p_nodes, 0.0))
    _, tool_f = iterate_residual(x, it, p, args)
    c = args.contact
    status = pair_status(p, pair_friction(c.tools, c.mu, args.mesh.nodes, p[:, 0], pair_speeds(c)))
    return it.f_int, it.states, contact_out(it, p, tool_f, status)


def exact_step_tangents(args, args_dot, x_star, p_star, contact_out):
    """Tangents (x_dot, outputs_dot) of a converged exact-contact step at ``x_star`` with contact forces
    ``p_star`` (m, 2), along the tangent ``args_dot`` of its data (None leaves: no change).
    ``contact_out(it, p, tool_f, status)``: the contact outputs' layout (:mod:`jaxfric.contact.exact`)."""
    it: Iterate = linearize_iterate(x_star, args)
    frames, K = contact_frames(it, args)
    d = piece_data(it, args, x_star, p_star, (frames, K))
    fr = d.fr
    h = jnp.where(fr.valid[:, None], p_star[fr.pairs], 0.0)
    mu_force = None
    if has_friction_law(args.contact.tools):   # static: mu(R_N) at the equilibrium forces (module docstring)
        mu, slope = _law_slope(args, fr, d.R_N)
        d = d._replace(fr=fr._replace(mu=mu))
        mu_force = mu + slope * (d.R_N - fr.c_n * d.gap)
    state = classify(d, args, h[:, 0], h[:, 1], d.gap, d.slip)
    matrix = piece_system(d, args, state, constrained=_constrained(args, fr, state), x=x_star,
                          mu_force=mu_force)[0]
    # Not separable from a reaction: a closed candidate that sticks with a prescribed dof, or has two.
    count = _prescribed_dofs(args, fr)
    undetermined = jnp.any((state != OPEN) & ((count == 2) | ((count == 1) & (state == STICK))))

    diff, diff_dot, static = moving_part(args, args_dot)
    held = (p_star, frames, K, state)

    _, r_dot = jax.jvp(lambda dd: _piece_residual(x_star, eqx.combine(dd, static), *held), (diff,), (diff_dot,))
    # A NaN factor, not a NaN value: the map stays linear, so reverse mode reports it too.
    x_dot = -linear_solve(matrix, r_dot) * jnp.where(undetermined, jnp.nan, 1.0)
    _, out_dot = jax.jvp(lambda x, dd: _outputs(x, eqx.combine(dd, static), *held, contact_out),
                         (x_star, diff), (x_dot, diff_dot))
    return x_dot, out_dot
