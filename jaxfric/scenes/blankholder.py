"""Scene ``blankholder``: blankholder with drawbead (benchmarks spec section 5).

The upper (female) die is fixed: two flat lands of length L at y = t around a round groove (concave arc
of radius Rp centred on the land line) with shoulder fillets of radius r and rounded outer edges (r_e).
The lower (male) tool carries a bead of height H (nose radius R on vertical flanks) between lands; it
rises by H (phase ``close``, displacement-driven), is then brought to the clamping force F_clamp (phase
``lock``, force-driven, linear ramp from the reaction at the end of ``close``), and holds it while the
right end of the sheet is pulled by U_pull (phase ``draw``). The left end is free; v = 0 at the right end.

Derived geometry (spec Table 7): x_g = sqrt((Rp + r)^2 - r^2) (half-width of the groove mouth), the
fillet/groove tangency T_R = (0, t) + Rp (c_fR - (0, t)) / (Rp + r) with c_fR = (x_g, t + r), T_L its mirror.

Tools, in order: ``upper`` (fixed, candidates: top surface), ``lower`` (e_q = (0, 1), candidates: bottom
surface; the clamping tool).

Values tagged [chosen] in the spec (section 9), all config fields here:
- reading of Table 7 (H, R, r, Rp, L) as above; ``t`` = 1.0 mm; edge radius ``r_e`` = 2 mm;
- lower lands extended to X_far = max(|x_left|, |x_right|) + ``land_margin`` (20 mm) upstream;
  downstream the lower land ends with the upper one, at x_g + L, in an edge arc of radius ``r_e``
  (``downstream_land`` = "clamp"; "far" extends it to X_far as the spec does). Why: the spec's land
  reaches under the grip, whose nodes are held at v = 0 on its level, so the force-driven lower tool
  presses on a rigid support: during the draw the grip's bottom node carries 141 of the lower tool's
  329 N/mm on shape1 and 201 of 318 on shape9 (``lcp_ssn``), the upper die only 191 and 122, and the
  lands' friction is that much smaller. Ended with the upper land, the lower one sends the whole
  clamping force through the clamped sheet (upper die 341 and 332 N/mm), and the steady drawing force
  is 182.6 N/mm on shape1 (164.6 with "far") and 142.6 on shape9 (115.6). The spec's own reason for X_far,
  that the unclamped upstream tail cannot swing below the lands, holds upstream only. The grip's nodes
  stay candidates (unlike the Nine's and the bead's, ``_common.movable``), so that "far" is the spec's
  model exactly; with "clamp" no tool reaches them.
- sheet extent x_left = -(x_g + L + U_pull + ``upstream_margin``), x_right = x_g + L + ``grip_length``
  (20 and 10 mm) and nx = round((x_right - x_left) / ``element_length``) with 0.5 mm (all derived when
  None; 2 layers ny = 2 [paper]);
- mu = 0.15 on both tools in all phases; F_clamp = 300 N/mm; U_pull = 55 mm; eps_n = 1e5 N/mm with
  eps_t = mu eps_n (``eps_t`` None);
- close/lock split (``lock_control`` = "force"; "position" keeps s = H during draw); v = 0 at the right
  end, u = 0 there during close and lock;
- increments ``ds_close`` = 0.05 mm, ``n_lock`` = 10 steps, ``dU`` = 0.1 mm; ``steady_window`` = (35, 55) mm.
- the upper die is set ``clearance`` = 0.05 mm above the sheet for the whole run (its control holds it
  at q = -clearance along e_q = (0, -1); its geometry is the spec's, so at rest the lands still touch).
  Why: with the lands touching, the sheet lies on both lands (2 L) at zero gap and zero force, an
  indeterminate contact state. At any stroke s > 0 the exact solution lifts it off every land node but
  the one at each fillet edge (shape3: gap rising by 0.11 s per mm from it), but zero-gap pairs count
  as closed, and with eps_n stiffer than the sheet's bending at the node scale ((4 E I / eps_n)^(1/4)
  = 0.7 mm) a Newton step only sees the tension at the first closed node: the lift-off front advances
  one node per iteration, so the first step needs about L / element_length + 3 iterations whatever its
  size (15 at 2 mm, 28 at 1 mm; at 0.5 mm it diverges), more than max_iterations = 25. With the
  clearance the sheet first meets the die at isolated points. The lock ramp closes the clearance (the
  lower tool rises by it); 0.05 mm is 5 % of t and well below the 0.2 mm left over the nose at
  closure. ``clearance`` = 0 is the spec's layout.
- Newton may take ``newton_iterations`` = 60 iterations per attempt, not the spec's 25 (section 1.9)
  [chosen]. Why: early in ``close`` the strip, held at v = 0 only at its right end, swings up about the
  nose and its free upstream part meets the upper land near its outer edge (shape4: at s = 0.025 mm).
  From then on single pairs there flip open/closed on alternate Newton iterations (residual
  2.7e-3, 6e-5, 2.7e-3, ... N/mm) until the line search breaks the cycle, which took 14 iterations
  in one measured attempt and more than 25 in others, at any increment down to nominal / 1024: the
  long-land shapes 2, 4 and 7 and shape 9 stopped in ``close`` at 25 (measured with F-bar, spec mesh);
  shape2 completes at 60 (1947 steps, 22599 iterations). Set ``newton_iterations=25`` for the
  spec's rule.
- exact contact by lcp_lemke: ``band`` = 256 of the 620 candidate nodes (shape1, spec mesh) enter the
  condensed complementarity problem [chosen]. Why: a pivot costs the square of the band's size and a
  solve takes more pivots on a larger band. Shape1, close + lock + a 2 mm pull (measured with F-bar):
  all 620 nodes, 153 steps, 48,303 pivots, 388 s of CPU; 256 nodes, 152 steps, 26,334 pivots, 99 s; the
  whole 55 mm pull at 256 nodes: 680 steps, 0 cutbacks, 41,195 pivots, 406 s. A band too small fails
  the attempt with CONTACT_BAND (a node outside it penetrates), never silently, and the run widens it
  and takes the step again (:func:`jaxfric.loadpath.controller.band_full`). The long lands need it: on
  shapes 2 and 4, 200 to 208 pairs close in the draw, and the band grows to 512 early in the pull; a 512
  band from the start would cost 9 times the time of a closing step (``python experiments/lemke_band.py``;
  docs/results.md, Lemke's proximity band on long lands).
- ``element`` = ``anst`` with ``thickness_points`` = 4 per layer (:mod:`jaxfric.fem.element`), not F-bar
  nor the Nine's ``ans``. Why (spec mesh, default layout, ``lcp_ssn``; docs/results.md, the
  through-thickness mode): at the nominal increments the mesh- and layer-converged steady force lies
  between bilinear ``anst`` with 8 points and six-node ``anst`` on 4 layers, and half the increments
  raise it by 0.1 to 0.2 % (to twice that by Richardson): converged, shape1 about 186.4 to 187.3 N/mm,
  shape5 162.4 to 163.7, shape9 145.2 to 145.8. ``anst`` with 4 points gives 185.42, 162.48 and 145.13,
  within 1.0 % of it, at 1.33 to 1.45 times F-bar's solve time. F-bar gives 182.60, 159.79 and 142.60,
  1.6 to 2.5 % low; ``anst`` with 2 points 189.74 on shape1 (the plastic stress through each of the 2
  layers integrated too coarsely); ``ans`` bends too softly on 2 layers (-9 % against F-bar with the
  spec's layout). F-bar stays available: ``element=fbar``, ``thickness_points=2``.
The spec's stop rule (a reaction above F_clamp at the end of ``close`` ends the run unconverged) needs
the run driver: the lock ramp alone would simply lower the force.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..contact.formulations import formulation
from ..contact.rigid import Force, Move, RigidTool
from ..contact.tools import Arc, Segment, Tool
from ..fem.loading import DirichletBC, Phase, Ramp
from ..fem.mesh import strip_mesh
from ..loadpath.model import StripModel
from ..numerics.newton import NewtonOptions
from . import _common as cm
from .base import Scene

__all__ = ["NAME", "BlankholderConfig", "VARIANTS", "DEFAULT_VARIANT", "BlankholderObserve", "build",
           "groove_geometry", "sheet_extent"]

NAME = "blankholder"
DEFAULT_VARIANT = "shape1"
# Config fields of the nominal increments (a float: an increment; an int: a phase's step count).
STEP_FIELDS = ("ds_close", "n_lock", "dU")
STROKE_FIELD = "U_pull"  # the drawing stroke: steady_window lies in [0, U_pull]
PHASES = ("close", "lock", "draw")
TOOLS = ("upper", "lower")
# Named instants (benchmarks spec, scene Outputs), in order, each with its rule
# (:func:`jaxfric.io.instants.select_instants`).
INSTANT_RULES = {"closed": ("end", "close"), "locked": ("end", "lock"), "drawing": ("closest", "draw", 27.5),
                 "final": ("final",)}
INSTANTS = tuple(INSTANT_RULES)

# Table 7 [paper]: H, R, r, R', L (mm).
TABLE7 = ((6, 6, 3, 7.25, 25), (6, 6, 3, 7.25, 50), (9, 6, 4.5, 10.2, 25), (9, 6, 4.5, 10.2, 50),
          (9, 9, 4.5, 10.2, 25), (12, 6, 6, 13.2, 25), (12, 6, 6, 13.2, 50), (12, 9, 6, 13.2, 25),
          (12, 12, 6, 13.2, 25))


@dataclasses.dataclass(frozen=True)
class BlankholderConfig(cm.FrictionLawFields, cm.PreselectField, cm.PlasticIntegrationField, cm.SolverFields):
    """Every value of the blankholder scene (spec section 5); defaults are the spec's (``shape1``)."""

    H: float = cm.spec_field(6.0, "mm", "bead height above the lower lands = closing stroke (Table 7) [paper]")
    R: float = cm.spec_field(6.0, "mm", "bead nose radius (Table 7) [paper]")
    r: float = cm.spec_field(3.0, "mm", "groove shoulder fillet radius (Table 7) [paper]")
    Rp: float = cm.spec_field(7.25, "mm", "groove radius R' (Table 7) [paper]")
    L: float = cm.spec_field(25.0, "mm", "length of each upper land (Table 7) [paper]")
    t: float = cm.spec_field(1.0, "mm", "sheet thickness, y in [0, t] [chosen]")
    r_e: float = cm.spec_field(2.0, "mm", "outer edge radius of the upper lands [chosen]")
    x_left: float | None = cm.spec_field(None, "mm", "left end; None: -(x_g + L + U_pull + 20) [chosen]")
    x_right: float | None = cm.spec_field(None, "mm", "right (pulled) end; None: x_g + L + 10 [chosen]")
    upstream_margin: float = cm.spec_field(20.0, "mm", "tail beyond the upper land at the end of draw [chosen]")
    grip_length: float = cm.spec_field(10.0, "mm", "free length between the land and the grip [chosen]")
    land_margin: float = cm.spec_field(20.0, "mm", "lower lands reach max(|x_left|, |x_right|) + this [chosen]")
    downstream_land: str = cm.spec_field("clamp", "-", "downstream lower land: 'clamp' ends it with the upper "
                                                       "land (x_g + L) in an edge arc of radius r_e; 'far' "
                                                       "reaches X_far, under the grip (the spec's layout) [chosen]")
    element_length: float = cm.spec_field(0.5, "mm", "element length giving nx when nx is None [chosen]")
    nx: int | None = cm.spec_field(None, "-", "elements along x; None: round((x_right - x_left) / "
                                                "element_length) [chosen]")
    ny: int = cm.spec_field(2, "-", "elements through the thickness [paper]")
    mu: float = cm.spec_field(0.15, "-", "friction on both tools, all phases [chosen]")
    E: float = cm.spec_field(71000.0, "MPa", "Young's modulus (Table 8) [paper]")
    nu: float = cm.spec_field(0.34, "-", "Poisson's ratio [paper]")
    sigma_y: float = cm.spec_field(139.0, "MPa", "initial yield stress [paper]")
    A: float = cm.spec_field(127.32852, "-", "hardening coefficient in sigma_y (1 + A eqps)^n [paper]")
    n: float = cm.spec_field(0.28, "-", "hardening exponent [paper]")
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
    clearance: float = cm.spec_field(0.05, "mm", "the upper die is set this far above the sheet [chosen]")
    d_capture: float = cm.spec_field(2.0, "mm", "capture depth [chosen]")
    band: int | None = cm.spec_field(256, "-", cm.BAND_DOC)
    element: str = cm.spec_field("anst", "-", cm.ELEMENT_DOC)
    element_order: int = cm.spec_field(1, "-", cm.ELEMENT_ORDER_DOC)
    thickness_points: int = cm.spec_field(4, "-", cm.THICKNESS_POINTS_DOC)
    enhanced_update: str = cm.spec_field("iterate", "-", cm.ENHANCED_UPDATE_DOC)
    F_clamp: float = cm.spec_field(300.0, "N/mm", "clamping force on the lower tool [chosen]")
    U_pull: float = cm.spec_field(55.0, "mm", "pull of the right end during draw [chosen]")
    lock_control: str = cm.spec_field("force", "-", "lower tool during draw: 'force' (P = F_clamp), "
                                                    "'position' (held where the lock left it) or 'depth' "
                                                    "(closed to `closure` and held there, no lock force: "
                                                    "the bead alone, for bead cards) [chosen]")
    closure: float | None = cm.spec_field(None, "mm", "with lock_control='depth': the lower tool's stroke, "
                                                      "0 < closure <= H (the bead's penetration); None: H")
    ds_close: float = cm.spec_field(0.05, "mm", "nominal increment of the stroke in close [chosen]")
    n_lock: int = cm.spec_field(10, "-", "steps of the lock force ramp [chosen]")
    dU: float = cm.spec_field(0.1, "mm", "nominal increment of the pull [chosen]")
    steady_window: tuple = cm.spec_field((35.0, 55.0), "mm", "steady window in U [chosen]")
    newton_iterations: int = cm.spec_field(60, "-", "Newton iterations allowed per attempt [chosen; spec 1.9: 25]")


VARIANTS = {f"shape{k + 1}": {"H": float(H), "R": float(R), "r": float(r), "Rp": float(Rp), "L": float(L)}
            for k, (H, R, r, Rp, L) in enumerate(TABLE7)}


def groove_geometry(config: BlankholderConfig) -> dict:
    """x_g (mm), the tangency point T_R (2,) (mm) and the fillet angle atan2(r, x_g) (rad)."""
    Rp, r, t = config.Rp, config.r, config.t
    x_g = math.sqrt((Rp + r) ** 2 - r**2)
    T_R = (Rp * x_g / (Rp + r), t + Rp * r / (Rp + r))
    return {"x_g": x_g, "T_R": T_R, "alpha": math.atan2(r, x_g)}


def sheet_extent(config: BlankholderConfig) -> tuple[float, float, int]:
    """(x_left, x_right, nx): the config's values, or the spec's derived ones where None."""
    x_g = groove_geometry(config)["x_g"]
    x_left = -(x_g + config.L + config.U_pull + config.upstream_margin) if config.x_left is None else config.x_left
    x_right = x_g + config.L + config.grip_length if config.x_right is None else config.x_right
    nx = int(round((x_right - x_left) / config.element_length)) if config.nx is None else config.nx
    return float(x_left), float(x_right), max(nx, 1)


class BlankholderObserve(eqx.Module):
    """Static ``observe(model, state)`` of the blankholder (spec section 5, Outputs).

    drawing_force = sum of the right-end reactions along +x; clamping_force = e_q . resultant of the
    lower tool (e_q = (0, 1)); tool_position = s; drawing_displacement = U; n_land_closed = closed upper
    pairs whose node lies over a land (x_g <= |x| <= x_g + L).
    """

    right: tuple = eqx.field(static=True)    # right-end nodes
    tail: int = eqx.field(static=True)       # bottom-left node
    U_pull: float = eqx.field(static=True)   # mm
    x_g: float = eqx.field(static=True)      # mm
    L: float = eqx.field(static=True)        # mm

    def __call__(self, model, state) -> dict:
        c = state.contact
        upper, lower = cm.tool_resultants(model, state)
        n_up = len(model.tools[0].candidates)
        top = np.asarray(model.tools[0].candidates)
        x_top = jnp.abs(model.mesh.nodes[top, 0] + state.u[top, 0])
        on_land = (x_top >= self.x_g) & (x_top <= self.x_g + self.L)
        return {
            "drawing_displacement": self.U_pull * cm.phase_progress(state, 2),
            "drawing_force": cm.end_reaction(model, state, self.right)[0],
            "clamping_force": c.force[1],
            "tool_position": c.q[1],
            **cm.contact_columns(state),
            "upper_fx": upper[0], "upper_fy": upper[1],
            "lower_fx": lower[0],
            "n_land_closed": jnp.sum((c.status[:n_up] > 0) & on_land),
            "tail_x": model.mesh.nodes[self.tail, 0] + state.u[self.tail, 0],
        }


def _check(config: BlankholderConfig) -> None:
    cm.check_config(config, positive=("H", "R", "r", "Rp", "L", "t", "r_e", "element_length", "U_pull", "ds_close",
                                      "dU", "closure"),
                    nonnegative=("stabilize", "step_error", "mu", "F_clamp", "upstream_margin", "grip_length",
                                 "land_margin", "clearance"),
                    integers=("nx", "ny", "band", "n_lock", "newton_iterations", "stall_steps"),
                    choices={"lock_control": ("force", "position", "depth"), "downstream_land": ("clamp", "far")},
                    lengths=("H", "R", "r", "Rp", "L", "t", "r_e", "x_left", "x_right", "upstream_margin",
                             "grip_length", "land_margin", "clearance"))
    if config.R > config.H:
        raise ValueError(f"config field 'R' = {config.R!r} must not exceed H = {config.H!r} (the nose sits "
                         "on flanks of height H - R)")
    # At closure the bead nose top (y = H) carries the sheet (to y = H + t) under the groove top (t + Rp).
    if not config.H < config.Rp:
        raise ValueError(f"config field 'H' = {config.H!r} leaves no room for the sheet under the groove "
                         f"(Rp = {config.Rp!r}): need H + t < t + Rp")
    if config.closure is not None:
        if config.lock_control != "depth":
            raise ValueError(f"config field 'closure' = {config.closure!r} needs lock_control='depth' (it is "
                             f"{config.lock_control!r})")
        if not config.closure <= config.H:
            raise ValueError(f"config field 'closure' = {config.closure!r} must lie in (0, H = {config.H!r}]")
    x_left, x_right, _ = sheet_extent(config)
    if not x_right > x_left:
        raise ValueError(f"config field 'x_right' = {x_right!r} must exceed x_left = {x_left!r}")


def _upper_die(config: BlankholderConfig, x_g: float, alpha: float) -> Tool:
    """Chain left to right, sheet below (normal side 'right'): edge arc, land, fillet, groove (concave),
    fillet, land, edge arc."""
    t, r, Rp, L, r_e = config.t, config.r, config.Rp, config.L, config.r_e
    pi = math.pi
    a = x_g + L
    prims = (Arc((-a, t + r_e), r_e, pi, 1.5 * pi),
             Segment((-a, t), (-x_g, t)),
             Arc((-x_g, t + r), r, -0.5 * pi, -alpha),                   # towards T_L: direction (x_g, -r)
             Arc((0.0, t), Rp, pi - alpha, alpha, concave=True),          # T_L over the top to T_R
             Arc((x_g, t + r), r, -pi + alpha, -0.5 * pi),                # from T_R: direction (-x_g, -r)
             Segment((x_g, t), (a, t)),
             Arc((a, t + r_e), r_e, -0.5 * pi, 0.0))
    return Tool(prims, normal_side="right", d_capture=config.d_capture)


def _lower_tool(config: BlankholderConfig, x_far: float) -> Tool:
    """At rest (s = 0), chain left to right, sheet above (normal side 'left'): land at y = -H, flank,
    nose (centre (0, -R)), flank, land. The flanks exist when H > R."""
    H, R = config.H, config.R
    prims: list[Segment | Arc] = [Segment((-x_far, -H), (-R, -H))]
    if H > R:
        prims.append(Segment((-R, -H), (-R, -R)))
    prims.append(Arc((0.0, -R), R, math.pi, 0.0))
    if H > R:
        prims.append(Segment((R, -R), (R, -H)))
    if config.downstream_land == "far":
        prims.append(Segment((R, -H), (x_far, -H)))
    else:  # ends under the upper land's edge arc, mirrored
        end, r_e = groove_geometry(config)["x_g"] + config.L, config.r_e
        prims += [Segment((R, -H), (end, -H)), Arc((end, -H - r_e), r_e, 0.5 * math.pi, 0.0)]
    return Tool(tuple(prims), normal_side="left", d_capture=config.d_capture)


def build(config: BlankholderConfig = BlankholderConfig(), algorithm: str = "penalty",
          variant: str = DEFAULT_VARIANT) -> Scene:
    """The blankholder scene for ``config`` (the variant's overrides already applied) and ``algorithm``."""
    cm.check_variant(NAME, VARIANTS, variant)
    cm.check_algorithm(algorithm)
    _check(config)
    groove = groove_geometry(config)
    x_g = groove["x_g"]
    x_left, x_right, nx = sheet_extent(config)
    x_far = max(abs(x_left), abs(x_right)) + config.land_margin
    mesh = strip_mesh(x_left, x_right, 0.0, config.t, nx, config.ny, order=config.element_order)

    hold = DirichletBC(mesh.right, (0, 1))
    pull = DirichletBC(mesh.right, (0, 1), Ramp((0.0, 0.0), (config.U_pull, 0.0)))
    depth = config.lock_control == "depth"
    stroke = config.H if config.closure is None else config.closure
    phases = (Phase("close", [hold], cm.n_steps("ds_close", stroke, config.ds_close)),
              Phase("lock", [hold], config.n_lock),
              Phase("draw", [pull], cm.n_steps("dU", config.U_pull, config.dU)))

    mu = config.mu if config.mu > 0 else 0.0
    # The die is set `clearance` above the sheet (along its e_q = (0, -1)) and held there (module doc).
    fixed = (Move(-config.clearance, -config.clearance), Move(0.0, 0.0), Move(0.0, 0.0))
    draw = Force(config.F_clamp, start=config.F_clamp) if config.lock_control == "force" else Move(0.0, 0.0)
    lock = Move(0.0, 0.0) if depth else Force(config.F_clamp)  # 'depth': held at the closure, no lock force
    law = cm.friction_law(config) if mu > 0 else None
    tools = (RigidTool("upper", _upper_die(config, x_g, groove["alpha"]), (0.0, -1.0), mesh.top, fixed, mu,
                       frictional=mu > 0, friction=law),
             RigidTool("lower", _lower_tool(config, x_far), (0.0, 1.0), mesh.bottom,
                       (Move(0.0, stroke), lock, draw), mu, frictional=mu > 0, friction=law))

    eps_t = cm.resolve_eps_t(config, config.mu)
    law = formulation(algorithm, config.eps_n, eps_t, config.target_gap, config.band, config.smoothing,
                      config.max_augmentations, stiff_above=cm.stiff_penalty(config),
                      search=config.lemke_search, exact_start=config.exact_start)
    material = cm.material(config)
    model = StripModel(mesh, material, phases, tools=cm.preselected(tools, mesh, config.preselect),
                       contact=law, formulation=config.element,
                       thickness_points=config.thickness_points,
                       enhanced_update=config.enhanced_update,
                       phase_seconds=cm.phase_seconds(config, phases, config.U_pull))
    observe = BlankholderObserve(right=tuple(int(a) for a in mesh.right), tail=int(mesh.node_index(0, 0)),
                                 U_pull=float(config.U_pull), x_g=float(x_g), L=float(config.L))

    parameters = {
        "variant": variant,
        "config": cm.config_dict(config),
        "geometry": {"H": config.H, "R": config.R, "r": config.r, "Rp": config.Rp, "L": config.L,
                     "t": config.t, "r_e": config.r_e, "clearance": config.clearance, "x_g": x_g,
                     "T_R": list(groove["T_R"]),
                     "T_L": [-groove["T_R"][0], groove["T_R"][1]], "x_left": x_left, "x_right": x_right,
                     "X_far": x_far, "U_pull": config.U_pull},
        "material": cm.material_dict(config),
        "friction": cm.friction_table(TOOLS, PHASES, [(config.mu,) * 3, (config.mu,) * 3]),
        "contact": {"algorithm": algorithm, "eps_n": config.eps_n, "eps_t": eps_t,
                    "target_gap": config.target_gap if algorithm == "auglag" else None,
                    "max_augmentations": config.max_augmentations if algorithm == "auglag" else None,
                    "d_capture": config.d_capture},
        "mesh": {"nx": nx, "ny": config.ny},
        "schedule": [
            cm.schedule_entry(phases[0], "displacement of the lower tool", "s", "mm", 0.0, stroke),
            (cm.schedule_entry(phases[1], "displacement of the lower tool (held)", "s", "mm", stroke, stroke)
             if depth else
             {**cm.schedule_entry(phases[1], "force on the lower tool", "P", "N/mm", None, config.F_clamp),
              "start": "reaction at the end of close"}),
            {**cm.schedule_entry(phases[2], "displacement of the right end", "U", "mm", 0.0, config.U_pull),
             "lower": {"force": "force-driven, P = F_clamp", "position": "held where the lock left it",
                       "depth": f"held at s = {stroke:g}"}[config.lock_control]},
        ],
    }
    return Scene(
        name=NAME, variant=variant, algorithm=algorithm, config=config, model=model, observe=observe,
        snapshot=cm.ContactSnapshot(),
        control=cm.step_control(phases, config.max_steps, config.stabilize, config.step_error,
                                     config.stall_steps),
        phase_names=PHASES, tool_names=TOOLS, clamping_tool=1, instants=INSTANTS,
        steady_window=tuple(float(v) for v in config.steady_window),
        roi=(-(x_g + 10.0), x_g + 10.0, -3.0, config.H + 5.0), y_scale=1.0, parameters=parameters,
        newton=NewtonOptions(max_iterations=config.newton_iterations))
