"""Finite-strain J2 plasticity with nonlinear kinematic hardening (Armstrong-Frederick / Chaboche) at one point.

A strip drawn through a bead is bent, unbent and bent again; after each reversal it yields earlier than
an isotropic law says (the Bauschinger effect), which lowers the drawing force. The yield surface here
is centred on a back stress beta = sum_i beta_i, each of Armstrong and Frederick's form (Chaboche's
superposition for two or more):

    Phi = sqrt(3/2) |dev tau - beta| - sigma_R(eqps),
    d beta_i = (2/3) C_i d eps^p - gamma_i beta_i d eqps,    d eps^p = d eqps sqrt(3/2) n,

n = (dev tau - beta) / |dev tau - beta|; gamma_i = 0 is Prager's linear rule (Armstrong & Frederick,
CEGB report RD/B/N731, 1966, reprinted in Mater. High Temp. 24 (2007) 1-26; Chaboche, Int. J. Plasticity
5 (1989) 247-302).

**Isotropic radius and monotonic curve.** The monotonic proportional hardening curve is the spec's power
law plus optional Voce terms (Q_j of either sign, b_j >= 0; Voce, J. Inst. Metals 74 (1948) 537-562),

    M(eqps) = sigma_y (1 + A eqps)^n + sum_j Q_j (1 - exp(-b_j eqps)).

Under monotonic proportional loading beta_i saturates at (C_i / gamma_i) (1 - exp(-gamma_i eqps)) in the
equivalent (uniaxial) measure, so ``keep_monotonic=True`` (the scenes' choice) takes the isotropic radius

    sigma_R(eqps) = M(eqps) - sum_i (C_i / gamma_i) (1 - exp(-gamma_i eqps)),

and monotonic loading follows M exactly as an isotropic law of radius M would: the comparison with that
law (the same constants without back stresses) measures the Bauschinger effect alone. With
``keep_monotonic=False`` sigma_R = M and the monotonic curve is M plus the saturation, the usual form of a
combined fit. With no back stress (m = 0) the law is the isotropic one of radius M.

**Finite strain.** As in :class:`~jaxfric.fem.material.J2Material`: multiplicative split, Hencky energy
in the logarithmic elastic strain eps^e = 1/2 ln b^e, with the plastic metric C_p^-1 as history. The back
stresses are kept in the frame that the rotation R of F = R U (polar decomposition) takes back to the
reference orientation: the trial back stress is R beta_hat R^T (the Green-Naghdi corotational
transport), so the law is objective (a superposed rotation Q of F turns tau and beta by Q). The plastic
correction is applied to the trial log strain, eps^e = eps^e_tr - d eqps sqrt(3/2) n: the exponential
map is exact where n is coaxial with b^e_tr (always without back stress) and otherwise first order in
the increment, the order of the backward Euler rule for beta itself (as in the logarithmic-strain
formulations of combined hardening, e.g. Eterovic & Bathe, Int. J. Numer. Meth. Engng 30 (1990)
1099-1114).

**Return mapping** (backward Euler, reduced to one scalar equation; e.g. Kobayashi & Ohno, Int. J.
Numer. Meth. Engng 53 (2002) 2217-2238): with dg = d eqps and the trial values dev tau_tr, beta_i,tr,

    beta_i = (beta_i,tr + sqrt(2/3) C_i dg n) / (1 + gamma_i dg),
    dev tau - beta = a(dg) - c(dg) n,   a(dg) = dev tau_tr - sum_i beta_i,tr / (1 + gamma_i dg),

so n = a / |a| and the yield condition is the scalar equation

    R(dg) = sqrt(3/2) |a(dg)| - 3 G dg - sum_i C_i dg / (1 + gamma_i dg) - sigma_R(eqps_n + dg) = 0,

solved by Newton from dg = 0. R decreases: the elastic term -3 G dg outweighs both the growth of |a|
(sqrt(3/2) |d|a| / d dg| <= sum_i C_i, every |beta_i| staying within sqrt(2/3) C_i / gamma_i) and any
softening of the radius. As in J2Material, the Newton loop runs without gradients and one more Newton
step taken with gradients on gives the implicit-function derivative; the consistent tangent is the
element code's forward derivative of :meth:`update`.

**A published steel fit** (:data:`S355J2N`): Hartloper, de Castro e Sousa & Lignos, "Constitutive modeling
of structural steels: nonlinear isotropic/kinematic hardening material model and its calibration", J.
Struct. Eng. (ASCE), doi:10.1061/(ASCE)ST.1943-541X.0002964, fit two Chaboche back stresses and an
isotropic law sigma_y + Q_inf (1 - exp(-b p)) - D_inf (1 - exp(-a p)) (their "updated Voce", whose D_inf
term is the yield plateau's drop) to cyclic coupon tests of twelve structural steels, with the back-stress
rule written as here; the S355J2+N 25 mm plate's values as tabulated in the OpenSees documentation of the
model (``UVCuniaxial``). Its isotropic law is this law's radius with ``keep_monotonic=False``; the source
gives no Poisson's ratio.

Units: MPa for E, sigma_y, C_i, Q_j and the stresses; A, n, gamma_i, b_j and the strains dimensionless.
Verified (``tests/test_kinematic.py``): plane-strain tension-compression cycles against the closed-form
Armstrong-Frederick response, the tangent against central differences, objectivity, and the isotropic law
recovered with no back stress.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..numerics.tensor import inv2, safe_norm, sym2_exp
from .material import J2Material, MaterialState, scalar_newton, trial_log_strain

__all__ = ["KinematicJ2Material", "S355J2N", "polar_rotation", "to_plane", "from_plane"]

# Hartloper et al.'s S355J2+N (25 mm plate) fit (module docstring): E, sigma_y = f_y in MPa; the isotropic
# law as Voce terms (Q_inf, b) and (-D_inf, a); two back stresses (C_i MPa, gamma_i).
S355J2N = {"E": 197410.0, "sigma_y": 338.80, "Q": (134.34, -133.75), "b": (14.71, 229.25),
           "C": (26242.00, 2445.30), "gamma": (199.04, 11.66)}

_SQRT_3_2 = math.sqrt(1.5)
_SQRT_2_3 = math.sqrt(2.0 / 3.0)
_NEWTON_RTOL = 1e-12  # |R| <= 1e-12 sigma_y, as J2Material
_YIELD_TOL = 1e-10


def polar_rotation(F: jax.Array) -> jax.Array:
    """The rotation R of the polar decomposition F = R U of an in-plane (2, 2) F with det F > 0, as a
    (3, 3) matrix (R_zz = 1). For F = R U with U symmetric, F_11 + F_22 = cos(theta) tr U and
    F_21 - F_12 = sin(theta) tr U, with tr U > 0: closed form, smooth wherever det F > 0."""
    c, s = F[0, 0] + F[1, 1], F[1, 0] - F[0, 1]
    h = jnp.sqrt(c * c + s * s)
    c, s = c / h, s / h
    return jnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=F.dtype)


def to_plane(t2: jax.Array, tzz: jax.Array) -> jax.Array:
    """The (3, 3) block-diagonal tensor of an in-plane block (..., 2, 2) and a zz entry (...)."""
    out = jnp.zeros((*t2.shape[:-2], 3, 3), t2.dtype)
    return out.at[..., :2, :2].set(t2).at[..., 2, 2].set(tzz)


def from_plane(t: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The in-plane block and the zz entry of block-diagonal (..., 3, 3) tensors."""
    return t[..., :2, :2], t[..., 2, 2]


class KinematicJ2Material(eqx.Module):
    """Plane-strain finite-strain J2 plasticity with power-law isotropic hardening and m Armstrong-Frederick
    back stresses (module docstring).

    Attributes (float64 array leaves; only ``keep_monotonic`` is static):
        E, nu, sigma_y, A, n: as :class:`~jaxfric.fem.material.J2Material` (MPa, -, MPa, -, -).
        C: (m,) back-stress moduli C_i (MPa), >= 0 and finite; m may be 0.
        gamma: (m,) recall rates gamma_i (-), >= 0 and finite (0: linear Prager rule).
        Q: (k,) Voce terms of the monotonic curve (MPa, either sign); k may be 0.
        b: (k,) their rates b_j (-), >= 0 and finite.
        keep_monotonic: True: the isotropic radius is the monotonic curve less the back stresses'
            saturation, so that monotonic loading follows the monotonic curve (module docstring).
    """

    E: jax.Array
    nu: jax.Array
    sigma_y: jax.Array
    A: jax.Array
    n: jax.Array
    C: jax.Array
    gamma: jax.Array
    Q: jax.Array
    b: jax.Array
    keep_monotonic: bool = eqx.field(static=True)

    def __init__(self, E, nu, sigma_y, A, n, C, gamma, Q=(), b=(), keep_monotonic: bool = True):
        iso = J2Material(E, nu, sigma_y, A, n)  # validates the isotropic constants, naming the field
        self.E, self.nu, self.sigma_y, self.A, self.n = iso.E, iso.nu, iso.sigma_y, iso.A, iso.n
        for name, value in (("C", C), ("gamma", gamma), ("Q", Q), ("b", b)):
            if value is None or isinstance(value, (str, bytes, bool)) or np.iscomplexobj(value):
                raise ValueError(f"KinematicJ2Material: {name} = {value!r} is invalid: it must be real numbers.")
        self.C, self.gamma, self.Q, self.b = (jnp.reshape(jnp.asarray(v, jnp.float64), (-1,))
                                              for v in (C, gamma, Q, b))
        self.keep_monotonic = bool(keep_monotonic)

    def __check_init__(self):
        def bad(name, value, ok, why):
            if not isinstance(value, jax.core.Tracer) and not np.all(ok(np.asarray(value))):
                raise ValueError(f"KinematicJ2Material: {name} = {np.asarray(value)} is invalid: {why}.")

        for name, other in (("gamma", "C"), ("b", "Q")):
            if getattr(self, name).shape != getattr(self, other).shape:
                raise ValueError(f"KinematicJ2Material: {name} has {getattr(self, name).shape[0]} entries and "
                                 f"{other} {getattr(self, other).shape[0]}: give one entry per back stress "
                                 "(C, gamma) and per Voce term (Q, b).")
        bad("C", self.C, lambda v: np.isfinite(v) & (v >= 0), "every C_i must be finite and >= 0")
        bad("gamma", self.gamma, lambda v: np.isfinite(v) & (v >= 0), "every gamma_i must be finite and >= 0")
        bad("Q", self.Q, np.isfinite, "every Q_j must be finite")
        bad("b", self.b, lambda v: np.isfinite(v) & (v >= 0), "every b_j must be finite and >= 0")
        bad("sigma_y", self.sigma_y, np.isfinite, "it must be finite with kinematic hardening")
        # The yield surface must keep a positive radius: a back stress that saturates above the hardening
        # of the monotonic curve (keep_monotonic) would shrink it to nothing.
        leaves = (self.sigma_y, self.A, self.n, self.C, self.gamma, self.Q, self.b)
        if not any(isinstance(x, jax.core.Tracer) for x in leaves):
            p = np.concatenate([[0.0], np.geomspace(1e-6, 10.0, 400)])
            radius = np.asarray(self.yield_stress(jnp.asarray(p)))
            if not np.all(radius > 0):
                k = int(np.argmin(radius))
                raise ValueError(f"KinematicJ2Material: the isotropic radius falls to {radius[k]:.4g} MPa at "
                                 f"eqps = {p[k]:.3g}: the back stresses' saturation sum C_i / gamma_i exceeds "
                                 "the hardening of the monotonic curve (lower C or raise gamma).")

    @property
    def isotropic(self) -> J2Material:
        """The isotropic law of the same constants (its moduli and power law)."""
        return J2Material(self.E, self.nu, self.sigma_y, self.A, self.n)

    @property
    def bulk_modulus(self) -> jax.Array:
        return self.isotropic.bulk_modulus

    @property
    def shear_modulus(self) -> jax.Array:
        return self.isotropic.shear_modulus

    @staticmethod
    def _saturating(rates: jax.Array, eqps: jax.Array) -> jax.Array:
        """(1 - exp(-r eqps)) / r per rate r, eqps at any leading shape (eqps where r eqps is tiny)."""
        eqps = jnp.asarray(eqps)[..., None]
        small = rates * eqps < 1e-8
        r = jnp.where(small, 1.0, rates)
        return jnp.where(small, eqps * (1.0 - 0.5 * rates * eqps), -jnp.expm1(-r * eqps) / r)

    def back_saturation(self, eqps: jax.Array) -> jax.Array:
        """sum_i (C_i / gamma_i) (1 - exp(-gamma_i eqps)), MPa: the back stresses' equivalent value after
        monotonic proportional loading to ``eqps`` from a virgin state (C_i eqps where gamma_i = 0)."""
        return jnp.sum(self.C * self._saturating(self.gamma, eqps), axis=-1)

    def monotonic_curve(self, eqps: jax.Array) -> jax.Array:
        """The flow stress of monotonic proportional loading, MPa (module docstring)."""
        curve = (self.isotropic.yield_stress(eqps)
                 + jnp.sum(self.Q * self.b * self._saturating(self.b, eqps), axis=-1))
        return curve if self.keep_monotonic else curve + self.back_saturation(eqps)

    def yield_stress(self, eqps: jax.Array) -> jax.Array:
        """The isotropic radius sigma_R(eqps) of the yield surface, MPa (module docstring)."""
        return self.monotonic_curve(eqps) - self.back_saturation(eqps)

    @property
    def n_back(self) -> int:
        """m, the number of back stresses (static)."""
        return int(self.C.shape[0])

    def init_state(self) -> MaterialState:
        """Virgin state: C_p^-1 = I, eqps = 0, every back stress 0 ((m, 3, 3), reference orientation;
        None when m = 0, so that the element loops batch no empty arrays)."""
        state = self.isotropic.init_state()
        if self.n_back == 0:
            return state
        return eqx.tree_at(lambda s: s.back, state, jnp.zeros((self.n_back, 3, 3), jnp.float64),
                           is_leaf=lambda x: x is None)

    def _residual(self, dg, dev_trial, back_trial, eqps_n):
        """R(dg) of the module docstring and a(dg), (3, 3)."""
        shrink = 1.0 / (1.0 + self.gamma * dg)                               # (m,)
        a = dev_trial - jnp.einsum("i,ijk->jk", shrink, back_trial)
        residual = (_SQRT_3_2 * safe_norm(a) - 3.0 * self.shear_modulus * dg
                    - jnp.sum(self.C * dg * shrink) - self.yield_stress(eqps_n + dg))
        return residual, a

    def update(self, F: jax.Array, state: MaterialState) -> tuple[jax.Array, MaterialState]:
        """Stress update n -> n+1 at one point (module docstring).

        Args:
            F: (2, 2) in-plane deformation gradient F_{n+1} (F_zz = 1), det F > 0.
            state: history at t_n, with ``back`` (m, 3, 3) in the reference orientation.

        Returns:
            tau: (3, 3) Kirchhoff stress (MPa), block diagonal.
            new_state: history at t_{n+1}.
        """
        if (state.back is None) != (self.n_back == 0):
            raise ValueError("KinematicJ2Material.update: the point state's back stresses do not match the "
                             "law's; start it from this law's init_state()")
        back_n = jnp.zeros((0, 3, 3), F.dtype) if state.back is None else state.back
        kappa, G = self.bulk_modulus, self.shear_modulus
        eps_trial, eps_trial_zz = trial_log_strain(F, state)
        trace = jnp.trace(eps_trial) + eps_trial_zz
        eye3 = jnp.eye(3, dtype=F.dtype)
        dev_trial = 2.0 * G * (to_plane(eps_trial, eps_trial_zz) - (trace / 3.0) * eye3)   # dev tau_tr
        R = polar_rotation(F)
        back_trial = jnp.einsum("ij,mjk,lk->mil", R, back_n, R)

        f_trial = _SQRT_3_2 * safe_norm(dev_trial - jnp.sum(back_trial, axis=0)) - self.yield_stress(state.eqps)
        plastic = f_trial > _YIELD_TOL * self.yield_stress(state.eqps)

        def residual(dg, material, dev, back, eqps_n):
            return material._residual(dg, dev, back, eqps_n)[0]

        inputs = (self, dev_trial, back_trial, state.eqps)
        frozen = jax.lax.stop_gradient(inputs)
        dg_star = scalar_newton(lambda dg: jax.value_and_grad(residual)(dg, *frozen),
                                _NEWTON_RTOL * jax.lax.stop_gradient(self.sigma_y), jnp.zeros((), F.dtype), plastic)
        r, slope = jax.value_and_grad(residual)(dg_star, *inputs)
        dg = jnp.where(plastic, dg_star - r / jnp.where(plastic, slope, -1.0), 0.0)

        _, a = self._residual(dg, dev_trial, back_trial, state.eqps)
        a_norm = safe_norm(a)
        normal = a / jnp.where(plastic, a_norm, 1.0)
        dev = dev_trial - 2.0 * G * _SQRT_3_2 * dg * normal
        back = (back_trial + (_SQRT_2_3 * self.C * dg)[:, None, None] * normal) / (1.0 + self.gamma * dg)[:, None, None]
        tau = kappa * trace * eye3 + dev

        eps_e2, eps_ezz = from_plane(dev / (2.0 * G) + (trace / 3.0) * eye3)
        F_inv = inv2(F)
        cp_inv = F_inv @ sym2_exp(2.0 * eps_e2) @ F_inv.T
        new_state = MaterialState(
            cp_inv=jnp.where(plastic, 0.5 * (cp_inv + cp_inv.T), state.cp_inv),
            cp_inv_zz=jnp.where(plastic, jnp.exp(2.0 * eps_ezz), state.cp_inv_zz),
            eqps=state.eqps + dg,
            enhanced=state.enhanced,
            back=None if state.back is None else jnp.where(plastic, jnp.einsum("ji,mjk,kl->mil", R, back, R),
                                                           state.back),
        )
        return tau, new_state
