"""An estimate of a load step's time-discretisation error, for increments chosen by it.

The return mapping integrates the plastic flow by backward Euler: a step's plastic strain increment is
taken along the flow direction at its end, dgamma N_(n+1). Where the direction turns during the step
(a fibre bent under a changing tension, the flow at a tool's entry) the exact increment follows the
turning direction, and the difference is the step's local error, about

    e = 1/2 dgamma |N_(n+1) - N_n| (2 dt_(n+1) / (dt_n + dt_(n+1))),

the first neglected term of the flow's expansion, with the direction's rate of change taken from the
last two accepted steps (backward Euler is first order: Simo & Hughes, *Computational Inelasticity*,
1998; the factor rescales the change of N over the previous step to the current increment). A
constant flow direction, however its rate varies, gives e = 0: the exponential-map return
(:mod:`jaxfric.fem.material`) is exact for proportional flow.

Strains are Lagrangian: the increment of the logarithmic plastic strain -1/2 ln C_p^-1 that the
material states keep, so that a rigid rotation of an element changes nothing.

Per step, the points' errors are weighted with their yield stress and volume and divided by the step's
plastic work so weighted:

    eta = sum_g w_g sigma_Y,g e_g / sum_g w_g sigma_Y,g dgamma_g,

an error of the step's plastic work relative to that work. Friction is not in it: its backward-Euler
error, 1/2 (|R_T,(n+1)| - |R_T,n|) |ds| per sliding pair, cancels in a steady draw between the pairs
that enter a wrap and those that leave it, and summed pair by pair without that cancellation it
overstates the step error many times. What eta <= tol leaves in a force is measured, not implied:
on the Nine's steady force 0.04 to 0.35 times tol, on a turned strip's end reaction 2.8 times
(``experiments/step_error_control.py``, ``tests/test_step_error.py``; docs/results.md, increments by
the step error). A step without plastic flow has eta = 0; the first step, and one after a restart,
has none (``-1``): no previous direction.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..numerics.tensor import safe_norm, sym2_log

__all__ = ["FlowMemory", "plastic_increment", "plastic_step_error"]

_SQRT2 = float(np.sqrt(2.0))


def _log_plastic_metric(material) -> jax.Array:
    """ln C_p^-1 of every point as a vector (xx, yy, zz, sqrt 2 xy): (..., 4), so that its Euclidean
    norm is the tensor's."""
    log_in = jnp.vectorize(sym2_log, signature="(2,2)->(2,2)")(material.cp_inv)
    return jnp.stack([log_in[..., 0, 0], log_in[..., 1, 1], jnp.log(material.cp_inv_zz),
                      _SQRT2 * log_in[..., 0, 1]], axis=-1)


def plastic_increment(old, new) -> jax.Array:
    """The Lagrangian logarithmic plastic strain increment -1/2 (ln C_p,new^-1 - ln C_p,old^-1) of
    every point between two material states (batched :class:`~jaxfric.fem.material.MaterialState`,
    leading axes (n_el, gp)): (n_el, gp, 4), components (xx, yy, zz, sqrt 2 xy). Exactly zero where a
    point stayed elastic (the law leaves C_p^-1 unchanged)."""
    return -0.5 * (_log_plastic_metric(new) - _log_plastic_metric(old))


def plastic_step_error(increment, previous, weight, yield_stress, scale) -> tuple[jax.Array, jax.Array]:
    """eta's numerator and denominator (module docstring) for one step: its estimated error and its work.

    Args:
        increment: (n_el, gp, 4) the step's plastic increments (:func:`plastic_increment`).
        previous: (n_el, gp, 4) those of the last accepted step.
        weight: (n_el, gp) the points' reference areas (mm^2 per mm).
        yield_stress: (n_el, gp) their yield stresses at the step's end (MPa).
        scale: () 2 dt_(n+1) / (dt_n + dt_(n+1)) (1 across a phase change, where pseudo-times of the two
            phases mean different strokes).

    Returns:
        (error, work): () sum_g w_g sigma_Y,g e_g and sum_g w_g sigma_Y,g dgamma_g (N mm per mm).
    """
    size, size_prev = safe_norm(increment, axis=-1), safe_norm(previous, axis=-1)
    both = (size > 0) & (size_prev > 0)
    direction = increment / jnp.where(size > 0, size, 1.0)[..., None]
    direction_prev = previous / jnp.where(size_prev > 0, size_prev, 1.0)[..., None]
    turn = jnp.where(both, safe_norm(direction - direction_prev, axis=-1), 0.0)
    # dgamma = |increment|: N is the unit direction of the increment. An elastic law's infinite yield
    # stress weighs nothing (it never flows).
    w = weight * jnp.where(jnp.isfinite(yield_stress), yield_stress, 0.0)
    return 0.5 * scale * jnp.sum(w * size * turn), jnp.sum(w * size)


class FlowMemory(eqx.Module):
    """What the estimate keeps of the last accepted step: its plastic increments, pseudo-time increment
    and phase. Empty arrays (shape (0,)) where the run does not estimate its step error, so that such
    runs carry nothing.

    Attributes:
        increment: (n_el, gp, 4) the last accepted step's plastic increments, or (0,).
        dt: () its pseudo-time increment; 0: no step yet (no estimate).
        phase: () int32 its phase.
    """

    increment: jax.Array
    dt: jax.Array
    phase: jax.Array

    @classmethod
    def empty(cls, material, on: bool) -> FlowMemory:
        """Before the first step; ``material``: the batched point states (their shape), ``on``: static,
        whether the run estimates its step error."""
        shape = material.eqps.shape + (4,) if on else (0,)
        return cls(jnp.zeros(shape), jnp.array(0.0), jnp.array(0, jnp.int32))

    @property
    def on(self) -> bool:
        return self.increment.ndim > 1

    def estimate(self, geo_weight, material_law, old, new):
        """eta of the step from the converged state ``old`` to the attempt ``new`` (SimStates), and the
        step's plastic increments; eta = -1 where there is no previous step to compare with."""
        increment = plastic_increment(old.material, new.material)
        dt = new.time - old.time
        same_phase = new.phase == self.phase
        scale = jnp.where(same_phase, 2.0 * dt / jnp.where(same_phase, self.dt + dt, 1.0), 1.0)
        error, work = plastic_step_error(increment, self.increment, geo_weight,
                                         material_law.yield_stress(new.material.eqps), scale)
        eta = jnp.where(work > 0, error / jnp.where(work > 0, work, 1.0), 0.0)
        return jnp.where(self.dt > 0, eta, -1.0), increment

    def after(self, ok, old, new, increment) -> FlowMemory:
        """The memory after an attempt from ``old`` to ``new`` with plastic ``increment``, accepted if
        ``ok``."""
        return FlowMemory(increment=jnp.where(ok, increment, self.increment),
                          dt=jnp.where(ok, new.time - old.time, self.dt),
                          phase=jnp.where(ok, new.phase, self.phase).astype(jnp.int32))
