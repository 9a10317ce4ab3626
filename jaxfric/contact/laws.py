"""Frictional contact laws for ONE node-to-rigid-surface pair (vmapped outward by the assembly).

Penalty (benchmarks spec 1.5, paper eq. 19) and augmented Lagrangian (spec 1.6, eq. 20) share one
law: with multipliers (lambda_N, lambda_T) frozen during a Newton solve,

    R_N    = < lambda_N - eps_N g_N >                     (<x> = max(x, 0))
    R_T^tr = lambda_T - eps_T s                           (stick predictor; s: slip since the reference)
    R_T    = R_T^tr                  if |R_T^tr| <  mu R_N   (stick)
           = mu R_N sign(R_T^tr)     otherwise               (slip: return to the Coulomb limit)

Penalty is the case lambda_N = 0, lambda_T = R_T,n (converged tangential force of the last step) and s
the slip since the last converged step (Wriggers, *Computational Contact Mechanics*, 2006, ch. 5;
Laursen, *Computational Contact and Impact Mechanics*, 2002, ch. 5). Forces are nodal (per unit
out-of-plane width, N/mm); eps_N, eps_T in N/mm per mm.

Optional smoothing (for gradient work; default off): with a force scale s > 0 (N/mm),

    R_N = s softplus(R_N^tr / s),         R_T = R_T^tr - s softplus((R_T^tr - mu R_N)/s)
                                                  + s softplus((-R_T^tr - mu R_N)/s),

a smooth <.> and a smooth clip to [-mu R_N, mu R_N]; both tend to the exact law as s -> 0 (the error
is at most s log 2 near the kinks and decays exponentially away from them). Effect on forces: an open
pair at gap g > 0 still carries s softplus(-eps_N g / s), a closed one penetrates by about s log 2 /
eps_N more at the contact edge, and the Coulomb limit is approached over a band of width ~s.

Kinks of the exact law are decided once, here, with explicit ``where`` branches (never a tie-averaging
max/clip):
- a pair with R_N^tr = lambda_N - eps_N g_N = 0 exactly counts as closed (spec 0: a tool that starts
  exactly touching gives a non-singular first iteration);
- |R_T^tr| = mu R_N counts as slip; with mu R_N = 0 the slip branch gives R_T = 0 and a zero
  tangential stiffness, so a frictionless or just-touching pair never gets a spurious stick stiffness.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .status import OPEN, SLIP, STICK, contact_status

__all__ = ["PairForce", "augmented_pair"]


class PairForce(NamedTuple):
    normal: jax.Array       # () R_N >= 0 (N/mm)
    tangential: jax.Array   # () R_T along t (N/mm)
    status: jax.Array       # () int8: OPEN, STICK or SLIP (the branch the law took)


def augmented_pair(gap, slip, lambda_n, lambda_t, mu, eps_n, eps_t, valid=True, smoothing=None) -> PairForce:
    """The augmented-Lagrangian pair law (penalty when lambda_n = 0, lambda_t = R_T,n).

    Args:
        gap: () normal gap g_N (mm), negative when penetrating.
        slip: () tangential slip s since the multipliers' reference configuration (mm), along t.
        lambda_n, lambda_t: () frozen multipliers (N/mm).
        mu: () friction coefficient, or a function of the pair's normal force R_N (a friction law of the
            pressure, :mod:`jaxfric.contact.friction`), evaluated at the R_N this law gives.
        eps_n, eps_t: () normal and tangential penalties (N/mm per mm).
        valid: () bool, False when the node projects on no tool primitive (the pair is open).
        smoothing: None for the exact law, or a force scale s > 0 (N/mm) for the smoothed one.
    """
    if smoothing is not None:
        return _smoothed_pair(gap, slip, lambda_n, lambda_t, mu, eps_n, eps_t, valid, smoothing)
    rn_trial = lambda_n - eps_n * gap
    closed = valid & (rn_trial >= 0.0)
    rn = jnp.where(closed, rn_trial, 0.0)
    rt_trial = jnp.where(closed, lambda_t - eps_t * slip, 0.0)
    limit = _coefficient(mu, rn) * rn
    stick = jnp.abs(rt_trial) < limit
    rt = jnp.where(stick, rt_trial, limit * jnp.sign(rt_trial))
    status = jnp.where(closed, jnp.where(stick, STICK, SLIP), OPEN).astype(jnp.int8)
    return PairForce(rn, rt, status)


def _smoothed_pair(gap, slip, lambda_n, lambda_t, mu, eps_n, eps_t, valid, s) -> PairForce:
    # Double where, no -inf: with the force scale s a traced leaf, the tangent of rn_trial / s carries
    # -rn_trial ds / s^2, which at rn_trial = -inf is inf * 0 = NaN even when ds = 0 (forward mode
    # then spreads it through the whole step; reverse mode only into s's own, unread, cotangent).
    rn_trial = jnp.where(valid, lambda_n - eps_n * gap, 0.0)
    rn = jnp.where(valid, s * jax.nn.softplus(rn_trial / s), 0.0)
    rt_trial = jnp.where(valid, lambda_t - eps_t * slip, 0.0)
    mu = _coefficient(mu, rn)
    limit = mu * rn
    rt = rt_trial - s * jax.nn.softplus((rt_trial - limit) / s) + s * jax.nn.softplus((-rt_trial - limit) / s)
    return PairForce(rn, rt, contact_status(rn, rt, mu))


def _coefficient(mu, rn):
    """The friction coefficient at normal force ``rn``: ``mu`` itself, or ``mu(rn)`` for a pressure law."""
    return mu(rn) if callable(mu) else mu
