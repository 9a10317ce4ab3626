"""Friction coefficients that depend on the contact pressure (issue: pressure-dependent friction).

The spec's law is Coulomb's with one coefficient per tool and phase (``RigidTool.mu``). A tool may carry
a :class:`FrictionLaw` instead, which turns that coefficient mu_0 into a function of the pair's contact
pressure p:

    PressurePolynomial:   mu(p) = max(mu_0 + c_p p + c_pp p^2, 0)    (0 where mu_0 = 0)

the pressure terms of OpenRadioss's generalised viscous law (``/FRICTION`` with ``Ifric`` = 1:
mu = Fric + C1 p + C2 v + C3 p v + C4 p^2 + C5 v^2, with Fric = mu_0, C1 = c_p, C4 = c_pp and the
velocity terms zero; :func:`jaxfric.cards.formats.openradioss_friction` writes it). The coefficient is
clipped at zero, so that a decreasing law never turns friction into a driving force, and a phase whose
mu_0 is 0 (the flat die's clamp) stays frictionless.

Pressure. A pair is a node of the sheet's surface against a rigid tool, and its force R_N is per unit
out-of-plane width (N/mm). Its pressure is R_N over the node's share of the surface,
p = R_N / l_a (N/mm^2 = MPa), with l_a half the reference lengths of the two surface segments at the
node (one at the ends of a tool's candidate row: :func:`tributary_lengths`). Reference lengths keep the
law local to the pair (a current length would couple each pair to its neighbours' displacements); on the
Nine's 300 x 3 mesh the surface stretches by at most a few per cent in the wraps, which the pressure then
overstates by as much.

Every formulation takes the law: the penalty and augmented-Lagrangian pair laws evaluate mu(R_N / l_a)
inside the pair force, so the tangent (by forward mode) and the parameters' derivatives carry d mu / dp.
Exact contact (``lcp_ssn``, ``lcp_lemke``) solves each Newton iteration's complementarity problem with
the coefficients of the forces its last direction predicted, so a converged step meets the law at its
own forces; its derivatives are not implemented for such a law (the active set's matrix would need the
d mu / dp terms), and asking for them raises a one-line error.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp

from ..numerics._checks import is_concrete

__all__ = ["FrictionLaw", "PressurePolynomial", "tributary_lengths"]


class FrictionLaw(eqx.Module):
    """A friction coefficient as a function of the contact pressure (module doc)."""

    @abc.abstractmethod
    def coefficient(self, mu0, p) -> jax.Array:
        """The coefficient at pressure ``p`` (MPa, >= 0) for the tool's Coulomb coefficient ``mu0``."""

    @abc.abstractmethod
    def describe(self) -> dict:
        """The law's name and parameters, JSON-ready (summaries and exports)."""


class PressurePolynomial(FrictionLaw):
    """mu(p) = max(mu_0 + c_p p + c_pp p^2, 0), p in MPa (module doc).

    Attributes:
        c_p: () linear coefficient (1/MPa).
        c_pp: () quadratic coefficient (1/MPa^2).
    """

    c_p: jax.Array
    c_pp: jax.Array

    def __init__(self, c_p=0.0, c_pp=0.0):
        self.c_p = jnp.asarray(c_p, jnp.float64)
        self.c_pp = jnp.asarray(c_pp, jnp.float64)

    def __check_init__(self):
        for name in ("c_p", "c_pp"):
            value = getattr(self, name)
            if value.shape != ():
                raise ValueError(f"field '{name}' must be a scalar, got shape {value.shape}")
            if is_concrete(value) and not bool(jnp.isfinite(value)):
                raise ValueError(f"field '{name}' must be finite, got {float(value)}")

    def coefficient(self, mu0, p) -> jax.Array:
        # A phase without friction (mu_0 = 0: the flat die's clamp) stays without it.
        return jnp.where(mu0 > 0.0, jnp.maximum(mu0 + self.c_p * p + self.c_pp * p * p, 0.0), 0.0)

    def describe(self) -> dict:
        return {"law": "pressure_polynomial", "c_p": float(self.c_p), "c_pp": float(self.c_pp)}


def tributary_lengths(X) -> jax.Array:
    """(n,) each node's share of a surface row: half the lengths of its two segments (one at the ends),
    for the reference positions ``X`` (n, 2) of the row's nodes in order (mm)."""
    seg = jnp.linalg.norm(jnp.diff(X, axis=0), axis=-1)
    if seg.shape[0] == 0:
        return jnp.ones(X.shape[0])
    return 0.5 * (jnp.concatenate([seg[:1] * 0.0, seg]) + jnp.concatenate([seg, seg[:1] * 0.0]))
