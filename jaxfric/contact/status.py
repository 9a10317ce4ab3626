"""The contact status of a pair, open, stick or slip, read off its forces (benchmarks spec section 0).

One rule with two sets of thresholds:

- :func:`contact_status`, the spec's: open when R_N <= 1e-9 N/mm; otherwise stick when
  |R_T| < (1 - 1e-6) mu R_N, slip otherwise (a closed frictionless pair slips). Every status that is
  written out, counted (``n_active``, ``n_slip``) or compared by exact contact's Newton loop uses it.
- :func:`settled_status`, Newton's "no status change" test for the regularised laws: the same rule with
  the step's force tolerance in place of the spec's margins. A pair whose normal force is within the
  tolerance counts as open, and a closed pair within it of the Coulomb cone counts as slipping
  whichever branch the law took, since the law is continuous there: a flip of such a pair moves the
  residual by less than the tolerance. Without it, pairs touching at zero gap (a clamp's lands, the
  edges of a wrap) flip open <-> closed with forces of 1e-9 N/mm, and pairs on the cone flip
  stick <-> slip at every iteration, and a step whose residual is far below its tolerance never
  converges (``python experiments/stiff_penalty_newton.py --spec --mesh 300x3 --eps-n 1e6``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["OPEN", "STICK", "SLIP", "OPEN_FORCE", "STICK_MARGIN", "contact_status", "settled_status"]

OPEN, STICK, SLIP = 0, 1, 2
OPEN_FORCE = 1e-9      # N/mm: R_N at or below this is "open"
STICK_MARGIN = 1e-6    # |R_T| < (1 - STICK_MARGIN) mu R_N is "stick"


def contact_status(rn, rt, mu) -> jax.Array:
    """(...,) int8 status of pairs with normal and tangential forces ``rn``, ``rt`` (N/mm) and friction
    coefficients ``mu`` (broadcast), by the spec's thresholds. Works on NumPy and JAX arrays (jit-able)."""
    rn, rt = jnp.asarray(rn), jnp.asarray(rt)
    closed = rn > OPEN_FORCE
    stick = jnp.abs(rt) < (1.0 - STICK_MARGIN) * mu * rn
    return jnp.where(closed, jnp.where(stick, STICK, SLIP), OPEN).astype(jnp.int8)


def settled_status(branch, rn, rt, mu, tolerance) -> jax.Array:
    """(...,) int8 status for Newton's "no status change" test: ``branch`` (the status the law took) with
    pairs of R_N <= ``tolerance`` open and closed pairs within ``tolerance`` of the cone slipping."""
    on_cone = jnp.abs(mu * rn - jnp.abs(rt)) <= tolerance
    closed = jnp.where(on_cone, SLIP, branch)
    return jnp.where(rn > tolerance, closed, OPEN).astype(jnp.int8)
