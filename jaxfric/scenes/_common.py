"""Building blocks shared by the four scene modules: config fields with units, validation, the
per-step columns common to every scene, the ``contact.npz`` snapshot, and the JSON description of a
load schedule (benchmarks spec sections 0 and 6; outputs spec sections 2 to 4).

Units: mm, MPa, N/mm (per unit out-of-plane width), degrees in configs, s of pseudo-time.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..contact.formulations import ALGORITHMS, STIFF_PENALTY_RATIO
from ..contact.friction import Polynomial, VelocityDecay
from ..contact.preselection import PAYS_FROM, tool_capacity
from ..contact.rigid import has_friction_law, max_penetration, pair_friction, split_pairs
from ..contact.status import SLIP
from ..contact.tools import GAP_OPEN, Arc, Segment, Tool
from ..fem.element import ENHANCED_UPDATES, QUADRATIC_FORMULATIONS
from ..fem.kinematic import KinematicJ2Material
from ..fem.loading import Phase, constraint_masks, schedule
from ..fem.material import INTEGRATIONS, J2Material
from ..fem.mesh import ORDERS
from ..loadpath.controller import STABILIZE, STALL_STEPS, StepControl
from ..loadpath.model import reactions

__all__ = ["spec_field", "PreselectField", "SolverFields", "preselected",
           "check_config", "check_steady_window", "check_variant", "check_algorithm", "pair_forces",
           "tool_resultants", "contact_columns", "phase_progress", "ContactSnapshot", "n_steps",
           "schedule_entry", "friction_table", "material", "material_dict", "config_dict", "end_reaction",
           "resolve_eps_t", "step_control", "stiff_penalty"]


def spec_field(default, unit: str, doc: str):
    """A config field with its unit and a one-line description (listed by ``jaxfric scenes``)."""
    return dataclasses.field(default=default, metadata={"unit": unit, "doc": doc})


# ---- validation -------------------------------------------------------------------------------------

SMOOTHING_DOC = ("force scale of the smoothed contact law (penalty and auglag; for gradients through "
                 "contact opening and stick/slip switches); 0: the exact law [chosen]")
BAND_DOC = ("exact contact by lcp_lemke: candidate nodes nearest to a tool that enter the condensed "
            "complementarity problem; None: all. Too small a band fails the attempt with CONTACT_BAND, and "
            "the run widens it and tries the step again (doubled, at most all: BAND_FULL, noted in "
            "summary.json's message) (lcp_ssn works on every candidate and ignores it)")
MAX_AUGMENTATIONS_DOC = ("auglag: augmentations allowed per step attempt before it fails (spec 1.6: 20) "
                         "[chosen]")
MAX_STEPS_DOC = ("size of the history buffer in accepted steps; a run that fills it stops (MAX_STEPS). "
                 "None: 10x the nominal step count + 200 [chosen]")
STABILIZE_DOC = ("the step controller's damper where a step fails at the smallest increment: eta = stabilize E "
                 "(N/mm per mm) on every free node's increment, then 100 eta; the energy it takes is reported "
                 "(jaxfric.loadpath.controller.StepControl). 0: a run stops there instead [chosen]")
STALL_STEPS_DOC = ("consecutive steps taken at the smallest increment after failed attempts, after which a run "
                   "stops as stalled (STALLED, its results kept: jaxfric.loadpath.controller.StepControl) [chosen]")
STEP_ERROR_DOC = ("increments by the estimate of each step's time-discretisation error: the target of the relative "
                  "error of a step's plastic work (jaxfric.loadpath.step_error); 0: the nominal increments "
                  "(spec 1.9) [chosen]")
ELEMENTS = ("fbar", "ans", "anst", "eas")  # plain Q4 locks in plastic flow: kept for elastic checks only
ELEMENT_DOC = ("element formulation (jaxfric.fem.element): 'fbar' F-bar Q4, 'ans' F-bar with assumed "
               "natural strain through the thickness (no parasitic shear), 'anst' assumed natural strain with "
               "a condensed through-thickness mode (no parasitic shear, exact elastic bending at 2 layers), "
               "'eas' enhanced strain Q1/E4")
ELEMENT_ORDER_DOC = ("the elements' order along the strip (jaxfric.fem.mesh): 1 bilinear, 2 quadratic along the strip "
                     "and linear through each layer (six nodes; with element='anst': the bending strain varies "
                     "linearly along each element) [chosen]")
THICKNESS_POINTS_DOC = ("Gauss points through each element's thickness (2: the 2 x 2 rule; more integrate the "
                        "stress through the thickness more finely at the cost of more material evaluations; "
                        "jaxfric.fem.element.gauss_rule) [chosen]")
ENHANCED_UPDATE_DOC = ("how 'anst' and 'eas' find their enhanced parameters in a Newton loop: 'iterate' with the "
                       "Newton iterate (the enhanced-strain update: one material pass per iteration), 'local' "
                       "by a local solve in every element evaluation (the same answer; jaxfric.fem.element) "
                       "[chosen]")
FRICTION_LAWS = ("coulomb", "polynomial", "velocity_decay")
FRICTION_LAW_DOC = ("friction law of the frictional tools, in phases where mu > 0 (jaxfric.contact.friction): "
                    "coulomb (mu); polynomial: mu = max(mu + mu_p p + mu_v v + mu_pv p v + mu_pp p^2 + mu_vv v^2, "
                    "0), p the contact pressure (MPa), v the sliding speed (mm/s); velocity_decay: mu = mu_d + "
                    "(mu - mu_d) exp(-decay v) [chosen]")
POLYNOMIAL_TERMS = ("mu_p", "mu_v", "mu_pv", "mu_pp", "mu_vv")
MU_P_DOC = "friction_law=polynomial: coefficient of p (1/MPa; OpenRadioss C1) [chosen]"
MU_V_DOC = "friction_law=polynomial: coefficient of v (s/mm; OpenRadioss C2) [chosen]"
MU_PV_DOC = "friction_law=polynomial: coefficient of p v (s/(MPa mm); OpenRadioss C3) [chosen]"
MU_PP_DOC = "friction_law=polynomial: coefficient of p^2 (1/MPa^2; OpenRadioss C4) [chosen]"
MU_VV_DOC = "friction_law=polynomial: coefficient of v^2 (s^2/mm^2; OpenRadioss C5) [chosen]"
MU_D_DOC = "friction_law=velocity_decay: dynamic coefficient (LS-DYNA FD; None: mu, no decay) [chosen]"
DECAY_DOC = "friction_law=velocity_decay: decay coefficient (s/mm; LS-DYNA DC) [chosen]"
SPEED_PERIOD_DOC = ("friction laws of speed: time constant of the first-order filter through which a pair's slip "
                    "rate becomes the speed its law reads (s; 0: the last step's rate, which oscillates at short "
                    "steps; jaxfric.contact.friction) [chosen]")
DRAW_SPEED_DOC = ("drawing speed (mm/s): the drawing phase lasts its stroke over this speed, which gives a friction "
                  "law its sliding speeds; the other phases have none (v = 0) [chosen]")


@dataclasses.dataclass(frozen=True)
class FrictionLawFields:
    """The friction-law fields every scene's config has (:func:`friction_law`, :func:`phase_seconds`)."""

    friction_law: str = spec_field("coulomb", "-", FRICTION_LAW_DOC)
    mu_p: float = spec_field(0.0, "1/MPa", MU_P_DOC)
    mu_v: float = spec_field(0.0, "s/mm", MU_V_DOC)
    mu_pv: float = spec_field(0.0, "s/(MPa mm)", MU_PV_DOC)
    mu_pp: float = spec_field(0.0, "1/MPa^2", MU_PP_DOC)
    mu_vv: float = spec_field(0.0, "s^2/mm^2", MU_VV_DOC)
    mu_d: float | None = spec_field(None, "-", MU_D_DOC)
    decay: float | None = spec_field(None, "s/mm", DECAY_DOC)
    draw_speed: float = spec_field(1.0, "mm/s", DRAW_SPEED_DOC)
    speed_period: float = spec_field(0.005, "s", SPEED_PERIOD_DOC)


PRESELECT_DOC = ("True: evaluate, in each load step, only the candidate nodes nearest to each tool that can reach "
                 "it within the step (jaxfric.contact.preselection; results unchanged); False: every candidate at "
                 f"every Newton iteration; None: True where the tools' capacities leave out {PAYS_FROM} pairs or more "
                 "(PAYS_FROM), False below, where the selection costs more compilation than it saves [chosen]")


PLASTIC_INTEGRATION_DOC = ("how a load step's plastic flow is integrated (jaxfric.fem.material.J2Material): 'radial' "
                           "the exponential-map radial return along the end point's flow direction (backward "
                           "Euler, first order in the increment where the strain path turns), 'midpoint' along "
                           "the mean of the plastic part's ends, consistent at the step's end (second order; "
                           "isotropic hardening only) [chosen]")


@dataclasses.dataclass(frozen=True)
class PlasticIntegrationField:
    """The plastic integration switch every scene's config has (:func:`material`)."""

    plastic_integration: str = spec_field("radial", "-", PLASTIC_INTEGRATION_DOC)


LEMKE_SEARCH_DOC = ("lcp_lemke: line-search its Newton steps on the semismooth merit as lcp_ssn's are "
                    "(jaxfric.contact.exact, step 6), so that Lemke takes lcp_ssn's steps; False: full Newton "
                    "steps, which invert elements or end on rays where lcp_ssn takes the step and leave the "
                    "Nine's plan for 1.6 to 1.8 times its steps (docs/results.md, study common_steps) [chosen]")


EXACT_START_DOC = ("penalty and auglag: solve every step attempt first by exact contact's semismooth Newton and "
                   "start from its solution (penalty: jaxfric.contact.formulations.ExactStartPenalty, with the "
                   "penalty's compliance, which gives the penalty law's solution and derivatives on the steps the "
                   "plain law cuts; auglag: exact contact, its forces as the multipliers, exact contact's "
                   "solution and derivatives without augmenting); False: from the load loop's guess (the penalty "
                   "law from the compliant solve only after a failed attempt above the stiff threshold) [chosen]")


@dataclasses.dataclass(frozen=True)
class SolverFields:
    """The solver switches every scene's config has: Lemke's line search (``Complementarity.search``) and
    the penalty law's and the augmented Lagrangian's start from exact contact (``exact_start``)."""

    lemke_search: bool = spec_field(True, "-", LEMKE_SEARCH_DOC)
    exact_start: bool = spec_field(False, "-", EXACT_START_DOC)


@dataclasses.dataclass(frozen=True)
class PreselectField:
    """The pair pre-selection switch every scene's config has (:func:`preselected`)."""

    preselect: bool | None = spec_field(None, "-", PRESELECT_DOC)


def preselected(tools, mesh, on: bool | None) -> tuple:
    """``tools`` with their pair pre-selection's capacities (:func:`jaxfric.contact.preselection.tool_capacity`;
    a tool that reaches most of its candidates keeps them all); unchanged where ``on`` is False, or where it
    is None and the capacities leave out fewer than :data:`~jaxfric.contact.preselection.PAYS_FROM` pairs."""
    if on is False:
        return tuple(tools)
    nodes = np.asarray(mesh.nodes)
    out, left_out = [], 0
    for tool in tools:
        idx = np.asarray(tool.candidates)
        along = idx[np.argsort(nodes[idx, 0], kind="stable")]   # consecutive along the strip
        capacity = tool_capacity(tool.geometry, nodes[along])
        left_out += 0 if capacity is None else len(idx) - capacity
        out.append(dataclasses.replace(tool, capacity=capacity))
    if on is None and left_out < PAYS_FROM:
        return tuple(tools)
    return tuple(out)


C_KIN_DOC = ("moduli C_i of the Armstrong-Frederick back stresses, comma-separated, one per back stress "
             "(jaxfric.fem.kinematic); empty: isotropic hardening only [paper]")
GAMMA_KIN_DOC = ("recall rates gamma_i of the back stresses, one per C_i (0: linear Prager rule); the isotropic "
                 "radius is the monotonic curve less the back stresses' saturation, so monotonic loading keeps "
                 "the curve of sigma_y, A, n, Q_voce, b_voce [chosen]")
Q_VOCE_DOC = ("Voce terms Q_j (1 - exp(-b_j eqps)) added to the power law's monotonic curve, comma-separated "
              "(either sign; jaxfric.fem.kinematic); empty: the power law alone [paper]")
B_VOCE_DOC = "rates b_j of the Voce terms, one per Q_j [chosen]"
MAX_NOMINAL_STEPS = 1_000_000  # per phase: an increment that needs more is a typo, not a study
# A dimension of the sheet or a tool beyond 1 km is a typo; far beyond it the tool chains no longer close
# in float64 (an edge radius of 1e300 mm next to a 1 mm sheet) and derived lengths overflow.
MAX_LENGTH = 1e6  # mm


def _bad(field: str, value, why: str) -> ValueError:
    return ValueError(f"config field '{field}' = {value!r} is invalid: {why}")


def _number(field: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise _bad(field, value, "it must be a number")
    v = float(value)
    if not math.isfinite(v):
        raise _bad(field, value, "it must be finite")
    return v


def check_config(config, *, positive=(), nonnegative=(), integers=(), choices=None, lengths=()) -> None:
    """Validate the common fields of a scene config; every error names the field.

    Args:
        config: the config dataclass.
        positive: names of fields that must be finite and > 0 (None allowed: derived in build).
        nonnegative: names of fields that must be finite and >= 0 (None allowed).
        integers: names of fields that must be integers >= 1 (None allowed).
        choices: {field: allowed values} for string fields.
        lengths: names of the geometry's fields (mm) that must be finite with |value| <= MAX_LENGTH
            (None allowed).
    """
    for name in positive:
        v = getattr(config, name)
        if v is not None and not _number(name, v) > 0:
            raise _bad(name, v, "it must be > 0")
    for name in nonnegative:
        v = getattr(config, name)
        if v is not None and not _number(name, v) >= 0:
            raise _bad(name, v, "it must be >= 0")
    for name in integers:
        v = getattr(config, name)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1):
            raise _bad(name, v, "it must be an integer >= 1")
    for name in lengths:
        v = getattr(config, name)
        if v is not None and not abs(_number(name, v)) <= MAX_LENGTH:
            raise _bad(name, v, f"a length of the geometry must be at most {MAX_LENGTH:g} mm")
    for name, allowed in (choices or {}).items():
        v = getattr(config, name)
        if v not in allowed:
            raise _bad(name, v, f"choose one of {', '.join(map(repr, allowed))}")
    # Every scene carries the material of spec 1.2, the contact constants of spec 1.5-1.6 and an element.
    if len(config.C_kin) != len(config.gamma_kin):
        raise _bad("gamma_kin", config.gamma_kin, f"give one recall rate per modulus C_kin ({len(config.C_kin)})")
    if len(config.Q_voce) != len(config.b_voce):
        raise _bad("b_voce", config.b_voce, f"give one rate per Voce term Q_voce ({len(config.Q_voce)})")
    for name in ("C_kin", "gamma_kin", "Q_voce", "b_voce"):
        for v in getattr(config, name):
            if not (_number(name, v) >= 0 or name == "Q_voce"):
                raise _bad(name, getattr(config, name), "every entry must be >= 0")
    if config.plastic_integration not in INTEGRATIONS:
        raise _bad("plastic_integration", config.plastic_integration,
                   f"choose one of {', '.join(map(repr, INTEGRATIONS))}")
    if config.friction_law not in FRICTION_LAWS:
        raise _bad("friction_law", config.friction_law, f"choose one of {', '.join(map(repr, FRICTION_LAWS))}")
    for name in POLYNOMIAL_TERMS:
        v = _number(name, getattr(config, name))
        if not np.isfinite(v):
            raise _bad(name, v, "it must be finite")
        if v != 0.0 and config.friction_law != "polynomial":
            raise _bad(name, v, "a polynomial term needs --set friction_law=polynomial")
    for name in ("mu_d", "decay"):
        v = getattr(config, name)
        if v is not None and not _number(name, v) >= 0.0:
            raise _bad(name, v, "it must be >= 0")
        if v is not None and config.friction_law != "velocity_decay":
            raise _bad(name, v, "it needs --set friction_law=velocity_decay")
    if not _number("draw_speed", config.draw_speed) > 0.0:
        raise _bad("draw_speed", config.draw_speed, "it must be > 0")
    if not _number("speed_period", config.speed_period) >= 0.0 or not np.isfinite(config.speed_period):
        raise _bad("speed_period", config.speed_period, "it must be finite and >= 0")
    if config.element not in ELEMENTS:
        raise _bad("element", config.element, f"choose one of {', '.join(map(repr, ELEMENTS))}")
    if config.element_order not in ORDERS:
        raise _bad("element_order", config.element_order, f"choose one of {', '.join(map(repr, ORDERS))}")
    if config.element_order == 2 and config.element not in QUADRATIC_FORMULATIONS:
        raise _bad("element", config.element, "elements quadratic along the strip (element_order=2) take "
                   + " or ".join(repr(f) for f in QUADRATIC_FORMULATIONS if f in ELEMENTS))
    if config.enhanced_update not in ENHANCED_UPDATES:
        raise _bad("enhanced_update", config.enhanced_update,
                   f"choose one of {', '.join(map(repr, ENHANCED_UPDATES))}")
    if not -1.0 < _number("nu", config.nu) < 0.5:
        raise _bad("nu", config.nu, "Poisson's ratio must lie in (-1, 0.5)")
    for name in ("E", "sigma_y", "eps_n", "target_gap", "d_capture"):
        if not _number(name, getattr(config, name)) > 0:
            raise _bad(name, getattr(config, name), "it must be > 0")
    m = config.max_augmentations
    if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or not 1 <= m <= 10_000:
        raise _bad("max_augmentations", m, "it must be an integer from 1 to 10000")
    m = config.max_steps
    if m is not None and (isinstance(m, bool) or not isinstance(m, (int, np.integer)) or not 1 <= m <= 10_000_000):
        raise _bad("max_steps", m, "it must be an integer from 1 to 10000000, or None (10x the nominal steps)")
    for name in ("A", "n", "smoothing"):
        if not _number(name, getattr(config, name)) >= 0:
            raise _bad(name, getattr(config, name), "it must be >= 0")
    if config.eps_t is not None and not _number("eps_t", config.eps_t) >= 0:
        raise _bad("eps_t", config.eps_t, "it must be >= 0 (or None: mu * eps_n)")
    window = config.steady_window
    if (not isinstance(window, tuple) or len(window) != 2
            or not _number("steady_window", window[0]) < _number("steady_window", window[1])):
        raise _bad("steady_window", window, "it must be a pair (a, b) with a < b (mm)")


def check_steady_window(config, stroke: str) -> None:
    """A steady window given by the user must lie within the drawing stroke [0, config.<stroke>] (a
    default window beyond a shortened stroke leaves the run without a steady force, reported as such)."""
    (a, b), end = config.steady_window, getattr(config, stroke)
    if not 0.0 <= a < b <= end:
        raise _bad("steady_window", config.steady_window, f"it must lie within the drawing stroke [0, {end:g}] mm "
                                                          f"({stroke})")


def check_variant(scene: str, variants: dict, variant: str) -> None:
    if not isinstance(variant, str) or variant not in variants:
        raise ValueError(f"unknown variant {variant!r} of scene '{scene}'; choose one of "
                         f"{', '.join(variants)}")


def check_algorithm(algorithm: str) -> None:
    if not isinstance(algorithm, str) or algorithm not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {algorithm!r}; choose one of {', '.join(ALGORITHMS)}")


def resolve_eps_t(config, mu_max: float) -> float:
    """eps_t of the config, or the spec rule eps_t = mu eps_n (spec 1.5) when it is None."""
    return float(mu_max * config.eps_n) if config.eps_t is None else float(config.eps_t)


def n_steps(field: str, length: float, increment: float) -> int:
    """Number of nominal steps of size ``increment`` covering ``length`` (at least 1)."""
    if not _number(field, increment) > 0:
        raise _bad(field, increment, "a nominal increment must be > 0")
    count = abs(_number(field, length)) / increment
    if count > MAX_NOMINAL_STEPS:
        raise _bad(field, increment, f"it would take {count:.3g} nominal steps (at most {MAX_NOMINAL_STEPS:,})")
    return max(1, int(round(count)))


# ---- per-step columns -------------------------------------------------------------------------------

def movable(mesh, nodes, phases) -> np.ndarray:
    """``nodes`` (the candidates of a tool) less those held in both directions in every phase (a grip, a
    jaw): such a node cannot move, and a tool touching it would share its reaction with the grip in no
    determined way (the split moves force between a tool and the grip's reaction, and exact contact has
    no derivative there), so the tools act on the sheet's movable nodes only."""
    held = np.asarray(constraint_masks(mesh.n_nodes, phases).all(axis=0).reshape(-1, 2).all(axis=1), bool)
    nodes = np.asarray(nodes).ravel()
    return nodes[~held[nodes]]


def pair_forces(state) -> jnp.ndarray:
    """(m, 2) force on the sheet of every pair, f = R_N n + R_T t with t = (-n_y, n_x) (N/mm)."""
    c = state.contact
    tangent = jnp.stack([-c.normal[:, 1], c.normal[:, 0]], axis=1)
    return c.rn[:, None] * c.normal + c.rt[:, None] * tangent


def flat_faces(x_start: float, x_end: float, y_top: float, y_bottom: float, lip: float, d_capture) -> tuple:
    """Two fixed flat faces over x in [x_start, x_end] (mm) with convex quarter-circle lips of radius ``lip``
    at both ends: the upper at y_top with the sheet below it (normal side 'right'), the lower at
    y_bottom with the sheet above it ('left'). The bead's clamp dies and the Nine's entry guide."""
    a, b, r, pi = x_start, x_end, lip, math.pi
    upper = Tool((Arc((a, y_top + r), r, pi, 1.5 * pi), Segment((a, y_top), (b, y_top)),
                  Arc((b, y_top + r), r, 1.5 * pi, 2 * pi)), normal_side="right", d_capture=d_capture)
    lower = Tool((Arc((a, y_bottom - r), r, pi, 0.5 * pi), Segment((a, y_bottom), (b, y_bottom)),
                  Arc((b, y_bottom - r), r, 0.5 * pi, 0.0)), normal_side="left", d_capture=d_capture)
    return upper, lower


def tool_resultants(model, state) -> tuple:
    """Per tool, the (2,) resultant of its contact forces on the sheet (N/mm)."""
    return tuple(jnp.sum(f, axis=0) for f in split_pairs(model.tools, pair_forces(state)))


def contact_columns(state) -> dict:
    """max_penetration (mm), n_active (closed pairs), n_slip (pairs at the Coulomb limit)."""
    c = state.contact
    return {"max_penetration": max_penetration(c.status, c.gap),
            "n_active": jnp.sum(c.status > 0), "n_slip": jnp.sum(c.status == SLIP)}


def end_reaction(model, state, nodes) -> jnp.ndarray:
    """(2,) sum of the reactions f_int - f_c over ``nodes`` (N/mm): the force the support exerts on
    the sheet there."""
    return jnp.sum(reactions(model, state)[np.asarray(nodes)], axis=0)


def stiff_penalty(config) -> float:
    """The penalty (N/mm per mm) above which the scene's penalty law starts a failed attempt again from
    exact contact (:class:`jaxfric.contact.formulations.StiffPenalty`): ``STIFF_PENALTY_RATIO`` times the
    scene's spec penalty (its config's default eps_n), times (t / t_spec)^3 for a sheet thinner than the
    spec's. Why the cube: what a penalty is stiff against is the sheet's bending, E t^3 / 12 per unit
    width; a thin sheet under the spec's penalty is the spec's sheet under a penalty (t_spec / t)^3 times
    stiffer (the blankholder at t = 0.12 mm, 1e5 N/mm: as stiff as 5.8e7 on the spec's 1 mm sheet, where
    a pair's lift-off front advances one node per Newton iteration; tests/test_extreme.py)."""
    spec = type(config)()   # the spec's values: every config field has its spec default
    name = "t" if hasattr(config, "t") else "h"   # the flat die's half thickness
    thinner = min(1.0, float(getattr(config, name)) / float(getattr(spec, name))) ** 3
    return STIFF_PENALTY_RATIO * float(spec.eps_n) * thinner


def ramp_end(model, phase: int, bc: int) -> jnp.ndarray:
    """The x-displacement that Dirichlet condition ``bc`` of phase ``phase`` (a :class:`Ramp` from 0)
    reaches at the phase's end: a scene's stroke, read from the model (data: a longer stroke is the same
    program) rather than held by its static observer."""
    return model.phases[phase].bcs[bc].motion.end[0]


def phase_progress(state, phase: int) -> jnp.ndarray:
    """Progress tau in [0, 1] of phase ``phase`` (0-based): 0 before it, 1 after it. Pseudo-time is
    linear in the phase's control variable, so control = start + tau (end - start)."""
    return jnp.clip(state.time - float(phase), 0.0, 1.0)


class ContactSnapshot(eqx.Module):
    """Static ``snapshot(model, state)``: the per-instant arrays of ``contact.npz`` (outputs spec 4).

    Returns x (n_nodes, 2) current coordinates (mm), eqps (n_el,) element mean over the Gauss points,
    per pair rn, rt (N/mm), gap (mm; 1e30 where the pair has no projection), normal (m, 2) ((0, 0)
    without projection), status (int8), mu (the tool's coefficient in the state's phase), and
    tool_offset (n_tools, 2) = q_k e_q,k (mm). Everything comes from the model and the state, so one
    instance serves every scene.
    """

    def __call__(self, model, state) -> dict:
        c = state.contact
        projects = c.gap < 0.5 * GAP_OPEN
        # Each pair's coefficient: a slipping pair's is |R_T| / R_N (a friction law's value at its force
        # and speed), the others' that at rest (Coulomb's: the tool's mu).
        at_rest = pair_friction(model.tools, [t.mu[state.phase] for t in model.tools], model.mesh.nodes, c.rn)
        slipping = (c.status == SLIP) & (c.rn > 0.0)
        mu = at_rest if not has_friction_law(model.tools) else \
            jnp.where(slipping, jnp.abs(c.rt) / jnp.where(slipping, c.rn, 1.0), at_rest)
        drive = jnp.stack([t.drive for t in model.tools])
        return {
            "x": model.mesh.nodes + state.u,
            "eqps": jnp.mean(state.material.eqps, axis=1),
            "rn": c.rn,
            "rt": c.rt,
            "gap": jnp.where(projects, c.gap, 1e30),
            "normal": jnp.where(projects[:, None], c.normal, 0.0),
            "status": c.status.astype(jnp.int8),
            "mu": mu,
            "tool_offset": c.q[:, None] * drive,
        }


# ---- JSON description ----------------------------------------------------------------------------

def step_control(phases, max_steps: int | None = None, stabilize: float = STABILIZE,
                 step_error: float = 0.0, stall_steps: int = STALL_STEPS) -> StepControl:
    """The spec's step controller (section 1.9: StepControl defaults) with a history buffer of
    ``max_steps`` rows, by default 10x the nominal step count + 200, the damper ``stabilize``
    (:class:`StepControl`) where a step fails at the smallest increment, and with ``step_error`` > 0 the
    increments chosen by the step error estimate, and a stop after ``stall_steps`` crawling steps.

    Why 10x: the controller halves the increment on a failure and grows it back (x1.5) only after two
    consecutive steps of at most 6 Newton iterations, so a phase whose steps regularly need 7 or more
    iterations stays at the cut increment. The Nine clamp (300 x 3, penalty) takes about 9x its nominal
    110 steps this way. The buffer holds a few dozen scalars per row (~2 MB for the longest scene), so
    10x costs little, while a full buffer stops the run (Result.MAX_STEPS). The spec's controller has no
    such limit (it stops only below nominal / 2**10): a run that needs more rows (the Nine with a
    penalty of 1e6, about 20x its nominal steps) sets ``max_steps``.
    """
    return StepControl(max_steps=max_steps or 10 * schedule(phases).n_nominal_steps + 200, stabilize=stabilize,
                       step_error=step_error, stall_steps=stall_steps)


def schedule_entry(phase: Phase, control: str, variable: str, unit: str, start: float | None,
                   end: float) -> dict:
    """JSON description of one phase: its control variable, range [start, end] and nominal increments
    (``start`` None: known only at run time, e.g. a force ramp from the reaction reached so far)."""
    pieces, tau0 = [], 0.0
    for tau_end, n in phase.increments:
        if start is None:
            pieces.append({"from_tau": tau0, "to_tau": tau_end, "n_steps": int(n)})
        else:
            lo, hi = start + tau0 * (end - start), start + tau_end * (end - start)
            pieces.append({"from": lo, "to": hi, "n_steps": int(n), "increment": (hi - lo) / n})
        tau0 = tau_end
    return {"name": phase.name, "control": control, "variable": variable, "unit": unit,
            "range": [None if start is None else float(start), float(end)], "increments": pieces}


def friction_table(tool_names, phase_names, mu) -> dict:
    """{tool: {phase: mu}} from a (n_tools, n_phases) table."""
    return {t: {p: float(mu[k][j]) for j, p in enumerate(phase_names)} for k, t in enumerate(tool_names)}


def friction_law(config):
    """The frictional tools' law (:mod:`jaxfric.contact.friction`) about each tool's mu: None for
    Coulomb, the :class:`Polynomial` of ``mu_p`` .. ``mu_vv``, or the :class:`VelocityDecay` of ``mu_d``
    (None: mu) and ``decay`` (None: 0), each reading speeds filtered with ``speed_period``."""
    if config.friction_law == "coulomb":
        return None
    if config.friction_law == "polynomial":
        return Polynomial(*(getattr(config, name) for name in POLYNOMIAL_TERMS), period=config.speed_period)
    mu_d = config.mu if config.mu_d is None else config.mu_d
    return VelocityDecay(mu_d, 0.0 if config.decay is None else config.decay, period=config.speed_period)


def phase_seconds(config, phases, stroke: float) -> tuple | None:
    """The phases' durations (``StripModel.phase_seconds``): the phase named "draw" lasts ``stroke`` (mm)
    over ``draw_speed``, the others none; None without a friction law (nothing reads them)."""
    if config.friction_law == "coulomb":
        return None
    return tuple(float(stroke) / float(config.draw_speed) if p.name == "draw" else 0.0 for p in phases)


def material(config):
    """The scene's material law: spec 1.2's isotropic J2Material, or with back stresses (``C_kin``,
    ``gamma_kin``) or Voce terms (``Q_voce``, ``b_voce``) the KinematicJ2Material whose monotonic curve is
    the power law plus the Voce terms, the back stresses taking their saturation out of its radius. A
    ValueError names the field of a radius that would not stay positive."""
    iso = (config.E, config.nu, config.sigma_y, config.A, config.n)
    if not (config.C_kin or config.Q_voce):
        return J2Material(*iso, integration=config.plastic_integration)
    if config.plastic_integration != "radial":
        raise _bad("plastic_integration", config.plastic_integration,
                   "the back stresses and Voce terms (C_kin, Q_voce) integrate by the radial return only")
    try:
        return KinematicJ2Material(*iso, C=config.C_kin, gamma=config.gamma_kin, Q=config.Q_voce, b=config.b_voce,
                                   keep_monotonic=True)
    except ValueError as error:
        raise _bad("C_kin", config.C_kin, str(error).removeprefix("KinematicJ2Material: ")) from None


def material_dict(config) -> dict:
    out: dict = {"E": float(config.E), "nu": float(config.nu), "sigma_y": float(config.sigma_y),
                 "A": float(config.A), "n": float(config.n)}
    for name in ("C_kin", "gamma_kin", "Q_voce", "b_voce"):
        if getattr(config, name):
            out[name] = [float(v) for v in getattr(config, name)]
    return out


def config_dict(config) -> dict:
    """Every config field, JSON-ready (tuples become lists)."""
    out = {}
    for f in dataclasses.fields(config):
        v = getattr(config, f.name)
        out[f.name] = list(v) if isinstance(v, tuple) else v
    return out
