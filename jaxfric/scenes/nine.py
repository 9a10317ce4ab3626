"""Scene ``nine``: radial strip drawing test on Nine's drawbead simulator (benchmarks spec section 4).

A strip x in [x_left, x_right], y in [0, t] lies on two fixed shoulders A and C (radius R1, below it);
the clamping bead B (radius R1, above it) is pushed down by ``stroke`` between them (phase ``clamp``),
then the right end is pulled by U_draw (phase ``draw``) through the bead and the guide rollers D (above)
and E (below, radius R2). The strip is fed through a frictionless entry guide, a channel on its two faces
that ends before A (see below).

Tools, in order: ``A, B, C, D, E`` (full circles), then with the guide ``guide_top, guide_bottom`` (flat
faces with rounded lips). Candidates: bottom-surface nodes vs A, C, E; top-surface nodes vs B, D (less
the pulled right end's corners, held in both directions: ``_common.movable``); the nodes that can enter
the channel vs its faces. B is displacement-driven (e_q = (0, -1)); the rest are
fixed.

Values tagged [chosen] in the spec (section 9), all config fields here:
- reading of Table 3: e is the thickness ``t``, ``L1`` = 2 R1 + e is the pitch A->B and B->C, ``L2`` the
  distance C->D, ``L3`` D->E, and x_left = -Delta x1 (origin at the centre of A);
- B starts touching the strip top; D above the strip, E below it;
- rotating cylinders modelled as frictionless fixed cylinders (``mu_guides`` = 0 on D and E always;
  ``mu`` on A, B, C: 0 for ``mu000``, 0.17 for ``mu017``);
- right end held (u = v = 0) during ``clamp``, u = U(t) and v = 0 during ``draw``;
- entry guide (``entry_guide`` = True; spec: "rigid tools on both faces of the strip that end before
  shoulder A at a documented position"): two fixed frictionless faces, ``guide_top`` above the strip's top
  and ``guide_bottom`` below its bottom, each ``guide_clearance`` away from the undeformed strip, straight
  over x in [guide_end - guide_length, guide_end] with rounded lips of radius ``guide_lip`` at both ends.
  Only the part of the strip inside the channel touches it: the tail leaves through the exit and passes
  the bead freely.
  * Why a guide: with a free end the 50 mm entry leg pivots about A while B descends and stands up
    vertically by the end of ``clamp``; it reaches A at U of about 7.5 mm and the steady window collapses.
  * ``guide_end`` = -3 mm (the exit 3 mm before A's top): the strip leaves the channel straight and
    wraps A, and the channel reacts the bending moment of the wrap with a constant lever, so the drawing
    force stays steady while the tail is inside. The tail reaches the exit after the steady window:
    at U = 35 mm it is at x = -5.2 (``mu000``) and -7.9 mm (``mu017``) on 300 x 3; a longer lever would
    let it out inside the window. The short lever presses the strip on A: with ``mu017`` its friction
    adds about 3 % to the steady force (docs/results.md, the tail leaving the bead), and the span's shear
    force (the channel's 26 N/mm) adds a layer error of its own (``mu000``, ``anst``: 3 to 6 layers -0.69 %
    with this lever, -0.34 % with 6 mm; six-node ``anst`` on 150 along, 3 to 12 layers: -1.22 % with this
    lever, -0.72 % with 6 mm, -0.21 % with the left-end nodes held; docs/results.md, ``anst`` with 4
    points and the entry channel, elements quadratic along the strip);
  * ``guide_length`` = 5 mm, ``guide_clearance`` = 0.01 mm, ``guide_lip`` = 1 mm: a channel long
    enough to hold the strip's slope, short enough that the nodes inside it (15 per face on 300 x 3)
    leave ``band`` room for the wraps; the clearance keeps the unloaded faces off the strip (no
    degenerate contact at zero gap) and lets it tilt by at most 0.004 rad; the lips let a node enter
    and leave without meeting a corner.
  ``entry_guide_kind`` = ``end_nodes`` replaces the channel by v = 0 on the left-end nodes for the whole
  run: the wrap's bending on A is then reacted with the lever from A to the tail (about 20 to 5 mm
  across the steady window), and from U of about 41 mm the held tail is dragged into the bead (drawing
  force up to 4 times the steady one). The Nine's tables of docs/results.md other than the tail's
  passage were measured with it (U_draw 36 mm). ``entry_guide`` = False leaves the spec's free end;
- ``U_draw`` = 70 mm; nominal increments ``dq_clamp`` = 0.1 mm and ``dU`` = 0.1 mm. Measured cost of
  that choice (``experiments/nine_error_sources.py``, with ``end_nodes``; docs/results.md, discretisation
  error of the Nine test): at 300 x 3 with the default element the steady drawing force carries a step
  error of about -0.6 % (``mu000``) and -0.8 % (``mu017``), first order in the increment, from the return
  mapping along the plastic bending path; halve both fields for half the error at 1.4x the Newton
  iterations, or integrate the flow by the midpoint rule (``plastic_integration`` = ``midpoint``: with
  the entry channel -0.35 and -0.58 % against -0.63 and -0.92 %, at 1.4 to 1.6 times the solve time;
  docs/results.md, integration of the plastic flow);
- ``element`` = ``ans`` (F-bar on assumed natural strains, :mod:`jaxfric.fem.element`): F-bar's parasitic
  shear put the steady force on 300 x 3 6.9 % (``mu000``) and 9.3 % (``mu017``) above its limit along
  the strip; ``ans`` 1.4 % and 3.5 % (docs/results.md, discretisation error of the Nine test, with
  ``end_nodes``). Elements quadratic along the strip with ``anst`` and 4 points through each element
  (``element_order`` = 2, ``element`` = ``anst``, ``thickness_points`` = 4) are converged along the strip
  from 150 elements on, with and without friction, and give the force converged in length, layers and
  step (docs/results.md, elements quadratic along the strip), at 1.7 times ``ans``' cost per Newton
  iteration on 150 x 3 (the spec mesh's nodes) and 3.2 to 4.2 times on 300 x 3; their 3 layers are 1.5 %
  high without friction (the plastic bend under the channel's shear force before A, ``guide_end`` above),
  ``ans`` on 300 x 3 within 1 % of that force by a balance of larger errors, so ``ans`` stays the default
  for its cost;
- ``steady_window`` = (20, 35) mm;
- eps_t = mu eps_n [paper] (``eps_t`` None), with mu the largest coefficient of the scene.
- exact contact by lcp_lemke: ``band`` = 128 of the 602 candidate nodes (at 300 x 3) enter the complementarity
  problem, the nearest to a tool; at most about 60 pairs are closed at once (A, B, C wraps, the
  rollers D and E), so the band holds them with margin while the problem stays a fifth of the full size.
  The channel adds about 30 nodes at small gaps, and Lemke slows down near its exit (docs/results.md,
  the tail leaving the bead).
Not in the spec: the seam of each circle (where its arc length jumps) is put where the strip never
touches it: at the top of B and D (the strip touches their bottoms), at the bottom of A, C and E.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..contact.formulations import formulation
from ..contact.rigid import Move, RigidTool
from ..contact.tools import Tool
from ..fem.loading import DirichletBC, Phase, Ramp
from ..fem.mesh import strip_mesh
from ..loadpath.model import StripModel
from . import _common as cm
from .base import Scene

__all__ = ["NAME", "NineConfig", "VARIANTS", "DEFAULT_VARIANT", "NineObserve", "build"]

NAME = "nine"
DEFAULT_VARIANT = "mu017"
# Config fields of the nominal increments (a float: an increment; an int: a phase's step count).
STEP_FIELDS = ("dq_clamp", "dU")
STROKE_FIELD = "U_draw"  # the drawing stroke: steady_window lies in [0, U_draw]
PHASES = ("clamp", "draw")
TOOLS = ("A", "B", "C", "D", "E")
GUIDE_TOOLS = ("guide_top", "guide_bottom")  # after TOOLS with the entry guide's channel
GUIDE_KINDS = ("channel", "end_nodes")
# Named instants (benchmarks spec, scene Outputs), in order, each with its rule
# (:func:`jaxfric.io.instants.select_instants`).
INSTANT_RULES = {"clamped": ("end", "clamp"), "steady": ("closest", "draw", 27.5), "final": ("final",)}
INSTANTS = tuple(INSTANT_RULES)


@dataclasses.dataclass(frozen=True)
class NineConfig(cm.FrictionLawFields, cm.PreselectField, cm.PlasticIntegrationField, cm.SolverFields):
    """Every value of the Nine scene (spec section 4); defaults are the spec's (variant ``mu017``)."""

    x_left: float = cm.spec_field(-50.0, "mm", "left (free) end of the strip; -Delta x1 [chosen reading]")
    x_right: float = cm.spec_field(50.0, "mm", "right (pulled) end of the strip [paper: 100 mm strip]")
    t: float = cm.spec_field(0.97, "mm", "strip thickness e [paper, chosen reading]")
    nx: int = cm.spec_field(300, "-", "elements along the strip [paper]")
    ny: int = cm.spec_field(3, "-", "elements through the thickness [paper]")
    R1: float = cm.spec_field(5.5, "mm", "radius of A, B, C [paper]")
    R2: float = cm.spec_field(2.87, "mm", "radius of D, E [paper]")
    L1: float | None = cm.spec_field(None, "mm", "pitch A->B and B->C; None: 2 R1 + t (= 11.97) [paper]")
    L2: float = cm.spec_field(2.63, "mm", "horizontal distance C->D [paper, chosen reading]")
    L3: float = cm.spec_field(12.43, "mm", "horizontal distance D->E [paper, chosen reading]")
    mu: float = cm.spec_field(0.17, "-", "friction on A, B, C (variant: 0 or 0.17) [paper]")
    mu_guides: float = cm.spec_field(0.0, "-", "friction on the guide rollers D, E [chosen: rolling]")
    E: float = cm.spec_field(200000.0, "MPa", "Young's modulus (Table 4) [paper]")
    nu: float = cm.spec_field(0.3, "-", "Poisson's ratio [paper]")
    sigma_y: float = cm.spec_field(171.0, "MPa", "initial yield stress [paper]")
    A: float = cm.spec_field(121.74485, "-", "hardening coefficient in sigma_y (1 + A eqps)^n [paper]")
    n: float = cm.spec_field(0.23, "-", "hardening exponent [paper]")
    C_kin: tuple = cm.spec_field((), "MPa", cm.C_KIN_DOC)
    gamma_kin: tuple = cm.spec_field((), "-", cm.GAMMA_KIN_DOC)
    Q_voce: tuple = cm.spec_field((), "MPa", cm.Q_VOCE_DOC)
    b_voce: tuple = cm.spec_field((), "-", cm.B_VOCE_DOC)
    eps_n: float = cm.spec_field(1e5, "N/mm/mm", "normal penalty [paper]")
    eps_t: float | None = cm.spec_field(None, "N/mm/mm", "tangential penalty; None: mu eps_n [paper]")
    target_gap: float = cm.spec_field(1e-5, "mm", "auglag target gap [chosen]")
    max_augmentations: int = cm.spec_field(20, "-", cm.MAX_AUGMENTATIONS_DOC)
    max_steps: int | None = cm.spec_field(None, "-", cm.MAX_STEPS_DOC)
    stabilize: float = cm.spec_field(cm.STABILIZE, "-", cm.STABILIZE_DOC)
    stall_steps: int = cm.spec_field(cm.STALL_STEPS, "-", cm.STALL_STEPS_DOC)
    step_error: float = cm.spec_field(0.0, "-", cm.STEP_ERROR_DOC)
    smoothing: float = cm.spec_field(0.0, "N/mm", cm.SMOOTHING_DOC)
    d_capture: float = cm.spec_field(2.0, "mm", "capture depth [chosen]")
    band: int | None = cm.spec_field(128, "-", cm.BAND_DOC)
    element: str = cm.spec_field("ans", "-", cm.ELEMENT_DOC)
    element_order: int = cm.spec_field(1, "-", cm.ELEMENT_ORDER_DOC)
    thickness_points: int = cm.spec_field(2, "-", cm.THICKNESS_POINTS_DOC)
    enhanced_update: str = cm.spec_field("iterate", "-", cm.ENHANCED_UPDATE_DOC)
    stroke: float = cm.spec_field(11.0, "mm", "downward travel of B during clamp (2 R1) [paper]")
    U_draw: float = cm.spec_field(70.0, "mm", "pull of the right end during draw [chosen]")
    dq_clamp: float = cm.spec_field(0.1, "mm", "nominal increment of B's travel [chosen]")
    dU: float = cm.spec_field(0.1, "mm", "nominal increment of the pull [chosen]")
    steady_window: tuple = cm.spec_field((20.0, 35.0), "mm", "steady window in U [chosen]")
    entry_guide: bool = cm.spec_field(True, "-", "feed the strip through a frictionless channel on its two "
                                      "faces ending before A; False: the spec's free end [chosen, see the "
                                      "module docstring]")
    entry_guide_kind: str = cm.spec_field("channel", "-", "'channel': frictionless faces on both sides of the "
                                          "strip ending at guide_end; 'end_nodes': v = 0 on the left-end "
                                          "nodes [chosen, see the module docstring]")
    guide_end: float = cm.spec_field(-3.0, "mm", "x of the entry guide's exit (A's top is at x = 0) [chosen]")
    guide_length: float = cm.spec_field(5.0, "mm", "length of the entry guide's straight faces [chosen]")
    guide_clearance: float = cm.spec_field(0.01, "mm", "gap between each guide face and the undeformed "
                                           "strip [chosen]")
    guide_lip: float = cm.spec_field(1.0, "mm", "radius of the rounded lips at the guide's ends [chosen]")


VARIANTS = {"mu000": {"mu": 0.0}, "mu017": {"mu": 0.17}}


class NineObserve(eqx.Module):
    """Static ``observe(model, state)`` of the Nine scene (spec section 4, Outputs).

    drawing_force = sum of the right-end reactions along +x; clamping_force = e_q . resultant of B
    (e_q = (0, -1)); tool_position = q_B; drawing_displacement = U (0 before draw); guide_top_fy and
    guide_bottom_fy: vertical resultants of the entry guide's faces on the strip (0 without the guide).
    """

    right: tuple = eqx.field(static=True)     # right-end nodes
    tail: int = eqx.field(static=True)        # bottom-left node
    pull: tuple = eqx.field(static=True)      # (phase, condition) of the pull's Ramp: its end is U_draw

    def __call__(self, model, state) -> dict:
        c = state.contact
        resultants = cm.tool_resultants(model, state)
        f_a, f_b, f_c, f_d, f_e = resultants[:len(TOOLS)]
        guide = resultants[len(TOOLS):] or (jnp.zeros(2), jnp.zeros(2))
        return {
            "drawing_displacement": cm.ramp_end(model, *self.pull) * cm.phase_progress(state, 1),
            "drawing_force": cm.end_reaction(model, state, self.right)[0],
            "clamping_force": c.force[1],
            "tool_position": c.q[1],
            **cm.contact_columns(state),
            "bead_fx": f_b[0],
            "tail_x": model.mesh.nodes[self.tail, 0] + state.u[self.tail, 0],
            "cyl_a_fx": f_a[0], "cyl_a_fy": f_a[1],
            "cyl_c_fx": f_c[0], "cyl_c_fy": f_c[1],
            "cyl_d_fy": f_d[1], "cyl_e_fy": f_e[1],
            "guide_top_fy": guide[0][1], "guide_bottom_fy": guide[1][1],
        }


def _check(config: NineConfig) -> None:
    cm.check_config(config, positive=("t", "R1", "R2", "L1", "U_draw", "dq_clamp", "dU", "guide_length",
                                      "guide_clearance", "guide_lip"),
                    nonnegative=("stabilize", "step_error", "mu", "mu_guides", "stroke", "L2", "L3"),
                    integers=("nx", "ny", "band", "stall_steps"),
                    choices={"entry_guide_kind": GUIDE_KINDS},
                    lengths=("x_left", "x_right", "t", "R1", "R2", "L1", "L2", "L3", "guide_end", "guide_length",
                             "guide_clearance", "guide_lip"))
    if not config.x_right > config.x_left:
        raise ValueError(f"config field 'x_right' = {config.x_right!r} must exceed x_left = {config.x_left!r}")
    if channel(config) and not config.x_left < config.guide_end < 0.0:
        raise ValueError(f"config field 'guide_end' = {config.guide_end!r} must lie between x_left = "
                         f"{config.x_left!r} and A's top at x = 0")


def channel(config: NineConfig) -> bool:
    """The strip is fed through the entry guide's channel (``entry_guide`` on, kind ``channel``)."""
    return bool(config.entry_guide) and config.entry_guide_kind == "channel"


def _guide(mesh, config: NineConfig) -> list:
    """The entry guide's two faces (module docstring): fixed, frictionless, each a straight face between
    two convex quarter-circle lips; candidates are the nodes that can reach the exit lip (the strip
    moves towards +x only)."""
    c = config.guide_clearance
    top, bottom = cm.flat_faces(config.guide_end - config.guide_length, config.guide_end, config.t + c, -c,
                                config.guide_lip, config.d_capture)
    x_reach = config.guide_end + config.guide_lip
    still = (Move(0.0, 0.0), Move(0.0, 0.0))
    faces = []
    for name, geometry, nodes, drive in (("guide_top", top, mesh.top, (0.0, -1.0)),
                                         ("guide_bottom", bottom, mesh.bottom, (0.0, 1.0))):
        candidates = np.asarray(nodes)[np.asarray(mesh.nodes)[np.asarray(nodes), 0] <= x_reach]
        faces.append(RigidTool(name, geometry, drive, candidates, still, 0.0, frictional=False))
    return faces


def build(config: NineConfig = NineConfig(), algorithm: str = "penalty", variant: str = DEFAULT_VARIANT) -> Scene:
    """The Nine scene for ``config`` (the variant's overrides already applied) and ``algorithm``."""
    cm.check_variant(NAME, VARIANTS, variant)
    cm.check_algorithm(algorithm)
    _check(config)
    t, R1, R2 = config.t, config.R1, config.R2
    L1 = 2.0 * R1 + t if config.L1 is None else config.L1
    # Centres: origin at the centre of A's top; strip bottom on y = 0 (spec section 4 table).
    centres = {"A": (0.0, -R1), "B": (L1, t + R1), "C": (2.0 * L1, -R1),
               "D": (2.0 * L1 + config.L2, t + R2), "E": (2.0 * L1 + config.L2 + config.L3, -R2)}
    radii = {"A": R1, "B": R1, "C": R1, "D": R2, "E": R2}
    above = {"A": False, "B": True, "C": False, "D": True, "E": False}
    mu = {"A": config.mu, "B": config.mu, "C": config.mu, "D": config.mu_guides, "E": config.mu_guides}

    mesh = strip_mesh(config.x_left, config.x_right, 0.0, t, config.nx, config.ny, order=config.element_order)
    n_clamp = cm.n_steps("dq_clamp", config.stroke, config.dq_clamp)
    n_draw = cm.n_steps("dU", config.U_draw, config.dU)
    hold = DirichletBC(mesh.right, (0, 1))
    pull = DirichletBC(mesh.right, (0, 1), Ramp((0.0, 0.0), (config.U_draw, 0.0)))
    end_nodes = [DirichletBC(mesh.left, (1,))] if config.entry_guide and not channel(config) else []
    phases = (Phase("clamp", [hold] + end_nodes, n_clamp), Phase("draw", [pull] + end_nodes, n_draw))

    tools = []
    for name in TOOLS:
        # Seam opposite the contact side: top for a cylinder above the strip, bottom for one below.
        seam = 0.5 * math.pi if above[name] else -0.5 * math.pi
        geometry = Tool.circle(centres[name], radii[name], d_capture=config.d_capture, seam=seam)
        drive = (0.0, -1.0) if above[name] else (0.0, 1.0)
        candidates = cm.movable(mesh, mesh.top if above[name] else mesh.bottom, phases)
        stroke = config.stroke if name == "B" else 0.0
        controls = (Move(0.0, stroke), Move(0.0, 0.0))
        # A tool of mu = 0 is declared frictionless: no friction term is built for it.
        tools.append(RigidTool(name, geometry, drive, candidates, controls, mu[name] if mu[name] > 0 else 0.0,
                               frictional=mu[name] > 0, friction=cm.friction_law(config) if mu[name] > 0 else None))
    if channel(config):
        tools += _guide(mesh, config)
    tool_names = tuple(t.name for t in tools)

    mu_max = max(mu.values())
    eps_t = cm.resolve_eps_t(config, mu_max)
    law = formulation(algorithm, config.eps_n, eps_t, config.target_gap, config.band, config.smoothing,
                      config.max_augmentations, stiff_above=cm.stiff_penalty(config),
                      search=config.lemke_search, exact_start=config.exact_start)
    material = cm.material(config)
    model = StripModel(mesh, material, phases, tools=cm.preselected(tools, mesh, config.preselect),
                       contact=law, formulation=config.element,
                       thickness_points=config.thickness_points,
                       enhanced_update=config.enhanced_update,
                       phase_seconds=cm.phase_seconds(config, phases, config.U_draw))
    observe = NineObserve(right=tuple(int(a) for a in mesh.right), tail=int(mesh.node_index(0, 0)), pull=(1, 0))

    parameters = {
        "variant": variant,
        "config": cm.config_dict(config),
        "geometry": {"x_left": config.x_left, "x_right": config.x_right, "t": t, "R1": R1, "R2": R2,
                     "L1": L1, "L2": config.L2, "L3": config.L3,
                     "centres": {k: list(v) for k, v in centres.items()},
                     "stroke": config.stroke, "U_draw": config.U_draw,
                     "entry_guide": ({"x": [config.guide_end - config.guide_length, config.guide_end],
                                      "clearance": config.guide_clearance, "lip": config.guide_lip}
                                     if channel(config) else None)},
        "material": cm.material_dict(config),
        "friction": cm.friction_table(tool_names, PHASES, [(mu.get(k, 0.0),) * 2 for k in tool_names]),
        "contact": {"algorithm": algorithm, "eps_n": config.eps_n, "eps_t": eps_t,
                    "target_gap": config.target_gap if algorithm == "auglag" else None,
                    "max_augmentations": config.max_augmentations if algorithm == "auglag" else None,
                    "d_capture": config.d_capture},
        "mesh": {"nx": config.nx, "ny": config.ny},
        "schedule": [cm.schedule_entry(phases[0], "displacement of B", "q_B", "mm", 0.0, config.stroke),
                     cm.schedule_entry(phases[1], "displacement of the right end", "U", "mm", 0.0,
                                       config.U_draw)],
    }
    return Scene(
        name=NAME, variant=variant, algorithm=algorithm, config=config, model=model, observe=observe,
        snapshot=cm.ContactSnapshot(),
        control=cm.step_control(phases, config.max_steps, config.stabilize, config.step_error,
                                     config.stall_steps),
        phase_names=PHASES, tool_names=tool_names, clamping_tool=1, instants=INSTANTS,
        steady_window=tuple(float(v) for v in config.steady_window),
        roi=(-15.0, 45.0, -15.0, 12.0), y_scale=1.0, parameters=parameters)
