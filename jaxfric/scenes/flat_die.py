"""Scene ``flat_die``: flat die friction test (benchmarks spec section 2).

A half sheet x in [0, L], y in [0, h] (symmetry plane y = 0: v = 0 on BC) is clamped by a rigid flat
die (a line y = h - d above it, force-driven to F_clamp, frictionless) in phase ``clamp``, then its
right edge DC is pulled by U_draw in phase ``draw`` with friction mu, until the sheet slides globally.

Tool: ``die`` (e_q = (0, -1)); candidates: the top-surface nodes (edge AD, A and D included).
Variants: ``const_force`` (the die stays force-driven at F_clamp during ``draw``) and ``const_position``
(the die is frozen where ``clamp`` left it: ``draw_control`` = "position").

Values tagged [chosen] in the spec (section 9), all config fields here:
- ``L`` = 48 mm; die over x in [-``die_overhang``, L + ``die_overhang``] with ``die_overhang`` = 2 mm;
- frictionless ``clamp`` (mu = 0 in that phase, so the tangential history starts at 0 in ``draw``);
- u = 0 on DC during ``clamp``; clamp in ``n_clamp`` = 10 steps;
- ``U_draw`` = 0.03 mm, increments ``dU_fine`` = 2.5e-5 mm up to ``U_fine`` = 0.0025 mm, then ``dU`` = 1e-4
  mm (100 + 275 steps);
- ``steady_window`` = (0.02, 0.03) mm.
eps_t = 1.5e8 N/mm [paper] is also mu eps_n (``eps_t`` None: the rule of spec 1.5).
Figure region [chosen here, the spec gives x only]: x in [-1, L + 1], y in [-0.1, h + 0.1], y x 20.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax.numpy as jnp

from ..contact.formulations import formulation
from ..contact.rigid import Force, Move, RigidTool
from ..contact.tools import Tool
from ..fem.loading import DirichletBC, Phase, Ramp
from ..fem.mesh import strip_mesh
from ..loadpath.model import StripModel
from . import _common as cm
from .base import Scene

__all__ = ["NAME", "FlatDieConfig", "VARIANTS", "DEFAULT_VARIANT", "FlatDieObserve", "build"]

NAME = "flat_die"
DEFAULT_VARIANT = "const_force"
# Config fields of the nominal increments (a float: an increment; an int: a phase's step count).
STEP_FIELDS = ("dU_fine", "dU", "n_clamp")
STROKE_FIELD = "U_draw"  # the drawing stroke: steady_window lies in [0, U_draw]
PHASES = ("clamp", "draw")
TOOLS = ("die",)
# Named instants (benchmarks spec, scene Outputs), in order, each with its rule
# (:func:`jaxfric.io.instants.select_instants`).
INSTANT_RULES = {"clamped": ("end", "clamp"), "intermediate": ("first_half_slip",),
                 "sliding": ("first_all_slip",), "final": ("final",)}
INSTANTS = tuple(INSTANT_RULES)


@dataclasses.dataclass(frozen=True)
class FlatDieConfig(cm.FrictionLawFields, cm.PreselectField, cm.PlasticIntegrationField, cm.SolverFields):
    """Every value of the flat die scene (spec section 2); defaults are the spec's (``const_force``)."""

    L: float = cm.spec_field(48.0, "mm", "sheet length, x in [0, L] [chosen]")
    h: float = cm.spec_field(0.395, "mm", "half thickness, y in [0, h] [paper]")
    nx: int = cm.spec_field(240, "-", "elements along the sheet [paper]")
    ny: int = cm.spec_field(2, "-", "elements through the half thickness [paper]")
    die_overhang: float = cm.spec_field(2.0, "mm", "die line from x = -overhang to L + overhang [chosen]")
    mu: float = cm.spec_field(0.15, "-", "die/sheet friction during draw (0 during clamp) [paper]")
    E: float = cm.spec_field(69004.0, "MPa", "Young's modulus (Table 1) [paper]")
    nu: float = cm.spec_field(0.3, "-", "Poisson's ratio [paper]")
    sigma_y: float = cm.spec_field(80.55923, "MPa", "initial yield stress [paper]")
    A: float = cm.spec_field(10000.0, "-", "hardening coefficient in sigma_y (1 + A eqps)^n [paper]")
    n: float = cm.spec_field(0.216, "-", "hardening exponent [paper]")
    C_kin: tuple = cm.spec_field((), "MPa", cm.C_KIN_DOC)
    gamma_kin: tuple = cm.spec_field((), "-", cm.GAMMA_KIN_DOC)
    Q_voce: tuple = cm.spec_field((), "MPa", cm.Q_VOCE_DOC)
    b_voce: tuple = cm.spec_field((), "-", cm.B_VOCE_DOC)
    eps_n: float = cm.spec_field(1e9, "N/mm/mm", "normal penalty [paper]")
    eps_t: float | None = cm.spec_field(None, "N/mm/mm", "tangential penalty; None: mu eps_n = 1.5e8 [paper]")
    target_gap: float = cm.spec_field(1e-5, "mm", "auglag target gap [chosen]")
    max_augmentations: int = cm.spec_field(20, "-", cm.MAX_AUGMENTATIONS_DOC)
    max_steps: int | None = cm.spec_field(None, "-", cm.MAX_STEPS_DOC)
    stabilize: float = cm.spec_field(cm.STABILIZE, "-", cm.STABILIZE_DOC)
    stall_steps: int = cm.spec_field(cm.STALL_STEPS, "-", cm.STALL_STEPS_DOC)
    step_error: float = cm.spec_field(0.0, "-", cm.STEP_ERROR_DOC)
    smoothing: float = cm.spec_field(0.0, "N/mm", cm.SMOOTHING_DOC)
    d_capture: float = cm.spec_field(2.0, "mm", "capture depth [chosen]")
    band: int | None = cm.spec_field(None, "-", cm.BAND_DOC)
    element: str = cm.spec_field("fbar", "-", cm.ELEMENT_DOC)
    element_order: int = cm.spec_field(1, "-", cm.ELEMENT_ORDER_DOC)
    thickness_points: int = cm.spec_field(2, "-", cm.THICKNESS_POINTS_DOC)
    enhanced_update: str = cm.spec_field("iterate", "-", cm.ENHANCED_UPDATE_DOC)
    F_clamp: float = cm.spec_field(50.0, "N/mm", "clamping force on the half model [paper]")
    draw_control: str = cm.spec_field("force", "-", "die during draw: 'force' (const_force) or 'position' "
                                                    "(const_position) [paper]")
    U_draw: float = cm.spec_field(0.03, "mm", "pull of DC during draw [chosen]")
    U_fine: float = cm.spec_field(0.0025, "mm", "end of the fine increments [chosen]")
    dU_fine: float = cm.spec_field(2.5e-5, "mm", "nominal increment up to U_fine [chosen]")
    dU: float = cm.spec_field(1e-4, "mm", "nominal increment after U_fine [chosen]")
    n_clamp: int = cm.spec_field(10, "-", "steps of the clamp force ramp [chosen]")
    steady_window: tuple = cm.spec_field((0.02, 0.03), "mm", "steady window in U [chosen]")


VARIANTS = {"const_force": {"draw_control": "force"}, "const_position": {"draw_control": "position"}}


class FlatDieObserve(eqx.Module):
    """Static ``observe(model, state)`` of the flat die (spec section 2, Outputs).

    drawing_force = sum of the DC reactions along +x; clamping_force = sum of R_N over the die pairs
    (= e_q . resultant, the die being flat); tool_position = d; sum_ft = |sum R_T|; mu_sum_fn = mu sum R_N
    with the phase's mu; n_candidates = number of die pairs.
    """

    right: tuple = eqx.field(static=True)    # DC nodes
    pull: tuple = eqx.field(static=True)     # (phase, condition) of the pull's Ramp: its end is U_draw

    def __call__(self, model, state) -> dict:
        c = state.contact
        sum_fn = jnp.sum(c.rn)
        return {
            "drawing_displacement": cm.ramp_end(model, *self.pull) * cm.phase_progress(state, 1),
            "drawing_force": cm.end_reaction(model, state, self.right)[0],
            "clamping_force": sum_fn,
            "tool_position": c.q[0],
            **cm.contact_columns(state),
            "sum_ft": jnp.abs(jnp.sum(c.rt)),
            "mu_sum_fn": model.tools[0].mu[state.phase] * sum_fn,
            "n_candidates": jnp.array(len(model.tools[0].candidates)),
        }


def _check(config: FlatDieConfig) -> None:
    cm.check_config(config, positive=("L", "h", "die_overhang", "U_draw", "U_fine", "dU_fine", "dU"),
                    nonnegative=("stabilize", "step_error", "mu", "F_clamp"),
                    integers=("nx", "ny", "band", "n_clamp", "stall_steps"),
                    choices={"draw_control": ("force", "position")}, lengths=("L", "h", "die_overhang"))


def _draw_increments(config: FlatDieConfig) -> tuple:
    """((tau_end, n), ...) of the draw phase: fine steps up to U_fine, then dU steps."""
    if config.U_fine >= config.U_draw:
        return ((1.0, cm.n_steps("dU_fine", config.U_draw, config.dU_fine)),)
    return ((config.U_fine / config.U_draw, cm.n_steps("dU_fine", config.U_fine, config.dU_fine)),
            (1.0, cm.n_steps("dU", config.U_draw - config.U_fine, config.dU)))


def build(config: FlatDieConfig = FlatDieConfig(), algorithm: str = "penalty",
          variant: str = DEFAULT_VARIANT) -> Scene:
    """The flat die scene for ``config`` (the variant's overrides already applied) and ``algorithm``."""
    cm.check_variant(NAME, VARIANTS, variant)
    cm.check_algorithm(algorithm)
    _check(config)
    L, h = config.L, config.h
    mesh = strip_mesh(0.0, L, 0.0, h, config.nx, config.ny, order=config.element_order)
    symmetry = DirichletBC(mesh.bottom, (1,))                     # BC: v = 0 (C included)
    hold = DirichletBC(mesh.right, (0,))                          # DC: u = 0 during clamp
    pull = DirichletBC(mesh.right, (0,), Ramp((0.0, 0.0), (config.U_draw, 0.0)))
    draw_increments = _draw_increments(config)
    phases = (Phase("clamp", [symmetry, hold], config.n_clamp),
              Phase("draw", [symmetry, pull], increments=draw_increments))

    die = Tool.line((-config.die_overhang, h), (L + config.die_overhang, h), normal_side="right",
                    d_capture=config.d_capture)
    draw = Force(config.F_clamp, start=config.F_clamp) if config.draw_control == "force" else Move(0.0, 0.0)
    mu = (0.0, config.mu) if config.mu > 0 else 0.0
    tool = RigidTool("die", die, (0.0, -1.0), mesh.top, (Force(config.F_clamp, start=0.0), draw), mu,
                     frictional=config.mu > 0, friction=cm.friction_law(config) if config.mu > 0 else None)

    eps_t = cm.resolve_eps_t(config, config.mu)
    law = formulation(algorithm, config.eps_n, eps_t, config.target_gap, config.band, config.smoothing,
                      config.max_augmentations, stiff_above=cm.stiff_penalty(config),
                      search=config.lemke_search, exact_start=config.exact_start)
    material = cm.material(config)
    model = StripModel(mesh, material, phases, tools=cm.preselected((tool,), mesh, config.preselect),
                       contact=law, formulation=config.element,
                       thickness_points=config.thickness_points,
                       enhanced_update=config.enhanced_update,
                       phase_seconds=cm.phase_seconds(config, phases, config.U_draw))
    observe = FlatDieObserve(right=tuple(int(a) for a in mesh.right), pull=(1, 1))

    parameters = {
        "variant": variant,
        "config": cm.config_dict(config),
        "geometry": {"L": L, "h": h, "die": {"start": [-config.die_overhang, h],
                                              "end": [L + config.die_overhang, h], "normal": [0.0, -1.0]}},
        "material": cm.material_dict(config),
        "friction": cm.friction_table(TOOLS, PHASES, [(0.0, config.mu)]),
        "contact": {"algorithm": algorithm, "eps_n": config.eps_n, "eps_t": eps_t,
                    "target_gap": config.target_gap if algorithm == "auglag" else None,
                    "max_augmentations": config.max_augmentations if algorithm == "auglag" else None,
                    "d_capture": config.d_capture},
        "mesh": {"nx": config.nx, "ny": config.ny},
        "schedule": [
            cm.schedule_entry(phases[0], "force on the die", "P", "N/mm", 0.0, config.F_clamp),
            {**cm.schedule_entry(phases[1], "displacement of DC", "U", "mm", 0.0, config.U_draw),
             "die": "force-driven, P = F_clamp" if config.draw_control == "force"
             else "position frozen at the end of clamp"},
        ],
    }
    return Scene(
        name=NAME, variant=variant, algorithm=algorithm, config=config, model=model, observe=observe,
        snapshot=cm.ContactSnapshot(),
        control=cm.step_control(phases, config.max_steps, config.stabilize, config.step_error,
                                     config.stall_steps),
        phase_names=PHASES, tool_names=TOOLS, clamping_tool=0, instants=INSTANTS,
        steady_window=tuple(float(v) for v in config.steady_window),
        roi=(-1.0, L + 1.0, -0.1, h + 0.1), y_scale=20.0, parameters=parameters)
