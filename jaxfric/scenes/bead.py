"""Scene ``bead``: friction on bead (draw-bend) test (benchmarks spec section 3).

A strip x in [x_left, x_right], y in [0, t] is held on the left between two flat clamp dies (the upper
one force-driven down at F_clamp, the lower one fixed), wound around a fixed roller (centre (0, -R_r),
strip bottom tangent to it at x = 0) by a jaw that turns clockwise about the roller centre by theta
(phase ``wind``), then pulled by s_draw along d(theta) = (cos theta, -sin theta) (phase ``draw``).
The jaw is a rigid map of all nodes with initial X >= x_jaw:

    x = O + Q(theta) (X - O) + s d(theta),   Q(theta) = [[cos, sin], [-sin, cos]]  (clockwise)

Tools, in order: ``die_up`` (force-driven, e_q = (0, -1), candidates: top surface), ``die_lo`` (fixed,
bottom surface), ``roller`` (fixed full circle, bottom surface), each less the jaw's nodes, which the jaw
holds in both directions in every phase (``_common.movable``). The clamping tool is ``die_up``.

Values tagged [chosen] in the spec (section 9), all config fields here:
- ``t`` = 1.5 mm; strip x in [-100, 100];
- roller ``R_r`` = 5 mm at (0, -R_r), fixed, not rotating; winding pivot at the roller centre;
- clamp dies over x in [``x_clamp_left``, ``x_clamp_right``] = [-90, -40] with end radius ``r_e`` = 2 mm;
- jaw = nodes with X >= ``x_jaw`` = 80 mm; draw direction d(theta);
- eps_n = 1e5 N/mm with eps_t = mu eps_n (``eps_t`` None; mu = the largest coefficient of the variant,
  0.17 in all six);
- increments: clamp in ``n_clamp`` = 10 steps, ``dtheta`` = 0.5 deg, ``ds`` = 0.05 mm;
- ``steady_window`` = (4, 8) mm;
- ``element`` = ``ans`` (:mod:`jaxfric.fem.element`): th090_mu017's steady force moves 0.03 % from 725 x 4
  to 1450 x 4 (300.74 to 300.66 N/mm, ``lcp_ssn``), with F-bar 0.29 % (301.93 to 301.07);
- exact contact by lcp_lemke: ``band`` = 512 of the 1452 candidate nodes (at 725 x 4) enter the
  complementarity problem, the nearest to a tool. About 350 pairs are closed at theta = 45 deg (the
  two clamp faces, 181 nodes each over 50 mm, plus the roller), an estimated 45 more on the roller
  at 135 deg. With all candidates the problem has 4356 unknowns and lcp_lemke made no progress past
  step 9 of the clamp in 7 minutes; with 512 it has 1536.
Not in the spec: the seam of the roller (where its arc length jumps) is at 202.5 deg, opposite the middle
of the widest contact arc (from 90 deg down to -45 deg for theta = 135 deg).
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..contact.formulations import formulation
from ..contact.rigid import Force, Move, RigidTool
from ..contact.tools import Tool
from ..fem.loading import DirichletBC, Phase, RigidMotion
from ..fem.mesh import strip_mesh
from ..loadpath.model import StripModel
from . import _common as cm
from .base import Scene

__all__ = ["NAME", "BeadConfig", "VARIANTS", "DEFAULT_VARIANT", "BeadObserve", "build", "jaw_nodes"]

NAME = "bead"
DEFAULT_VARIANT = "th090_mu017"
# Config fields of the nominal increments (a float: an increment; an int: a phase's step count).
STEP_FIELDS = ("n_clamp", "dtheta", "ds")
STROKE_FIELD = "s_draw"  # the drawing stroke: steady_window lies in [0, s_draw]
PHASES = ("clamp", "wind", "draw")
TOOLS = ("die_up", "die_lo", "roller")
# Named instants (benchmarks spec, scene Outputs), in order, each with its rule
# (:func:`jaxfric.io.instants.select_instants`).
INSTANT_RULES = {"clamped": ("end", "clamp"), "folded": ("end", "wind"), "drawing": ("closest", "draw", 4.0),
                 "final": ("final",)}
INSTANTS = tuple(INSTANT_RULES)
ROLLER_SEAM = math.radians(202.5)


@dataclasses.dataclass(frozen=True)
class BeadConfig(cm.FrictionLawFields, cm.PreselectField, cm.PlasticIntegrationField, cm.SolverFields):
    """Every value of the bead scene (spec section 3); defaults are the spec's (``th090_mu017``)."""

    x_left: float = cm.spec_field(-100.0, "mm", "left (clamped, free) end of the strip [chosen]")
    x_right: float = cm.spec_field(100.0, "mm", "right (gripped) end of the strip [chosen]")
    t: float = cm.spec_field(1.5, "mm", "strip thickness [chosen]")
    nx: int = cm.spec_field(725, "-", "elements along the strip [paper]")
    ny: int = cm.spec_field(4, "-", "elements through the thickness [paper]")
    R_r: float = cm.spec_field(5.0, "mm", "roller radius; centre (0, -R_r) [chosen]")
    x_clamp_left: float = cm.spec_field(-90.0, "mm", "left end of the clamp dies' flat [chosen]")
    x_clamp_right: float = cm.spec_field(-40.0, "mm", "right end of the clamp dies' flat [chosen]")
    r_e: float = cm.spec_field(2.0, "mm", "end radius of the clamp dies [chosen]")
    x_jaw: float = cm.spec_field(80.0, "mm", "the jaw grips all nodes with initial X >= x_jaw [chosen]")
    theta: float = cm.spec_field(90.0, "deg", "wrap angle: clockwise jaw rotation (variant) [paper]")
    s_draw: float = cm.spec_field(8.0, "mm", "jaw travel along d(theta) during draw [paper]")
    F_clamp: float = cm.spec_field(600.0, "N/mm", "clamp force on die_up [paper]")
    mu_clamp: float = cm.spec_field(0.17, "-", "friction of both clamp dies [paper]")
    mu_roller: float = cm.spec_field(0.17, "-", "friction of the roller (variant: 0 or 0.17) [paper]")
    E: float = cm.spec_field(200000.0, "MPa", "Young's modulus (Table 2) [paper]")
    nu: float = cm.spec_field(0.3, "-", "Poisson's ratio [paper]")
    sigma_y: float = cm.spec_field(169.0, "MPa", "initial yield stress [paper]")
    A: float = cm.spec_field(127.42425, "-", "hardening coefficient in sigma_y (1 + A eqps)^n [paper]")
    n: float = cm.spec_field(0.225, "-", "hardening exponent [paper]")
    C_kin: tuple = cm.spec_field((), "MPa", cm.C_KIN_DOC)
    gamma_kin: tuple = cm.spec_field((), "-", cm.GAMMA_KIN_DOC)
    Q_voce: tuple = cm.spec_field((), "MPa", cm.Q_VOCE_DOC)
    b_voce: tuple = cm.spec_field((), "-", cm.B_VOCE_DOC)
    eps_n: float = cm.spec_field(1e5, "N/mm/mm", "normal penalty [chosen]")
    eps_t: float | None = cm.spec_field(None, "N/mm/mm", "tangential penalty; None: mu eps_n [chosen]")
    target_gap: float = cm.spec_field(1e-5, "mm", "auglag target gap [chosen]")
    max_augmentations: int = cm.spec_field(20, "-", cm.MAX_AUGMENTATIONS_DOC)
    max_steps: int | None = cm.spec_field(None, "-", cm.MAX_STEPS_DOC)
    stabilize: float = cm.spec_field(cm.STABILIZE, "-", cm.STABILIZE_DOC)
    stall_steps: int = cm.spec_field(cm.STALL_STEPS, "-", cm.STALL_STEPS_DOC)
    step_error: float = cm.spec_field(0.0, "-", cm.STEP_ERROR_DOC)
    smoothing: float = cm.spec_field(0.0, "N/mm", cm.SMOOTHING_DOC)
    d_capture: float = cm.spec_field(2.0, "mm", "capture depth [chosen]")
    band: int | None = cm.spec_field(512, "-", cm.BAND_DOC)
    element: str = cm.spec_field("ans", "-", cm.ELEMENT_DOC)
    element_order: int = cm.spec_field(1, "-", cm.ELEMENT_ORDER_DOC)
    thickness_points: int = cm.spec_field(2, "-", cm.THICKNESS_POINTS_DOC)
    enhanced_update: str = cm.spec_field("iterate", "-", cm.ENHANCED_UPDATE_DOC)
    n_clamp: int = cm.spec_field(10, "-", "steps of the clamp force ramp [chosen]")
    dtheta: float = cm.spec_field(0.5, "deg", "nominal increment of the jaw angle [chosen]")
    ds: float = cm.spec_field(0.05, "mm", "nominal increment of the jaw travel [chosen]")
    steady_window: tuple = cm.spec_field((4.0, 8.0), "mm", "steady window in s [chosen]")


VARIANTS = {f"th{th:03d}_mu{round(100 * mu):03d}": {"theta": float(th), "mu_roller": mu}
            for mu in (0.0, 0.17) for th in (45, 90, 135)}


def jaw_nodes(mesh, x_jaw: float) -> np.ndarray:
    """Nodes with initial X >= x_jaw (to 1e-9 mm), in node order."""
    X = np.asarray(mesh.nodes[:, 0])
    return np.flatnonzero(X >= x_jaw - 1e-9)


class BeadObserve(eqx.Module):
    """Static ``observe(model, state)`` of the bead scene (spec section 3, Outputs).

    theta(t) = theta_v tau_wind, s(t) = s_draw tau_draw; drawing_force = (sum of the jaw reactions) .
    d(theta); clamping_force = e_q . resultant of die_up (e_q = (0, -1)); tool_position = q of die_up;
    drawing_displacement = s.
    """

    jaw: tuple = eqx.field(static=True)       # jaw nodes
    tail: int = eqx.field(static=True)        # bottom-left node
    theta: float = eqx.field(static=True)     # variant wrap angle (rad)
    s_draw: float = eqx.field(static=True)    # mm

    def __call__(self, model, state) -> dict:
        c = state.contact
        theta = self.theta * cm.phase_progress(state, 1)
        s = self.s_draw * cm.phase_progress(state, 2)
        d = jnp.stack([jnp.cos(theta), -jnp.sin(theta)])
        jaw = cm.end_reaction(model, state, self.jaw)
        pairs = cm.pair_forces(state)
        n_up, n_lo = len(model.tools[0].candidates), len(model.tools[1].candidates)
        tangent = jnp.stack([-c.normal[:, 1], c.normal[:, 0]], axis=1)
        clamp_ft = c.rt[: n_up + n_lo] @ tangent[: n_up + n_lo, 0]
        roller = jnp.sum(pairs[n_up + n_lo:], axis=0)
        return {
            "drawing_displacement": s,
            "drawing_force": jaw @ d,
            "clamping_force": c.force[0],
            "tool_position": c.q[0],
            **cm.contact_columns(state),
            "theta_deg": jnp.degrees(theta),
            "jaw_fx": jaw[0], "jaw_fy": jaw[1],
            "roller_fx": roller[0], "roller_fy": roller[1],
            "clamp_ft": jnp.abs(clamp_ft),
            "tail_x": model.mesh.nodes[self.tail, 0] + state.u[self.tail, 0],
        }


def _check(config: BeadConfig) -> None:
    cm.check_config(config, positive=("t", "R_r", "r_e", "F_clamp", "s_draw", "dtheta", "ds"),
                    nonnegative=("stabilize", "step_error", "mu_clamp", "mu_roller", "theta"),
                    integers=("nx", "ny", "band", "n_clamp", "stall_steps"),
                    lengths=("x_left", "x_right", "t", "R_r", "x_clamp_left", "x_clamp_right", "r_e", "x_jaw"))
    if not config.x_right > config.x_left:
        raise ValueError(f"config field 'x_right' = {config.x_right!r} must exceed x_left = {config.x_left!r}")
    if not config.x_clamp_left < config.x_clamp_right:
        raise ValueError(f"config field 'x_clamp_right' = {config.x_clamp_right!r} must exceed "
                         f"x_clamp_left = {config.x_clamp_left!r}")
    if not config.theta < 180.0:
        raise ValueError(f"config field 'theta' = {config.theta!r} must be below 180 deg")
    if not config.x_left < config.x_jaw < config.x_right:
        raise ValueError(f"config field 'x_jaw' = {config.x_jaw!r} must lie inside the strip "
                         f"({config.x_left}, {config.x_right})")


def build(config: BeadConfig = BeadConfig(), algorithm: str = "penalty", variant: str = DEFAULT_VARIANT) -> Scene:
    """The bead scene for ``config`` (the variant's overrides already applied) and ``algorithm``."""
    cm.check_variant(NAME, VARIANTS, variant)
    cm.check_algorithm(algorithm)
    _check(config)
    mesh = strip_mesh(config.x_left, config.x_right, 0.0, config.t, config.nx, config.ny, order=config.element_order)
    jaw = jaw_nodes(mesh, config.x_jaw)
    if jaw.size == 0:
        raise ValueError(f"config field 'x_jaw' = {config.x_jaw!r} selects no node")
    pivot = (0.0, -config.R_r)
    theta = math.radians(config.theta)
    d = (math.cos(theta), -math.sin(theta))
    # RigidMotion turns counter-clockwise: the clockwise jaw angle theta is -theta there.
    held = DirichletBC(jaw, (0, 1), RigidMotion(pivot))
    wind = DirichletBC(jaw, (0, 1), RigidMotion(pivot, 0.0, -theta))
    pull = DirichletBC(jaw, (0, 1), RigidMotion(pivot, -theta, -theta, (0.0, 0.0),
                                                 (config.s_draw * d[0], config.s_draw * d[1])))
    n_wind = cm.n_steps("dtheta", config.theta, config.dtheta)
    n_draw = cm.n_steps("ds", config.s_draw, config.ds)
    phases = (Phase("clamp", [held], config.n_clamp), Phase("wind", [wind], n_wind),
              Phase("draw", [pull], n_draw))

    upper, lower = cm.flat_faces(config.x_clamp_left, config.x_clamp_right, config.t, 0.0, config.r_e,
                                 config.d_capture)
    roller = Tool.circle(pivot, config.R_r, d_capture=config.d_capture, seam=ROLLER_SEAM)
    P = config.F_clamp
    fixed = (Move(0.0, 0.0),) * 3
    mu_c = config.mu_clamp if config.mu_clamp > 0 else 0.0
    mu_r = config.mu_roller if config.mu_roller > 0 else 0.0
    top, bottom = cm.movable(mesh, mesh.top, phases), cm.movable(mesh, mesh.bottom, phases)  # not the jaw's nodes
    law = cm.friction_law(config)
    tools = (RigidTool("die_up", upper, (0.0, -1.0), top,
                       (Force(P, start=0.0), Force(P, start=P), Force(P, start=P)), mu_c, frictional=mu_c > 0,
                       friction=law if mu_c > 0 else None),
             RigidTool("die_lo", lower, (0.0, 1.0), bottom, fixed, mu_c, frictional=mu_c > 0,
                       friction=law if mu_c > 0 else None),
             RigidTool("roller", roller, (0.0, 1.0), bottom, fixed, mu_r, frictional=mu_r > 0,
                       friction=law if mu_r > 0 else None))

    eps_t = cm.resolve_eps_t(config, max(config.mu_clamp, config.mu_roller))
    law = formulation(algorithm, config.eps_n, eps_t, config.target_gap, config.band, config.smoothing,
                      config.max_augmentations, stiff_above=cm.stiff_penalty(config),
                      search=config.lemke_search, exact_start=config.exact_start)
    material = cm.material(config)
    model = StripModel(mesh, material, phases, tools=cm.preselected(tools, mesh, config.preselect),
                       contact=law, formulation=config.element,
                       thickness_points=config.thickness_points,
                       enhanced_update=config.enhanced_update,
                       phase_seconds=cm.phase_seconds(config, phases, config.s_draw))
    observe = BeadObserve(jaw=tuple(int(a) for a in jaw), tail=int(mesh.node_index(0, 0)), theta=theta,
                          s_draw=float(config.s_draw))

    mu_table = [(config.mu_clamp,) * 3, (config.mu_clamp,) * 3, (config.mu_roller,) * 3]
    parameters = {
        "variant": variant,
        "config": cm.config_dict(config),
        "geometry": {"x_left": config.x_left, "x_right": config.x_right, "t": config.t,
                     "roller": {"centre": list(pivot), "radius": config.R_r},
                     "clamp_dies": {"x": [config.x_clamp_left, config.x_clamp_right], "r_e": config.r_e},
                     "x_jaw": config.x_jaw, "n_jaw_nodes": int(jaw.size), "pivot": list(pivot),
                     "theta_deg": config.theta, "draw_direction": list(d), "s_draw": config.s_draw},
        "material": cm.material_dict(config),
        "friction": cm.friction_table(TOOLS, PHASES, mu_table),
        "contact": {"algorithm": algorithm, "eps_n": config.eps_n, "eps_t": eps_t,
                    "target_gap": config.target_gap if algorithm == "auglag" else None,
                    "max_augmentations": config.max_augmentations if algorithm == "auglag" else None,
                    "d_capture": config.d_capture},
        "mesh": {"nx": config.nx, "ny": config.ny},
        "schedule": [cm.schedule_entry(phases[0], "force on die_up", "P", "N/mm", 0.0, P),
                     cm.schedule_entry(phases[1], "jaw angle (clockwise)", "theta", "deg", 0.0, config.theta),
                     cm.schedule_entry(phases[2], "jaw travel along d(theta)", "s", "mm", 0.0, config.s_draw)],
    }
    return Scene(
        name=NAME, variant=variant, algorithm=algorithm, config=config, model=model, observe=observe,
        snapshot=cm.ContactSnapshot(),
        control=cm.step_control(phases, config.max_steps, config.stabilize, config.step_error,
                                     config.stall_steps),
        phase_names=PHASES, tool_names=TOOLS, clamping_tool=0, instants=INSTANTS,
        steady_window=tuple(float(v) for v in config.steady_window),
        roi=(-95.0, 30.0, -45.0, 15.0), y_scale=1.0, parameters=parameters)
