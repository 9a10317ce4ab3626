"""Finite-strain J2 plasticity at one quadrature point (benchmarks spec section 1.2).

Multiplicative split F = F^e F^p, Hencky energy in the logarithmic elastic strain
eps^e = 1/2 ln b^e, von Mises yield with isotropic power-law hardening, and the exponential-map
return, which for Hencky's energy is an exact radial return in log strains:
Simo & Hughes, *Computational Inelasticity* (1998), ch. 9; de Souza Neto, Peric & Owen,
*Computational Methods for Plasticity* (2008), ch. 14.

A step's flow follows either the end point's deviator (``integration="radial"``: backward Euler,
first order in the step where the strain path turns) or the mean of the deviators at the two ends of
the step's plastic part, with consistency at the step's end (``integration="midpoint"``, the
generalized midpoint rule at alpha = 1/2 in log strains: second order; Ortiz & Popov, Int. J. Numer.
Meth. Engng 21, 1985; Simo & Hughes 1998, ch. 3). On the Nine it takes the steady force's step error
at the nominal increments from -0.63 / -0.92 % to -0.35 / -0.58 % (mu000 / mu017), for about 10 %
more Newton iterations and 1.4 to 1.6 times the solve time (``python experiments/plastic_integration.py``;
docs/results.md, integration of the plastic flow).

Units: stresses (E, sigma_y, tau) in MPa; strains, A, n and eqps dimensionless.
Plane strain: F = [[F_2D, 0], [0, 1]]; every 3x3 tensor is block diagonal (in-plane 2x2 block + zz).
The law acts on one point; the element code vmaps it and takes its consistent tangent from
:func:`piola_and_tangent` (the radial return's in closed form, :meth:`J2Material.piola_and_tangent`; ``jacfwd``
for the midpoint rule); parameter sensitivities by automatic differentiation, forward and reverse.
"""

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxfric.numerics.tensor import inv2, safe_norm, sym2_exp, sym2_log, sym2_log_derivative

__all__ = ["MaterialState", "J2Material", "INTEGRATIONS", "von_mises", "trial_log_strain", "scalar_newton", "piola",
           "piola_and_tangent", "piola_and_tangent_ad"]

INTEGRATIONS = ("radial", "midpoint")

_SQRT_3_2 = math.sqrt(1.5)
_NEWTON_RTOL = 1e-12  # |R| <= 1e-12 sigma_y, spec section 1.2
_NEWTON_MAX_ITER = 50
_YIELD_TOL = 1e-10  # relative round-off guard of the yield check
_STAGNATION = 2.0**-50  # |step| <= 4 ulp of dg: roundoff, no further progress possible


class MaterialState(eqx.Module):
    """Plastic history of ONE quadrature point.

    The spec stores (b^e_n, eqps_n, F_n) and builds the trial state b^e_tr = f b^e_n f^T with
    f = F_{n+1} F_n^-1. Storing instead the inverse plastic right Cauchy-Green tensor
    C_p^-1 = F_p^-1 F_p^-T = F^-1 b^e F^-T is exactly equivalent, since
    f b^e_n f^T = F_{n+1} F_n^-1 b^e_n F_n^-T F_{n+1}^T = F_{n+1} C_p,n^-1 F_{n+1}^T,
    and it needs no F_n. Plane strain keeps C_p^-1 block diagonal.

    Attributes:
        cp_inv: (2, 2) in-plane block of C_p^-1 (identity initially).
        cp_inv_zz: () its zz component (1 initially).
        eqps: () equivalent plastic strain (0 initially).
        enhanced: the enhanced parameters of the point's element (:mod:`jaxfric.fem.element`,
            ``formulation="anst"`` or ``"eas"``), kept with the history so that the next step starts
            from them: (n,) alpha for the local solve, (n, 9) the predictor of the last Newton iterate
            for ``enhanced_update="iterate"``; the law passes them through; None for the other formulations.
        back: (m, 3, 3) the back stresses of :class:`~jaxfric.fem.kinematic.KinematicJ2Material` (MPa,
            block diagonal, in the reference orientation); None for the isotropic law.
        F_n: (2, 2) the in-plane deformation gradient of the last converged step, which the midpoint
            return (``J2Material(..., integration="midpoint")``) needs to rotate that step's stress into
            the current configuration (identity initially); None for the radial return.
        dev_n: (5,) that step's deviatoric elastic log strain (xx, xy, yx, yy, zz; zero initially), kept
            by the midpoint return so that no Newton iteration takes its logarithm again; None for the
            radial return.
    """

    cp_inv: jax.Array
    cp_inv_zz: jax.Array
    eqps: jax.Array
    enhanced: jax.Array | None = None
    back: jax.Array | None = None
    F_n: jax.Array | None = None
    dev_n: jax.Array | None = None


def von_mises(tau: jax.Array) -> jax.Array:
    """Von Mises equivalent stress q = sqrt(3/2) |dev tau| of a (3, 3) stress (MPa); kink-safe at 0."""
    dev = tau - (jnp.trace(tau) / 3.0) * jnp.eye(3, dtype=tau.dtype)
    return _SQRT_3_2 * safe_norm(dev)


def trial_log_strain(F: jax.Array, state: MaterialState) -> tuple[jax.Array, jax.Array]:
    """The trial elastic log strain eps_tr = 1/2 ln(F C_p,n^-1 F^T): its in-plane block (2, 2) and zz entry."""
    return 0.5 * sym2_log(F @ state.cp_inv @ F.T), 0.5 * jnp.log(state.cp_inv_zz)


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _number_like(name: str, value) -> None:
    """A material constant must be a real number (or an array / tracer of them): name it otherwise."""
    if value is None or isinstance(value, (str, bytes, bool)) or np.iscomplexobj(value):
        raise ValueError(f"J2Material: {name} = {value!r} is invalid: it must be a real number.")


class J2Material(eqx.Module):
    """Plane-strain finite-strain J2 plasticity, Hencky energy in log elastic strains,
    sigma_Y = sigma_y (1 + A eqps)^n.

        psi(eps^e) = 1/2 kappa (tr eps^e)^2 + G |dev eps^e|^2
        kappa      = E / (3(1 - 2 nu)),   G = E / (2(1 + nu))
        tau        = kappa (tr eps^e) I + 2G dev eps^e                       (Kirchhoff stress)
        Phi        = sqrt(3/2) |dev tau| - sigma_Y(eqps),   sigma_Y(eqps) = sigma_y (1 + A eqps)^n

    Attributes (float64 array leaves, so new values neither retrace nor block `jax.grad`):
        E: Young's modulus (MPa), > 0 and finite.
        nu: Poisson's ratio, in (-1, 0.5).
        sigma_y: initial yield stress (MPa), > 0; +inf means purely elastic.
        A: hardening coefficient, >= 0 and finite (A = 0: perfectly plastic).
        n: hardening exponent, >= 0 and finite (n = 0: perfectly plastic; n < 0 would soften).
        integration: how a step's plastic flow is integrated (static), one of :data:`INTEGRATIONS`:
            ``"radial"``, the exponential-map radial return (backward Euler, the flow along the end
            point's deviator: first order in the step where the strain path turns), or ``"midpoint"``
            (:meth:`update`: the flow along the mean of the deviators where the step's path leaves the
            yield surface and of the trial, consistency at the end of the step: second order).
    """

    E: jax.Array
    nu: jax.Array
    sigma_y: jax.Array
    A: jax.Array
    n: jax.Array
    integration: str = eqx.field(static=True, default="radial")

    def __init__(self, E, nu, sigma_y, A, n, integration="radial"):
        for name, value in (("E", E), ("nu", nu), ("sigma_y", sigma_y), ("A", A), ("n", n)):
            _number_like(name, value)
        if integration not in INTEGRATIONS:
            raise ValueError(f"J2Material: integration = {integration!r} is invalid: use one of "
                             f"{', '.join(INTEGRATIONS)}.")
        self.integration = integration
        self.E = jnp.asarray(E, jnp.float64)
        self.nu = jnp.asarray(nu, jnp.float64)
        self.sigma_y = jnp.asarray(sigma_y, jnp.float64)
        self.A = jnp.asarray(A, jnp.float64)
        self.n = jnp.asarray(n, jnp.float64)

    def __check_init__(self):
        # Only concrete values can be checked; inside jit/grad the leaves are tracers.
        def bad(name, value, ok, why):
            if _is_concrete(value) and not np.all(ok(np.asarray(value))):
                raise ValueError(f"J2Material: {name} = {np.asarray(value)} is invalid: {why}.")

        bad("E", self.E, lambda v: np.isfinite(v) & (v > 0), "it must be finite and > 0")
        bad("nu", self.nu, lambda v: np.isfinite(v) & (v > -1) & (v < 0.5), "it must lie in (-1, 0.5)")
        bad("sigma_y", self.sigma_y, lambda v: ~np.isnan(v) & (v > 0), "it must be > 0 (+inf: elastic)")
        bad("A", self.A, lambda v: np.isfinite(v) & (v >= 0), "it must be finite and >= 0")
        bad("n", self.n, lambda v: np.isfinite(v) & (v >= 0), "it must be finite and >= 0 (n < 0 softens)")

    @classmethod
    def elastic(cls, E, nu) -> "J2Material":
        """Purely elastic Hencky material: sigma_y = +inf, A = 0, n = 0 (never yields)."""
        return cls(E=E, nu=nu, sigma_y=jnp.inf, A=0.0, n=0.0)

    @property
    def bulk_modulus(self) -> jax.Array:
        """kappa = E / (3 (1 - 2 nu)), MPa."""
        return self.E / (3.0 * (1.0 - 2.0 * self.nu))

    @property
    def shear_modulus(self) -> jax.Array:
        """G = E / (2 (1 + nu)), MPa."""
        return self.E / (2.0 * (1.0 + self.nu))

    def _sigma_y_finite(self) -> tuple[jax.Array, jax.Array]:
        # Double where for sigma_y = +inf: products like inf * 0 would turn a zero cotangent into NaN.
        finite = jnp.isfinite(self.sigma_y)
        return finite, jnp.where(finite, self.sigma_y, jnp.ones_like(self.sigma_y))

    def _hardening_factor(self, eqps: jax.Array, power: jax.Array) -> jax.Array:
        # (1 + A eqps)^power; the base is >= 1 for A, eqps >= 0, so no 0^negative even when n < 1.
        return (1.0 + self.A * eqps) ** power

    def yield_stress(self, eqps: jax.Array) -> jax.Array:
        """sigma_Y(eqps) = sigma_y (1 + A eqps)^n, MPa (+inf for the elastic material). eqps: any shape."""
        finite, sigma_y = self._sigma_y_finite()
        value = sigma_y * self._hardening_factor(eqps, self.n)
        return jnp.where(finite, value, jnp.full_like(value, jnp.inf))

    def hardening_slope(self, eqps: jax.Array) -> jax.Array:
        """sigma_Y'(eqps) = sigma_y n A (1 + A eqps)^(n - 1), MPa; 0 for the elastic material (0 * inf := 0)."""
        finite, sigma_y = self._sigma_y_finite()
        value = sigma_y * self.n * self.A * self._hardening_factor(eqps, self.n - 1.0)
        return jnp.where(finite, value, jnp.zeros_like(value))

    def init_state(self) -> MaterialState:
        """Virgin state: C_p^-1 = I (so b^e = I at F = I), eqps = 0; stress-free."""
        return MaterialState(
            cp_inv=jnp.eye(2, dtype=jnp.float64),
            cp_inv_zz=jnp.asarray(1.0, jnp.float64),
            eqps=jnp.asarray(0.0, jnp.float64),
            F_n=jnp.eye(2, dtype=jnp.float64) if self.integration == "midpoint" else None,
            dev_n=jnp.zeros(5, jnp.float64) if self.integration == "midpoint" else None,
        )

    def _return_residual(self, dg, q_trial, eqps_n):
        """R(dg) = q_tr - 3G dg - sigma_Y(eqps_n + dg) and R'(dg); an infinite sigma_y is replaced by 1."""
        _, sigma_y = self._sigma_y_finite()
        eqps = eqps_n + dg
        three_g = 3.0 * self.shear_modulus
        residual = q_trial - three_g * dg - sigma_y * self._hardening_factor(eqps, self.n)
        slope = -three_g - sigma_y * self.n * self.A * self._hardening_factor(eqps, self.n - 1.0)
        return residual, slope

    def update(self, F: jax.Array, state: MaterialState) -> tuple[jax.Array, MaterialState]:
        """Stress update n -> n+1 at one point: exponential-map radial return (Simo & Hughes 1998, ch. 9).

        Args:
            F: (2, 2) in-plane deformation gradient F_{n+1} (F_zz = 1, plane strain; the element passes
                F-bar), det F > 0.
            state: history at t_n.

        Returns:
            tau: (3, 3) Kirchhoff stress (MPa), block diagonal (in-plane block + zz).
            new_state: history at t_{n+1}.

        Algorithm (spec section 1.2):
            b^e_tr = F C_p,n^-1 F^T,  eps_tr = 1/2 ln b^e_tr,  tau_tr = kappa tr(eps_tr) I + 2G dev(eps_tr),
            q_tr = sqrt(3/2) |dev tau_tr|.  Elastic if q_tr - sigma_Y(eqps_n) <= 1e-10 sigma_Y (round-off guard);
            otherwise solve R(dg) = q_tr - 3G dg - sigma_Y(eqps_n + dg) = 0 by Newton from dg = 0 and set
            eps^e = eps_tr - sqrt(3/2) dg N = eps_tr - (3G dg / q_tr) dev eps_tr,  eqps_{n+1} = eqps_n + dg,
            b^e_{n+1} = exp(2 eps^e),  C_p,n+1^-1 = F^-1 b^e_{n+1} F^-T.

        Differentiation: the Newton loop runs on stop-gradient'ed inputs; one more Newton step
        dg = dg* - R(dg*) / R'(dg*) taken with gradients on gives, at convergence (R(dg*) = 0), the
        implicit-function derivative d(dg) = -dR / R' for F and for the material parameters, in both
        forward and reverse mode (first derivatives; higher ones are not exact). A run past the
        iteration cap returns its last iterate.
        """
        tau, new_state, _ = self._from_trial(F, state, *trial_log_strain(F, state))
        return tau, new_state

    def _from_trial(self, F, state, eps_trial, eps_trial_zz):
        """:meth:`update` from the trial elastic log strain (eq. b^e_tr = f b^e_n f^T, written with C_p^-1):
        tau, the new state, and the radial return's :class:`_Flow` (None for the midpoint rule)."""
        kappa, G = self.bulk_modulus, self.shear_modulus
        trace = jnp.trace(eps_trial) + eps_trial_zz
        dev_trial = eps_trial - (trace / 3.0) * jnp.eye(2, dtype=F.dtype)
        dev_trial_zz = eps_trial_zz - trace / 3.0
        # |dev eps| is 0 at F = I, where the tangent is first taken: safe_norm keeps it NaN-free.
        dev_norm = safe_norm(jnp.concatenate([dev_trial.ravel(), dev_trial_zz[None]]))
        q_trial = _SQRT_3_2 * 2.0 * G * dev_norm

        # Round-off guard: re-evaluating a converged plastic point (as every load step's first Newton
        # iteration does) puts q_tr on the yield surface up to ~1e-14 relative. Without a tolerance the
        # branch, and with it the tangent (elastic or elasto-plastic), is decided by round-off, and an
        # elastic unloading step starting from the elasto-plastic tangent needs many iterations.
        # Overshoots below 1e-10 sigma_Y are taken as elastic; the stress error is below that.
        plastic = q_trial - self.yield_stress(state.eqps) > _YIELD_TOL * self.yield_stress(state.eqps)

        flow = None
        if self.integration == "midpoint":
            dev, dev_zz, dg = self._midpoint_return(F, state, dev_trial, dev_trial_zz, plastic)
        else:
            # Double where: the elastic case hands the return a trial stress already on the yield surface
            # (R(0) = 0 exactly, zero iterations, dg = 0 with zero derivative) and divides by 1, not q_tr.
            _, sigma_y = self._sigma_y_finite()
            q_on_surface = sigma_y * self._hardening_factor(state.eqps, self.n)
            q_return = jnp.where(plastic, q_trial, q_on_surface)
            q_divisor = jnp.where(plastic, q_trial, jnp.ones_like(q_trial))
            dg_star = _newton_return(
                jax.lax.stop_gradient(self), jax.lax.stop_gradient(q_return), jax.lax.stop_gradient(state.eqps)
            )
            residual, slope = self._return_residual(dg_star, q_return, state.eqps)
            dg = dg_star - residual / slope
            # R(0) = 0 already gives dg = 0 when elastic; the where makes it exact whatever XLA's fusion does.
            dg = jnp.where(plastic, dg, jnp.zeros_like(dg))

            # Radial return: only the deviator shrinks, by the factor q_{n+1} / q_tr (1 when elastic).
            shrink = 1.0 - 3.0 * G * dg / q_divisor
            dev = shrink * dev_trial
            dev_zz = shrink * dev_trial_zz
            flow = _Flow(dev_trial, dev_trial_zz, dev_norm, plastic, dg, slope, q_divisor, shrink)
        tau_2d = kappa * trace * jnp.eye(2, dtype=F.dtype) + 2.0 * G * dev
        tau_zz = kappa * trace + 2.0 * G * dev_zz
        tau = jnp.zeros((3, 3), F.dtype).at[:2, :2].set(tau_2d).at[2, 2].set(tau_zz)

        # New plastic metric C_p^-1 = F^-1 b^e F^-T; an elastic step leaves it exactly unchanged.
        eps_2d = dev + (trace / 3.0) * jnp.eye(2, dtype=F.dtype)
        eps_zz = dev_zz + trace / 3.0
        F_inv = inv2(F)
        cp_inv_plastic = F_inv @ sym2_exp(2.0 * eps_2d) @ F_inv.T
        cp_inv_plastic = 0.5 * (cp_inv_plastic + cp_inv_plastic.T)
        new_state = MaterialState(
            cp_inv=jnp.where(plastic, cp_inv_plastic, state.cp_inv),
            cp_inv_zz=jnp.where(plastic, jnp.exp(2.0 * eps_zz), state.cp_inv_zz),
            eqps=state.eqps + dg,
            enhanced=state.enhanced,
            F_n=F if self.integration == "midpoint" else None,
            dev_n=jnp.concatenate([dev.ravel(), dev_zz[None]]) if self.integration == "midpoint" else None,
        )
        return tau, new_state, flow

    def piola_and_tangent(self, F: jax.Array, state: MaterialState):
        """The first Piola stress P = tau F^-T (in-plane block), its derivative dP/dF and the update.

        Returns:
            dP_dF: (2, 2, 2, 2), dP_ij / dF_kl; (P, tau, new_state): :func:`piola`'s.

        The radial return's consistent tangent in closed form: d eps_tr = 1/2 d log(b^e_tr)[dF C_p^-1 F^T
        + F C_p^-1 dF^T] (:func:`~jaxfric.numerics.tensor.sym2_log_derivative`, the four unit dF at
        once), then, with the return's dg differentiated as :meth:`update` does (d dg = -dq_tr / R'(dg*),
        zero where elastic) and shrink = 1 - 3G dg / q_tr,
            d tau = kappa tr(d eps) I + 2G (shrink d dev + d shrink dev eps_tr),
            dP = d tau F^-T - tau F^-T dF^T F^-T:
        ``jacfwd`` of :func:`piola` to round-off (``tests/test_material.py``), the Nine's element forces and
        tangents in 0.78 times their time with it (``python experiments/bench_element_tangent.py``). The
        midpoint rule takes ``jacfwd``.
        """
        if self.integration != "radial":
            return piola_and_tangent_ad(self, F, state)
        kappa, G = self.bulk_modulus, self.shear_modulus
        # Written entry by entry, each entry a vector over the four directions dF = e_k (x) e_l (k-major):
        # under vmap every operation is then elementwise, which XLA's CPU backend vectorises (batches of
        # tiny matrix products or reductions run several times slower).
        row_k, col_l = np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1])
        row = (state.cp_inv @ F.T)[col_l]                            # (4, 2): row l of C_p^-1 F^T, per direction
        on_0, on_1 = jnp.asarray(row_k == 0, F.dtype), jnp.asarray(row_k == 1, F.dtype)
        # d b = S + S^T with S = dF C_p^-1 F^T, whose only nonzero row is row k = row l of C_p^-1 F^T.
        d_b = jnp.stack([jnp.stack([2.0 * on_0 * row[:, 0], on_0 * row[:, 1] + on_1 * row[:, 0]], -1),
                         jnp.stack([on_0 * row[:, 1] + on_1 * row[:, 0], 2.0 * on_1 * row[:, 1]], -1)], -2)
        log_b, d_log_b = sym2_log_derivative(F @ state.cp_inv @ F.T, d_b)   # b as trial_log_strain forms it
        tau, new_state, flow = self._from_trial(F, state, 0.5 * log_b, 0.5 * jnp.log(state.cp_inv_zz))
        assert flow is not None

        d_eps = [[0.5 * d_log_b[:, i, j] for j in range(2)] for i in range(2)]   # d eps_zz = 0
        d_trace = d_eps[0][0] + d_eps[1][1]
        d_dev = [[d_eps[i][j] - (d_trace / 3.0 if i == j else 0.0) for j in range(2)] for i in range(2)]
        dev = flow.dev_trial
        d_norm = (sum(dev[i, j] * d_dev[i][j] for i in range(2) for j in range(2))
                  - flow.dev_trial_zz * d_trace / 3.0) / jnp.where(flow.dev_norm > 0, flow.dev_norm, 1.0)
        d_q = jnp.where(flow.plastic, _SQRT_3_2 * 2.0 * G * d_norm, 0.0)   # elastic: q held on the surface
        d_dg = jnp.where(flow.plastic, -d_q / flow.slope, 0.0)
        d_shrink = -3.0 * G * (d_dg / flow.q_divisor - flow.dg * d_q / flow.q_divisor**2)
        F_inv_T = inv2(F).T
        P = tau[:2, :2] @ F_inv_T
        # dP = (d tau - P dF^T) F^-T, and (P dF^T)_ij = P_il delta_jk.
        d_stress = [[kappa * d_trace * (1.0 if i == j else 0.0)
                     + 2.0 * G * (flow.shrink * d_dev[i][j] + d_shrink * dev[i, j])
                     - P[i, col_l] * jnp.asarray(row_k == j, F.dtype) for j in range(2)] for i in range(2)]
        d_P = jnp.stack([jnp.stack([d_stress[i][0] * F_inv_T[0, j] + d_stress[i][1] * F_inv_T[1, j]
                                    for j in range(2)]) for i in range(2)])   # (2, 2, 4)
        return d_P.reshape(2, 2, 2, 2), (P, tau, new_state)

    def _midpoint_residual(self, dg, size, along, eqps_n):
        """R(dg) = sqrt(6) G |v - sqrt(3/2) dg w| - sigma_Y(eqps_n + dg) and R'(dg), from |v|^2 (``size``)
        and v . w (``along``) (:meth:`_midpoint_return`)."""
        _, sigma_y = self._sigma_y_finite()
        G = self.shear_modulus
        x = _SQRT_3_2 * dg
        norm = jnp.sqrt(jnp.maximum(size - 2.0 * x * along + x * x, 0.0))
        slope = 3.0 * G * (x - along) / jnp.where(norm > 0, norm, 1.0)
        return (2.0 * _SQRT_3_2 * G * norm - sigma_y * self._hardening_factor(eqps_n + dg, self.n),
                slope - sigma_y * self.n * self.A * self._hardening_factor(eqps_n + dg, self.n - 1.0))

    def _midpoint_return(self, F, state, dev_trial, dev_trial_zz, plastic):
        """The elastic deviatoric log strain (in-plane (2, 2), zz) and the plastic increment dg of a step
        whose flow follows the midpoint of its plastic part (``integration="midpoint"``).

        In the 5 components v = (dev eps_xx, _xy, _yx, _yy, _zz) of the deviatoric log strain (where the
        stress deviator is 2G v and the yield surface the sphere |v| = r = sigma_Y / (sqrt(6) G)):
        - v_n, the last converged step's (kept in ``state.dev_n``), rotated into the current
          configuration by the rotation of the step's relative deformation f = F F_n^-1 (its polar
          decomposition), so the rule is objective;
        - v_c = v_n + theta (v_tr - v_n), where the straight path from v_n to the trial leaves the yield
          surface (the larger root theta of |v_c| = r, clipped to [0, 1]: 0 where the path leaves it at
          once, as for a point that was plastic and keeps flowing);
        - the flow direction w = (v_c + v_tr) / |v_c + v_tr|: the direction of the mean of the plastic
          part's ends v_c and v_{n+1}, since v_{n+1} = v_tr - sqrt(3/2) dg w (the midpoint rule);
        - v = v_tr - sqrt(3/2) dg w, and dg from the consistency at the step's end,
          R(dg) = sqrt(6) G |v_tr - sqrt(3/2) dg w| - sigma_Y(eqps_n + dg) = 0, by Newton from 0 (R is
          convex and decreasing, as the radial return's), differentiated by one more Newton step.
        Where v_n and v_tr are parallel (a proportional path) this is the radial return; where the
        path turns its error falls with the square of the step, the radial return's with the step
        (``tests/test_material.py``). Elastic points take the double-where route of :meth:`update`:
        their residual is evaluated on the yield surface, so that no branch divides by zero."""
        G = self.shear_modulus
        f = F @ inv2(state.F_n)
        angle = jnp.arctan2(f[1, 0] - f[0, 1], f[0, 0] + f[1, 1])
        c, s = jnp.cos(angle), jnp.sin(angle)
        rot = jnp.stack([jnp.stack([c, -s]), jnp.stack([s, c])])
        v_n = jnp.concatenate([(rot @ state.dev_n[:4].reshape(2, 2) @ rot.T).ravel(), state.dev_n[4:]])
        v_tr = jnp.concatenate([dev_trial.ravel(), dev_trial_zz[None]])

        _, sigma_y = self._sigma_y_finite()
        r = sigma_y * self._hardening_factor(state.eqps, self.n) / (2.0 * _SQRT_3_2 * G)
        dv = v_tr - v_n
        a, b, c0 = dv @ dv, 2.0 * (v_n @ dv), v_n @ v_n - r * r
        disc = b * b - 4.0 * a * c0
        crosses = plastic & (a > 0) & (disc > 0)
        root = (-b + jnp.sqrt(jnp.where(crosses, disc, 1.0))) / (2.0 * jnp.where(crosses, a, 1.0))
        theta = jnp.where(crosses, jnp.clip(root, 0.0, 1.0), 0.0)
        w = v_n + theta * dv + v_tr
        unit = jnp.zeros_like(w).at[0].set(1.0)
        w = jnp.where(plastic & (w @ w > 0), w, unit)
        w = w / jnp.sqrt(w @ w)
        v_res = jnp.where(plastic, v_tr, r * w)       # elastic: on the yield surface, R(0) = 0
        size, along = v_res @ v_res, v_res @ w
        stop = jax.lax.stop_gradient
        law = stop(self)
        dg_star = scalar_newton(lambda dg: law._midpoint_residual(dg, stop(size), stop(along), stop(state.eqps)),
                                _NEWTON_RTOL * stop(sigma_y), jnp.zeros_like(state.eqps), stop(plastic))
        residual, slope = self._midpoint_residual(dg_star, size, along, state.eqps)
        dg = jnp.where(plastic, dg_star - residual / slope, jnp.zeros_like(dg_star))
        v = v_tr - _SQRT_3_2 * dg * w
        return v[:4].reshape(2, 2), v[4], dg


class _Flow(NamedTuple):
    """What the radial return's consistent tangent needs of :meth:`J2Material._from_trial`."""

    dev_trial: jax.Array      # (2, 2) deviatoric trial log strain, in-plane
    dev_trial_zz: jax.Array   # () its zz entry
    dev_norm: jax.Array       # () |dev eps_tr| over the 3 x 3 tensor
    plastic: jax.Array        # () bool
    dg: jax.Array             # () the plastic increment (0 where elastic)
    slope: jax.Array          # () R'(dg*) of the return's equation
    q_divisor: jax.Array      # () q_tr where plastic, 1 where elastic
    shrink: jax.Array         # () 1 - 3G dg / q_divisor


def piola(material, F: jax.Array, state: MaterialState):
    """(P, tau, new_state) of a point law (``update(F, state) -> (tau, new_state)``): the first Piola
    stress P = tau F^-T (in-plane block), the Kirchhoff stress and the updated history."""
    tau, new_state = material.update(F, state)
    return tau[:2, :2] @ inv2(F).T, tau, new_state


def piola_and_tangent(material, F: jax.Array, state: MaterialState):
    """(dP/dF (2, 2, 2, 2), (P, tau, new_state)) of a point law: the law's own closed form where it has
    one (:meth:`J2Material.piola_and_tangent`), else ``jacfwd`` of :func:`piola`."""
    closed = getattr(material, "piola_and_tangent", None)
    return closed(F, state) if closed is not None else piola_and_tangent_ad(material, F, state)


def piola_and_tangent_ad(material, F: jax.Array, state: MaterialState):
    """:func:`piola_and_tangent` with dP/dF by ``jacfwd`` of :func:`piola`, whatever the law."""
    def with_aux(f):
        out = piola(material, f, state)
        return out[0], out
    return jax.jacfwd(with_aux, has_aux=True)(F)


def _newton_return(material: J2Material, q_trial: jax.Array, eqps_n: jax.Array) -> jax.Array:
    """Solve q_tr - 3G dg - sigma_Y(eqps_n + dg) = 0 for dg by Newton from dg = 0 (no gradients).

    R is decreasing; for n <= 1 it is convex, so the iterates increase monotonically to the root.
    Stops at |R| <= 1e-12 sigma_y, or when the step no longer changes dg (roundoff floor), or after
    _NEWTON_MAX_ITER iterations.
    """
    _, sigma_y = material._sigma_y_finite()
    return scalar_newton(lambda dg: material._return_residual(dg, q_trial, eqps_n), _NEWTON_RTOL * sigma_y,
                         jnp.zeros_like(q_trial))


def scalar_newton(residual_and_slope, tol, zero, active=True) -> jax.Array:
    """The root of a decreasing scalar function R (``residual_and_slope(dg) -> (R, R')``) by Newton from
    ``zero`` (no gradients: the return mappings differentiate the converged root by one more step).
    Stops at |R| <= ``tol``, when a step no longer changes dg (the round-off floor), after
    _NEWTON_MAX_ITER iterations, or at once where not ``active`` (an elastic point)."""
    residual0 = jnp.where(active, residual_and_slope(zero)[0], jnp.zeros_like(zero))

    def not_done(carry):
        it, dg, residual, step = carry
        # The stagnation test matters under vmap, where one stuck point would keep the batch looping.
        moving = jnp.abs(step) > _STAGNATION * jnp.abs(dg)
        return (jnp.abs(residual) > tol) & moving & (it < _NEWTON_MAX_ITER)

    def newton_step(carry):
        it, dg, residual, _ = carry
        _, slope = residual_and_slope(dg)
        step = -residual / slope
        residual, _ = residual_and_slope(dg + step)
        return it + 1, dg + step, residual, step

    init = (jnp.asarray(0, jnp.int32), zero, residual0, jnp.full_like(zero, jnp.inf))
    _, dg, _, _ = jax.lax.while_loop(not_done, newton_step, init)
    return dg
