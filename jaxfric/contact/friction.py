"""Friction coefficients that depend on the contact pressure and the sliding speed.

The spec's law is Coulomb's with one coefficient per tool and phase (``RigidTool.mu``). A tool may carry
a :class:`FrictionLaw` instead, which turns that coefficient mu_0 into a function of the pair's contact
pressure p (MPa) and sliding speed v (mm/s), in the forms stamping codes accept:

    Polynomial:     mu = max(mu_0 + c_p p + c_v v + c_pv p v + c_pp p^2 + c_vv v^2, 0)
    VelocityDecay:  mu = mu_d + (mu_0 - mu_d) exp(-decay v)

``Polynomial`` is OpenRadioss's generalised viscous law (``/FRICTION`` with ``Ifric`` = 1: Fric = mu_0,
C1 = c_p, C2 = c_v, C3 = c_pv, C4 = c_pp, C5 = c_vv), ``VelocityDecay`` LS-DYNA's static and dynamic
coefficients with an exponential decay (FS = mu_0, FD = mu_d, DC = decay);
:mod:`jaxfric.cards.friction` writes both. A phase whose mu_0 is 0 (the flat die's clamp) stays
frictionless, and the polynomial is clipped at zero, so that a falling law never turns friction into a
driving force. On the flat die the pressures of a draw gather where mu reaches that clip, and Newton
fails once several pairs sit at it (``python experiments/friction_laws.py --falling``): a law is to keep
mu positive over the pressures it is used at.

Pressure. A pair is a node of the sheet's surface against a rigid tool, and its force R_N is per unit
out-of-plane width (N/mm). Its pressure is R_N over the node's share of the surface,
p = R_N / l_a (N/mm^2 = MPa), with l_a half the reference lengths of the two surface segments at the
node (one at the ends of a tool's candidate row: :func:`tributary_lengths`). Reference lengths keep the
law local to the pair (a current length would couple each pair to its neighbours' displacements); where
the surface stretches, the pressure is overstated by the stretch (a few per cent in the Nine's wraps).

Speed. The load path is quasi-static in a pseudo-time; a scene gives its drawing phase a duration, the
drawn length over ``draw_speed`` (``StripModel.phase_seconds``), and a pair's slip rate over a step is its
slip divided by the step's duration, r = |Delta s| / Delta t. Phases without a duration (clamping,
closing) have v = 0: the coefficient there is the static one. A step reads the speeds of the step before
it (``ContactState.speed``), not its own: with its own, a coefficient that falls with speed gives a
slipping pair a negative tangential stiffness, R_N dmu/dv / Delta t, and the quasi-static problem loses
its uniqueness (the flat die with mu falling from 0.15 to 0.09 over 0.05 mm/s stopped 0.1 um into its
draw, Newton failing at every increment).

Read raw, that one-step lag is an explicit coupling whose gain grows as the steps shrink, R_N |dmu/dv| /
(k_t Delta t) with k_t the pair's tangential stiffness: on the flat die (24 x 2, 50 N/mm, 0.1 um steps
at 1 mm/s, i.e. 0.1 ms each, mu = 0.12 + 0.01 v) the stuck pairs alternate between v = 0 and v = 2 mm/s
from step to step and the drawing force between 6.02 and 6.09 N/mm, where steady sliding at 1 mm/s is
mu(1) F = 6.5 N/mm.
So the speed a law reads is the slip rate through a first-order low-pass filter of time constant
``period`` (s), exact for a rate held over the step (:func:`sliding_speed`):

    v_n = r_n + (v_{n-1} - r_n) exp(-Delta t / period)

Its gain per step is about Delta t / period times the raw one, which no longer grows as the steps shrink;
steady sliding reads the steady rate exactly, and a change of speed reaches the law within a few periods.
The period it needs grows with the pressure and the law's slope: on that flat die 1 ms (ten steps)
settles at 50 N/mm where 0.3 ms still oscillates, and at 200 N/mm 2 ms oscillates where 5 ms
settles (``python experiments/friction_laws.py --period``). The scenes' default ``speed_period`` is 5 ms,
5 um of drawing at 1 mm/s. ``period`` = 0 reads the last step's rate raw.
A coefficient that falls with speed (velocity weakening, stick-slip's cause) is no exception: through the
filter the flat die breaks away near the static coefficient and then slides steadily at mu(draw_speed)
(``python experiments/friction_laws.py --speed``, whose curves a decay law makes at three speeds).

Every formulation takes the law: the penalty and augmented-Lagrangian pair laws evaluate mu(p, v) inside
the pair force, so the tangent (by forward mode) and the parameters' derivatives carry its derivatives.
Exact contact (``lcp_ssn``, ``lcp_lemke``) solves each Newton iteration's complementarity problem with
the coefficients of the forces its last direction predicted, so a converged step meets the law at its
own forces; its derivatives (:mod:`jaxfric.contact.exact_derivative`) take the slip rows' mu(R_N) with its slope.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ..numerics._checks import is_concrete

__all__ = ["FrictionLaw", "Polynomial", "VelocityDecay", "tributary_lengths", "sliding_speed"]


class FrictionLaw(eqx.Module):
    """A friction coefficient as a function of contact pressure and sliding speed (module doc)."""

    @abc.abstractmethod
    def coefficient(self, mu0, p, v) -> jax.Array:
        """The coefficient at pressure ``p`` (MPa, >= 0) and speed ``v`` (mm/s, >= 0) for the tool's
        Coulomb coefficient ``mu0``."""

    @abc.abstractmethod
    def describe(self) -> dict:
        """The law's name and parameters, JSON-ready (summaries and exports)."""

    def _check_period(self):
        self._check_scalars(("period",))
        if is_concrete(self.period) and float(self.period) < 0.0:
            raise ValueError(f"field 'period' must be >= 0, got {float(self.period)}")

    def _check_scalars(self, names):
        for name in names:
            value = getattr(self, name)
            if value.shape != ():
                raise ValueError(f"field '{name}' must be a scalar, got shape {value.shape}")
            if is_concrete(value) and not bool(jnp.isfinite(value)):
                raise ValueError(f"field '{name}' must be finite, got {float(value)}")


class Polynomial(FrictionLaw):
    """mu = max(mu_0 + c_p p + c_v v + c_pv p v + c_pp p^2 + c_vv v^2, 0), p in MPa, v in mm/s; 0 where
    mu_0 = 0 (module doc). Attributes: the coefficients, () each (1/MPa, s/mm, s/(MPa mm), 1/MPa^2,
    s^2/mm^2), and ``period``, the speed filter's time constant (s; :func:`sliding_speed`)."""

    TERMS: ClassVar[tuple] = ("c_p", "c_v", "c_pv", "c_pp", "c_vv")
    c_p: jax.Array
    c_v: jax.Array
    c_pv: jax.Array
    c_pp: jax.Array
    c_vv: jax.Array
    period: jax.Array

    def __init__(self, c_p=0.0, c_v=0.0, c_pv=0.0, c_pp=0.0, c_vv=0.0, period=0.0):
        for name, value in zip(self.TERMS, (c_p, c_v, c_pv, c_pp, c_vv), strict=True):
            setattr(self, name, jnp.asarray(value, jnp.float64))
        self.period = jnp.asarray(period, jnp.float64)

    def __check_init__(self):
        self._check_scalars(self.TERMS)
        self._check_period()

    def coefficient(self, mu0, p, v) -> jax.Array:
        mu = mu0 + self.c_p * p + self.c_v * v + self.c_pv * p * v + self.c_pp * p * p + self.c_vv * v * v
        return jnp.where(mu0 > 0.0, jnp.maximum(mu, 0.0), 0.0)

    def describe(self) -> dict:
        return {"law": "polynomial", **{k: float(getattr(self, k)) for k in self.TERMS}, "period": float(self.period)}


class VelocityDecay(FrictionLaw):
    """mu = mu_d + (mu_0 - mu_d) exp(-decay v), v in mm/s; 0 where mu_0 = 0 (module doc).

    Attributes:
        mu_d: () dynamic coefficient (the limit at high speed), >= 0.
        decay: () decay coefficient (s/mm), >= 0.
        period: () the speed filter's time constant (s; :func:`sliding_speed`), >= 0.
    """

    mu_d: jax.Array
    decay: jax.Array
    period: jax.Array

    def __init__(self, mu_d, decay, period=0.0):
        self.mu_d = jnp.asarray(mu_d, jnp.float64)
        self.decay = jnp.asarray(decay, jnp.float64)
        self.period = jnp.asarray(period, jnp.float64)

    def __check_init__(self):
        self._check_period()
        self._check_scalars(("mu_d", "decay"))
        for name in ("mu_d", "decay"):
            value = getattr(self, name)
            if is_concrete(value) and float(value) < 0.0:
                raise ValueError(f"field '{name}' must be >= 0, got {float(value)}")

    def coefficient(self, mu0, p, v) -> jax.Array:
        return jnp.where(mu0 > 0.0, self.mu_d + (mu0 - self.mu_d) * jnp.exp(-self.decay * v), 0.0)

    def describe(self) -> dict:
        return {"law": "velocity_decay", "mu_d": float(self.mu_d), "decay": float(self.decay),
                "period": float(self.period)}


def tributary_lengths(X) -> jax.Array:
    """(n,) each node's share of a surface row: half the lengths of its two segments (one at the ends),
    for the reference positions ``X`` (n, 2) of the row's nodes in order (mm)."""
    seg = jnp.linalg.norm(jnp.diff(X, axis=0), axis=-1)
    if seg.shape[0] == 0:
        return jnp.ones(X.shape[0])
    return 0.5 * (jnp.concatenate([seg[:1] * 0.0, seg]) + jnp.concatenate([seg, seg[:1] * 0.0]))


def sliding_speed(slip, dt, previous=0.0, period=0.0) -> jax.Array:
    """The speed (mm/s) a law reads after a step of duration ``dt`` (s) with slip ``slip`` (mm): the rate
    r = |slip| / dt through the first-order filter of time constant ``period`` (s) from the ``previous``
    speed, r + (previous - r) exp(-dt / period) (module doc; ``period`` 0: r); 0 where the step has no
    duration."""
    moving = dt > 0.0
    rate = jnp.abs(slip) / jnp.where(moving, dt, 1.0)
    filtered = jnp.where(period > 0.0, rate + (previous - rate) * jnp.exp(-dt / jnp.where(period > 0.0, period, 1.0)),
                         rate)
    return jnp.where(moving, filtered, 0.0)
