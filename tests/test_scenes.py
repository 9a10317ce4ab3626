"""The four benchmark scenes (benchmarks spec sections 2-6): registry, configs, geometry of the spec,
validation, and one short run per scene at a coarse mesh with a physical check."""

import dataclasses
import json
import math

import jax.numpy as jnp
import numpy as np
import pytest

from jaxfric.contact.formulations import ExactStartPenalty, Penalty
from jaxfric.contact.rigid import pair_nodes
from jaxfric.contact.tools import project
from jaxfric.fem.loading import schedule
from jaxfric.loadpath.run import run
from jaxfric.numerics.results import Result
from jaxfric.scenes import (
    ALGORITHMS,
    bead,
    blankholder,
    config_fields,
    flat_die,
    make,
    nine,
    parse_mesh,
    parse_override,
    scene_names,
    variants,
)

SPEC_VARIANTS = {
    "flat_die": ("const_force", "const_position"),
    "bead": ("th045_mu000", "th090_mu000", "th135_mu000", "th045_mu017", "th090_mu017", "th135_mu017"),
    "nine": ("mu000", "mu017"),
    "blankholder": tuple(f"shape{k}" for k in range(1, 10)),
}
SPEC_TOOLS = {"flat_die": ("die",), "bead": ("die_up", "die_lo", "roller"), "nine": ("A", "B", "C", "D", "E"),
              "blankholder": ("upper", "lower")}
# The tools each scene builds by default: the spec's, then the Nine's entry guide (config entry_guide).
TOOLS = {**SPEC_TOOLS, "nine": SPEC_TOOLS["nine"] + ("guide_top", "guide_bottom")}
SPEC_PHASES = {"flat_die": ("clamp", "draw"), "bead": ("clamp", "wind", "draw"), "nine": ("clamp", "draw"),
               "blankholder": ("close", "lock", "draw")}
REQUIRED = ("drawing_displacement", "drawing_force", "clamping_force", "tool_position", "max_penetration",
            "n_active", "n_slip")
EXTRA = {"flat_die": ("sum_ft", "mu_sum_fn", "n_candidates"),
         "bead": ("theta_deg", "jaw_fx", "jaw_fy", "roller_fx", "roller_fy", "clamp_ft", "tail_x"),
         "nine": ("bead_fx", "tail_x", "cyl_a_fx", "cyl_a_fy", "cyl_c_fx", "cyl_c_fy", "cyl_d_fy", "cyl_e_fy",
                  "guide_top_fy", "guide_bottom_fy"),
         "blankholder": ("upper_fx", "upper_fy", "lower_fx", "n_land_closed", "tail_x")}
SNAPSHOT_KEYS = {"x", "eqps", "rn", "rt", "gap", "normal", "status", "mu", "tool_offset"}
# A coarse mesh per scene: every variant then has the same array shapes, so building the whole
# variant x algorithm matrix reuses the (eager) placement checks compiled for the first one.
COARSE = {"flat_die": {"mesh": "24x2"}, "bead": {"mesh": "50x2"}, "nine": {"mesh": "30x2"},
          "blankholder": {"nx": 40}}


# ---- registry, variants, configs ---------------------------------------------------------------

def test_registry_names_and_variants():
    assert scene_names() == tuple(SPEC_VARIANTS)
    for name, expected in SPEC_VARIANTS.items():
        assert variants(name) == expected


@pytest.mark.parametrize("name", list(SPEC_VARIANTS))
def test_config_fields_carry_units_and_docs(name):
    fields = config_fields(name)
    names = [f[0] for f in fields]
    for key in ("E", "nu", "sigma_y", "A", "n", "eps_n", "eps_t", "target_gap", "d_capture", "mu"
                if name != "bead" else "mu_clamp"):
        assert key in names
    assert all(unit and doc for _, _, unit, doc in fields)


@pytest.mark.parametrize("name", list(SPEC_VARIANTS))
def test_every_variant_builds_with_every_algorithm(name):
    for variant in SPEC_VARIANTS[name]:
        for algorithm in ALGORITHMS:
            scene = make(name, variant, algorithm, COARSE[name])
            assert (scene.name, scene.variant, scene.algorithm) == (name, variant, algorithm)
            assert scene.tool_names == TOOLS[name] == tuple(t.name for t in scene.model.tools)
            assert scene.phase_names == SPEC_PHASES[name] == tuple(p.name for p in scene.model.phases)
            params = json.loads(json.dumps(scene.parameters))  # JSON-ready
            assert params["contact"]["target_gap"] == (scene.config.target_gap if algorithm == "auglag" else None)
            assert set(params["material"]) == {"E", "nu", "sigma_y", "A", "n"}
            assert set(params["friction"]) == set(TOOLS[name])
            assert params["mesh"] == {"nx": scene.model.mesh.nx, "ny": scene.model.mesh.ny}
            assert [p["name"] for p in params["schedule"]] == list(SPEC_PHASES[name])
            assert params["variant"] == variant
            assert hash(scene.observe) == hash(scene.observe)


def test_equal_scenes_share_observe():
    a, b = make("nine", "mu017", "penalty", COARSE["nine"]), make("nine", "mu017", "auglag", COARSE["nine"])
    assert a.observe == b.observe and hash(a.observe) == hash(b.observe)
    assert a.snapshot == b.snapshot


def test_default_variants_and_spec_defaults():
    # Spec meshes (the builds below use coarse ones: building is dominated by eager checks per shape).
    assert (nine.NineConfig().nx, nine.NineConfig().ny) == (300, 3)
    assert (flat_die.FlatDieConfig().nx, flat_die.FlatDieConfig().ny) == (240, 2)
    assert (bead.BeadConfig().nx, bead.BeadConfig().ny) == (725, 4)
    assert blankholder.BlankholderConfig().nx is None and blankholder.BlankholderConfig().ny == 2
    scene = make("nine", overrides=COARSE["nine"])
    assert scene.variant == "mu017"
    assert scene.parameters["contact"]["eps_t"] == pytest.approx(0.17 * 1e5)
    assert [t.frictional for t in scene.model.tools] == [True, True, True, False, False, False, False]
    assert make("nine", overrides={**COARSE["nine"], "entry_guide": False}).tool_names == SPEC_TOOLS["nine"]
    # 110 clamp steps of 0.1 mm, 700 draw steps of 0.1 mm.
    assert [p.increments for p in scene.model.phases] == [((1.0, 110),), ((1.0, 700),)]
    assert scene.steady_window == (20.0, 35.0)
    frictionless = make("nine", "mu000", overrides=COARSE["nine"])
    assert frictionless.parameters["contact"]["eps_t"] == 0.0
    assert not any(t.frictional for t in frictionless.model.tools)

    die = make("flat_die", overrides=COARSE["flat_die"])
    assert die.variant == "const_force" and die.y_scale == 20.0
    assert die.parameters["contact"]["eps_t"] == pytest.approx(1.5e8)
    # Draw: 100 steps of 2.5e-5 mm to U = 0.0025 mm, then 275 of 1e-4 mm.
    assert die.model.phases[1].increments == ((0.0025 / 0.03, 100), (1.0, 275))
    assert die.parameters["friction"] == {"die": {"clamp": 0.0, "draw": 0.15}}

    b = make("bead", overrides=COARSE["bead"])
    assert b.variant == "th090_mu017"
    assert [p.increments[0][1] for p in b.model.phases] == [10, 180, 160]
    h = make("blankholder", overrides=COARSE["blankholder"])
    assert h.variant == "shape1"
    # 120 close steps of 0.05 mm, 10 lock steps, 550 draw steps of 0.1 mm.
    assert [p.increments[0][1] for p in h.model.phases] == [120, 10, 550]


def test_overrides_are_applied_after_the_variant():
    scene = make("nine", "mu000", overrides={"mesh": "30x2", "U_draw": "40", "mu": "0.1", "eps_t": "none"})
    assert (scene.model.mesh.nx, scene.model.mesh.ny) == (30, 2)
    assert scene.config.U_draw == 40.0 and scene.config.mu == 0.1 and scene.config.eps_t is None
    assert scene.model.phases[1].increments == ((1.0, 400),)
    assert make("nine", overrides={**COARSE["nine"], "steady_window": "10, 20"}).steady_window == (10.0, 20.0)
    die = make("flat_die", overrides={**COARSE["flat_die"], "draw_control": "position"})
    assert type(die.model.tools[0].controls[1]).__name__ == "Move"


def test_parse_helpers():
    assert parse_mesh("300x3") == (300, 3) and parse_mesh("150X6") == (150, 6)
    assert parse_override("nine", "nx", "600") == 600
    assert parse_override("nine", "eps_n", "1e4") == 1e4
    assert parse_override("blankholder", "nx", "None") is None
    assert parse_override("nine", "mesh", "30x2") == (30, 2)  # the command line's --mesh and --set mesh=
    for bad in ("300", "ax3", "0x3", "300x3x2"):
        with pytest.raises(ValueError, match="mesh"):
            parse_mesh(bad)
        with pytest.raises(ValueError, match="'mesh'"):
            parse_override("nine", "mesh", bad)
    with pytest.raises(ValueError, match="'eps_n'"):
        parse_override("nine", "eps_n", "stiff")
    with pytest.raises(ValueError, match="'nx'"):
        parse_override("nine", "nx", "3.5")
    with pytest.raises(ValueError, match="'radius'"):
        parse_override("nine", "radius", "3")
    with pytest.raises(ValueError, match="'radius'"):
        make("nine", overrides={"radius": 3.0})


@pytest.mark.parametrize("name, field, value", [
    ("nine", "t", -0.97), ("nine", "nu", 0.5), ("nine", "mu", -0.1), ("nine", "nx", 0), ("nine", "E", 0.0),
    ("nine", "eps_n", -1.0), ("nine", "eps_t", -1.0), ("nine", "target_gap", 0.0), ("nine", "R1", 0.0),
    ("flat_die", "h", 0.0), ("flat_die", "draw_control", "wobble"), ("flat_die", "F_clamp", -50.0),
    ("bead", "mu_roller", -0.17), ("bead", "theta", 200.0), ("bead", "d_capture", 0.0),
    ("blankholder", "R", 7.0), ("blankholder", "lock_control", "maybe"), ("blankholder", "mu", -1.0),
    ("blankholder", "sigma_y", float("nan")),
])
def test_bad_field_values_name_the_field(name, field, value):
    with pytest.raises(ValueError, match=f"'{field}'"):
        make(name, overrides={field: value})


def test_unknown_identifiers():
    with pytest.raises(ValueError, match="scene"):
        make("drawbead")
    with pytest.raises(ValueError, match="variant"):
        make("nine", "mu020")
    with pytest.raises(ValueError, match="algorithm"):
        make("nine", algorithm="lagrange")
    with pytest.raises(ValueError, match="variant"):
        nine.build(nine.NineConfig(), "penalty", "shape1")


# ---- geometry of the spec ---------------------------------------------------------------------

def _gaps(tool, points, offset=(0.0, 0.0)):
    off = jnp.asarray(offset, jnp.float64)
    return np.array([float(project(tool.geometry, jnp.asarray(p, jnp.float64), off).gap) for p in points])


def test_nine_geometry():
    scene = make("nine", overrides=COARSE["nine"])
    tools = {t.name: t for t in scene.model.tools}
    circles = {k: tools[k].geometry.primitives[0] for k in nine.TOOLS}
    centre = {k: np.asarray(c.centre) for k, c in circles.items()}
    radius = {k: float(c.radius) for k, c in circles.items()}
    t = 0.97
    # Table 3 read as in the spec: A at the origin's foot, pitch L1 = 2 R1 + e, then L2, L3.
    np.testing.assert_allclose(centre["A"], [0.0, -5.5], atol=1e-12)
    np.testing.assert_allclose(centre["B"], [11.97, 6.47], atol=1e-12)
    np.testing.assert_allclose(centre["C"], [23.94, -5.5], atol=1e-12)
    np.testing.assert_allclose(centre["D"], [26.57, 3.84], atol=1e-12)
    np.testing.assert_allclose(centre["E"], [39.00, -2.87], atol=1e-12)
    assert radius == {"A": 5.5, "B": 5.5, "C": 5.5, "D": 2.87, "E": 2.87}
    # B's bottom tangent to the strip top, A's (and C's, E's) top tangent to the strip bottom, D's
    # bottom tangent to the strip top: zero gap at the tangency points.
    assert abs(centre["B"][1] - radius["B"] - t) < 1e-12 and abs(centre["D"][1] - radius["D"] - t) < 1e-12
    for k in ("A", "C", "E"):
        assert abs(centre[k][1] + radius[k]) < 1e-12
    np.testing.assert_allclose(_gaps(tools["B"], [[11.97, t]]), 0.0, atol=1e-12)
    np.testing.assert_allclose(_gaps(tools["A"], [[0.0, 0.0]]), 0.0, atol=1e-12)
    # Candidates: bottom surface vs A, C, E; top surface vs B, D, less the pulled end's corner (held in
    # both directions). B is driven down by the stroke.
    mesh = scene.model.mesh
    for k in ("A", "C", "E"):
        assert tools[k].candidates == tuple(int(a) for a in mesh.bottom if a not in mesh.right)
    for k in ("B", "D"):
        assert tools[k].candidates == tuple(int(a) for a in mesh.top if a not in mesh.right)
    np.testing.assert_array_equal(np.asarray(tools["B"].drive), [0.0, -1.0])
    assert float(tools["B"].controls[0].end) == 11.0 and float(tools["B"].controls[1].end) == 0.0
    assert scene.clamping_tool == 1 and scene.instants == ("clamped", "steady", "final")


def test_flat_die_geometry():
    scene = make("flat_die", "const_position", overrides=COARSE["flat_die"])
    (die,) = scene.model.tools
    mesh = scene.model.mesh
    assert die.candidates == tuple(int(a) for a in mesh.top)
    X = np.asarray(mesh.nodes)
    assert np.allclose(X[die.candidates[0]], [0.0, 0.395]) and np.allclose(X[die.candidates[-1]], [48.0, 0.395])
    np.testing.assert_allclose(_gaps(die, X[list(die.candidates)]), 0.0, atol=1e-15)  # touching AD
    seg = die.geometry.primitives[0]
    np.testing.assert_allclose([np.asarray(seg.start), np.asarray(seg.end)], [[-2.0, 0.395], [50.0, 0.395]])
    assert type(die.controls[1]).__name__ == "Move"          # const_position: frozen die
    assert type(make("flat_die", overrides=COARSE["flat_die"]).model.tools[0].controls[1]).__name__ == "Force"
    # BCs: v = 0 on the bottom in both phases; DC held in x during clamp, pulled during draw.
    clamp, draw = scene.model.phases
    assert {(bc.nodes, bc.components) for bc in clamp.bcs} == {
        (tuple(int(a) for a in mesh.bottom), (1,)), (tuple(int(a) for a in mesh.right), (0,))}
    assert scene.roi[:2] == (-1.0, 49.0)


def test_bead_geometry():
    scene = make("bead", "th135_mu000", overrides=COARSE["bead"])
    mesh = scene.model.mesh
    X = np.asarray(mesh.nodes)
    jaw = bead.jaw_nodes(mesh, 80.0)
    assert np.all(X[jaw, 0] >= 80.0 - 1e-9) and np.all(X[np.setdiff1d(np.arange(len(X)), jaw), 0] < 80.0)
    columns = np.unique(np.round(X[:, 0], 9))
    assert jaw.size == np.sum(columns >= 80.0 - 1e-9) * (mesh.ny + 1)
    for phase in scene.model.phases:
        (bc,) = phase.bcs
        assert bc.nodes == tuple(int(a) for a in jaw) and bc.components == (0, 1)
    # Winding by 135 deg clockwise about O = (0, -5): a jaw node at (80, 0) goes to O + Q (X - O).
    wind = scene.model.phases[1].bcs[0].motion
    x = np.asarray(wind(jnp.array([[80.0, 0.0]]), 1.0))[0] + [80.0, 0.0]
    th = math.radians(135.0)
    rotation = np.array([[math.cos(th), math.sin(th)], [-math.sin(th), math.cos(th)]])
    expected = np.array([0.0, -5.0]) + rotation @ [80.0, 5.0]
    np.testing.assert_allclose(x, expected, atol=1e-12)
    draw = scene.model.phases[2].bcs[0].motion
    shift = np.asarray(draw(jnp.array([[80.0, 0.0]]), 1.0))[0] - np.asarray(wind(jnp.array([[80.0, 0.0]]), 1.0))[0]
    np.testing.assert_allclose(shift, 8.0 * np.array([math.cos(th), -math.sin(th)]), atol=1e-12)
    up, lo, roller = scene.model.tools
    # The strip bottom is tangent to the roller at x = 0; the clamp flats touch the strip on [-90, -40].
    np.testing.assert_allclose(_gaps(roller, [[0.0, 0.0]]), 0.0, atol=1e-12)
    np.testing.assert_allclose(_gaps(up, [[-90.0, 1.5], [-65.0, 1.5], [-40.0, 1.5]]), 0.0, atol=1e-12)
    np.testing.assert_allclose(_gaps(lo, [[-90.0, 0.0], [-40.0, 0.0]]), 0.0, atol=1e-12)
    assert not roller.frictional and up.frictional and lo.frictional
    assert type(up.controls[0]).__name__ == "Force" and float(up.controls[0].start) == 0.0
    assert scene.parameters["contact"]["eps_t"] == pytest.approx(0.17e5)


TABLE7 = {  # x_g, T_R, x_left, x_right, nx
    1: (9.801, (6.933, 3.122), -109.801, 44.801, 309), 2: (9.801, (6.933, 3.122), -134.801, 69.801, 409),
    3: (13.994, (9.710, 4.122), -113.994, 48.994, 326), 4: (13.994, (9.710, 4.122), -138.994, 73.994, 426),
    5: (13.994, (9.710, 4.122), -113.994, 48.994, 326), 6: (18.238, (12.539, 5.125), -118.238, 53.238, 343),
    7: (18.238, (12.539, 5.125), -143.238, 78.238, 443), 8: (18.238, (12.539, 5.125), -118.238, 53.238, 343),
    9: (18.238, (12.539, 5.125), -118.238, 53.238, 343),
}


@pytest.mark.parametrize("shape", range(1, 10))
def test_blankholder_table7(shape):
    config = blankholder.BlankholderConfig(**blankholder.VARIANTS[f"shape{shape}"])
    x_g, T_R, x_left, x_right, nx = TABLE7[shape]
    g = blankholder.groove_geometry(config)
    assert abs(g["x_g"] - x_g) < 1e-3
    np.testing.assert_allclose(g["T_R"], T_R, atol=1e-3)
    extent = blankholder.sheet_extent(config)
    np.testing.assert_allclose(extent[:2], (x_left, x_right), atol=1e-3)
    assert extent[2] == nx
    # The upper die's chain is connected (checked at construction) and its fillets meet the groove at T.
    upper = blankholder._upper_die(config, g["x_g"], g["alpha"])
    groove = upper.primitives[3]
    end = np.asarray(groove.centre) + float(groove.radius) * np.array([math.cos(float(groove.angle_end)),
                                                                       math.sin(float(groove.angle_end))])
    np.testing.assert_allclose(end, g["T_R"], atol=1e-12)


def test_blankholder_tools_at_rest():
    scene = make("blankholder", "shape6", overrides=COARSE["blankholder"])
    upper, lower = scene.model.tools
    t, H = 1.0, 12.0
    # The nose top touches the sheet bottom at x = 0, the lands touch the sheet top, lower lands H below.
    np.testing.assert_allclose(_gaps(lower, [[0.0, 0.0]]), 0.0, atol=1e-12)
    np.testing.assert_allclose(_gaps(lower, [[-50.0, 0.0], [40.0, 0.0]]), H, atol=1e-12)
    np.testing.assert_allclose(_gaps(upper, [[-30.0, t], [30.0, t]]), 0.0, atol=1e-12)
    # Closure s = H: the lower lands reach y = 0; flanks exist since H > R.
    np.testing.assert_allclose(_gaps(lower, [[-50.0, 0.0]], offset=(0.0, H)), 0.0, atol=1e-12)
    # Downstream the lower land ends under the upper land's edge, x_g + L = 43.238, in an edge arc of
    # r_e = 2 mm (centre 2 mm below the land's end): a point on the land's line 1 mm beyond the end is
    # sqrt(5) - 2 from the arc; the spec's land ("far") goes on.
    end = blankholder.groove_geometry(scene.config)["x_g"] + 25.0
    np.testing.assert_allclose(_gaps(lower, [[end + 1.0, 0.0]], offset=(0.0, H)), math.sqrt(5.0) - 2.0, atol=1e-12)
    far = make("blankholder", "shape6", overrides={**COARSE["blankholder"], "downstream_land": "far"})
    np.testing.assert_allclose(_gaps(far.model.tools[1], [[50.0, 0.0]], offset=(0.0, H)), 0.0, atol=1e-12)
    assert len(lower.geometry.primitives) == 6 and len(far.model.tools[1].geometry.primitives) == 5
    assert len(make("blankholder", "shape9", overrides=COARSE["blankholder"]).model.tools[1].geometry.primitives) == 4
    assert float(lower.controls[0].end) == H and lower.controls[1].start is None
    assert scene.roi == pytest.approx((-28.238, 28.238, -3.0, 17.0), abs=1e-3)


# ---- short runs at a coarse mesh ----------------------------------------------------------------

def _run(scene):
    result = run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                 snapshot=scene.snapshot, progress=False)
    h = result.history
    for key in REQUIRED + EXTRA[scene.name]:
        assert key in h and np.all(np.isfinite(h[key])), key
    assert np.all(h["n_slip"] <= h["n_active"]) and np.all(h["max_penetration"] >= 0)
    last = max(result.snapshots)
    snap = result.snapshots[last]
    assert set(snap) == SNAPSHOT_KEYS
    m = len(pair_nodes(scene.model.tools))
    assert snap["rn"].shape == (m,) and snap["normal"].shape == (m, 2) and snap["status"].dtype == np.int8
    assert snap["tool_offset"].shape == (len(scene.tool_names), 2)
    assert snap["eqps"].shape == (scene.model.mesh.n_elements,)
    # contact.npz consistency (outputs spec 4): clamping force and counts from the pair arrays.
    f = snap["rn"][:, None] * snap["normal"] + snap["rt"][:, None] * np.stack(
        [-snap["normal"][:, 1], snap["normal"][:, 0]], 1)
    sizes = np.cumsum([0] + [len(t.candidates) for t in scene.model.tools])
    k = scene.clamping_tool
    e_q = np.asarray(scene.model.tools[k].drive)
    np.testing.assert_allclose(np.sum(f[sizes[k]:sizes[k + 1]] @ e_q), h["clamping_force"][last],
                               rtol=1e-6, atol=1e-9)
    assert np.sum(snap["status"] > 0) == h["n_active"][last] and np.sum(snap["status"] == 2) == h["n_slip"][last]
    assert np.all(snap["gap"] <= 1e30) and np.all(np.isfinite(snap["gap"]))
    return result, h


def test_flat_die_short_run():
    """Clamp to F_clamp (force balance of the force-driven die), then pull until the whole top slides:
    global Coulomb sliding gives drawing force = sum_ft = mu F_clamp."""
    scene = make("flat_die", "const_force", overrides={
        "mesh": "24x2", "L": 4.8, "U_draw": 0.006, "U_fine": 0.001, "dU_fine": 1e-4, "dU": 1e-3, "n_clamp": 2})
    result, h = _run(scene)
    assert result.converged
    clamp = h["phase_name"] == "clamp"
    end_clamp = np.flatnonzero(clamp)[-1]
    assert abs(h["clamping_force"][end_clamp] - 50.0) <= 1e-8 * 50.0
    assert np.all(h["drawing_displacement"][clamp] == 0.0) and h["drawing_displacement"][-1] == pytest.approx(0.006)
    assert h["n_active"][-1] == h["n_slip"][-1] == h["n_candidates"][-1] == 25
    np.testing.assert_allclose([h["drawing_force"][-1], h["sum_ft"][-1]], 0.15 * 50.0, rtol=1e-6)
    np.testing.assert_allclose(h["mu_sum_fn"][-1], 0.15 * 50.0, rtol=1e-8)
    assert np.all(result.snapshots[end_clamp]["mu"] == 0.0)
    assert np.all(result.snapshots[len(h["time"]) - 1]["mu"] == 0.15)


def test_smoothing_field_selects_the_smoothed_law():
    assert make("flat_die", "const_force", overrides={"smoothing": 0.5}).model.contact.smooth
    law = make("nine", "mu017", "auglag", overrides={"mesh": "30x2", "smoothing": 2.0}).model.contact
    assert law.smooth and float(law.smoothing) == 2.0 and float(law.target_gap) == 1e-5
    assert not make("bead", None, "penalty", overrides={"mesh": "50x2"}).model.contact.smooth


@pytest.mark.parametrize("scene", ["flat_die", "bead", "nine", "blankholder"])
def test_max_augmentations_field_reaches_the_law(scene):
    """Every scene's ``max_augmentations`` (default: the spec's 20) is the AL law's limit per step."""
    assert make(scene, None, "auglag").model.contact.max_augmentations == 20
    law = make(scene, None, "auglag", overrides={"max_augmentations": 60}).model.contact
    assert law.max_augmentations == 60


@pytest.mark.parametrize("scene", ["flat_die", "bead", "nine", "blankholder"])
def test_solver_fields_reach_the_law(scene):
    """Every scene's ``lemke_search`` (default True) is lcp_lemke's line search; lcp_ssn has its own.
    Its ``exact_start`` (default False) makes the penalty law ExactStartPenalty and starts the augmented
    Lagrangian from exact contact; exact contact ignores it."""
    assert make(scene, None, "lcp_lemke").model.contact.search is True
    assert make(scene, None, "lcp_lemke", overrides={"lemke_search": False}).model.contact.search is False
    assert make(scene, None, "lcp_ssn", overrides={"lemke_search": False}).model.contact.solver == "ssn"
    assert type(make(scene, None, "penalty").model.contact) is Penalty
    assert type(make(scene, None, "penalty", overrides={"exact_start": True}).model.contact) is ExactStartPenalty
    assert make(scene, None, "auglag", overrides={"exact_start": True}).model.contact.exact_start is True
    assert make(scene, None, "lcp_ssn", overrides={"exact_start": True}).model.contact.solver == "ssn"


@pytest.mark.parametrize("scene", ["flat_die", "nine"])
def test_max_steps_field_sizes_the_history_buffer(scene):
    """``max_steps`` None: 10x the nominal steps + 200 rows; a number: that many."""
    built = make(scene, None)
    assert built.control.max_steps == 10 * schedule(built.model.phases).n_nominal_steps + 200
    assert make(scene, None, overrides={"max_steps": 30_000}).control.max_steps == 30_000


@pytest.mark.slow  # a flat-die run of its own compilation (12 s)
def test_smoothed_contact_law_through_the_scene_config():
    """``smoothing`` = S selects the smoothed penalty law (contact.laws): the die still balances
    F_clamp, and at full sliding the drawing force stays within the law's bound of mu F_clamp,
    n_pairs (1 + mu) S log 2 (the smooth clip approaches the Coulomb limit from below; the lower end
    allows the Newton tolerance)."""
    s = 0.01
    scene = make("flat_die", "const_force", overrides={
        "mesh": "24x2", "L": 4.8, "U_draw": 0.006, "U_fine": 0.001, "dU_fine": 1e-4, "dU": 1e-3, "n_clamp": 2,
        "smoothing": s})
    assert scene.model.contact.smooth and float(scene.model.contact.smoothing) == s
    assert not make("flat_die", "const_force", overrides={"mesh": "24x2"}).model.contact.smooth
    result, h = _run(scene)
    assert result.converged
    end_clamp = np.flatnonzero(h["phase_name"] == "clamp")[-1]
    assert abs(h["clamping_force"][end_clamp] - 50.0) <= 1e-8 * 50.0
    bound = 25 * (1 + 0.15) * s * math.log(2)
    # (here every pair slips far beyond the limit, where the smooth clip is exponentially close to it)
    assert -1e-8 * 7.5 <= 0.15 * 50.0 - h["drawing_force"][-1] <= bound


def test_nine_entry_guide_kinds():
    """The channel (default): two fixed frictionless faces clear of the undeformed strip by
    guide_clearance, ending at guide_end, whose candidates are the surface nodes that can reach the exit
    lip, and no constraint on the left end; ``end_nodes``: v = 0 on the left-end nodes in both phases
    and no guide tools; entry_guide off: neither."""

    scene = make("nine", overrides=COARSE["nine"])
    config, mesh = scene.config, scene.model.mesh
    guide = scene.model.tools[len(nine.TOOLS):]
    assert tuple(t.name for t in guide) == nine.GUIDE_TOOLS
    assert all(not t.frictional and np.all(np.asarray(t.mu) == 0.0) for t in guide)
    assert not any(bc.nodes == tuple(mesh.left) for p in scene.model.phases for bc in p.bcs)
    nodes = np.asarray(mesh.nodes)
    for tool, surface in zip(guide, (mesh.top, mesh.bottom)):
        reach = [int(a) for a in surface if nodes[a, 0] <= config.guide_end + config.guide_lip]
        assert list(tool.candidates) == reach and len(reach) < len(surface)
        gaps = _gaps(tool, nodes[reach])
        inside = (nodes[reach, 0] >= config.guide_end - config.guide_length) & (nodes[reach, 0] <= config.guide_end)
        assert np.any(inside)
        np.testing.assert_allclose(gaps[inside], config.guide_clearance, rtol=1e-9)
        assert np.all(gaps >= config.guide_clearance * (1 - 1e-9))
    end_nodes = make("nine", overrides={**COARSE["nine"], "entry_guide_kind": "end_nodes"})
    assert end_nodes.tool_names == SPEC_TOOLS["nine"]
    for phase in end_nodes.model.phases:
        assert [bc.components for bc in phase.bcs if bc.nodes == tuple(mesh.left)] == [(1,)]
    free = make("nine", overrides={**COARSE["nine"], "entry_guide": False})
    assert free.tool_names == SPEC_TOOLS["nine"]
    assert not any(bc.nodes == tuple(mesh.left) for p in free.model.phases for bc in p.bcs)
    with pytest.raises(ValueError, match="'guide_end'"):
        make("nine", overrides={**COARSE["nine"], "guide_end": 1.0})
    make("nine", overrides={**COARSE["nine"], "guide_end": 1.0, "entry_guide": False})  # no channel: unused


def test_nine_short_run():
    """B pushed 3 mm down between A and C, then the strip pulled 1 mm: B presses on the strip and the
    grip must pull, the cylinders' forces balance the reactions."""
    scene = make("nine", "mu017", overrides={"mesh": "60x2", "stroke": 3.0, "dq_clamp": 0.5, "U_draw": 1.0,
                                             "dU": 0.25})
    result, h = _run(scene)
    assert result.converged
    draw = h["phase_name"] == "draw"
    assert np.all(h["clamping_force"][1:] > 0) and np.all(h["drawing_force"][draw] > 0)
    assert h["tool_position"][-1] == pytest.approx(3.0)
    assert h["tail_x"][-1] > -50.0  # the strip is drawn in from its free end
    # Equilibrium of the strip in x: the grip's pull is balanced by the cylinders' forces.
    snap = result.snapshots[len(h["time"]) - 1]
    fx = snap["rn"] * snap["normal"][:, 0] - snap["rt"] * snap["normal"][:, 1]
    np.testing.assert_allclose(h["drawing_force"][-1], -np.sum(fx), rtol=1e-6)
    sizes = np.cumsum([0] + [len(t.candidates) for t in scene.model.tools])
    np.testing.assert_allclose([np.sum(fx[sizes[1]:sizes[2]]), np.sum(fx[:sizes[1]])],
                               [h["bead_fx"][-1], h["cyl_a_fx"][-1]], rtol=1e-9, atol=1e-12)


def test_strokes_and_increments_are_data_of_one_program():
    """The short Nine run again with another stroke of B, a longer pull and other increments (and with them
    another history buffer): the nominal increments, the strokes and ``max_steps`` are data, so the run
    finds the first one's compiled program (a compilation takes seconds, a hit about a millisecond), and
    draws to the new stroke in the new increments."""
    overrides = {"mesh": "60x2", "stroke": 3.0, "dq_clamp": 0.5, "U_draw": 1.0, "dU": 0.25}
    first, h0 = _run(make("nine", "mu017", overrides=overrides))
    longer = make("nine", "mu017", overrides={**overrides, "stroke": 3.5, "dq_clamp": 0.25, "U_draw": 1.5, "dU": 0.05})
    result, h = _run(longer)
    assert result.converged and result.compile_s < 0.05
    assert h["drawing_displacement"][-1] == 1.5 and h["tool_position"][-1] == pytest.approx(3.5)
    # The controller never exceeds the nominal increment: the new one, 0.05 mm, was the program's.
    largest = [np.max(np.diff(x["drawing_displacement"][x["phase_name"] == "draw"])) for x in (h0, h)]
    assert largest[1] <= 0.05 * (1 + 1e-12) < largest[0]


@pytest.mark.slow
def test_bead_short_run():
    """Clamp, wind by 10 deg, draw 0.5 mm on a coarse strip. Frictionless clamp: with the spec's
    mu_clamp = 0.17 the first clamp step does not converge with the current Newton solver (reported).
    Checks: force balance of the force-driven die, the jaw's motion, and zero moment of the forces of
    the frictionless roller about its centre (spec section 8). Slow: about 30 s of compilation."""
    scene = make("bead", "th090_mu000", overrides={
        "mesh": "100x2", "theta": 10.0, "dtheta": 2.5, "s_draw": 0.5, "ds": 0.25, "n_clamp": 2, "mu_clamp": 0.0})
    result, h = _run(scene)
    assert result.converged
    loaded = h["time"] >= 1.0
    np.testing.assert_allclose(h["clamping_force"][loaded], 600.0, rtol=1e-8)
    wind = h["phase_name"] == "wind"
    assert h["theta_deg"][wind][-1] == pytest.approx(10.0) and h["theta_deg"][-1] == pytest.approx(10.0)
    assert h["drawing_displacement"][-1] == pytest.approx(0.5)
    assert np.all(h["drawing_displacement"][~(h["phase_name"] == "draw")] == 0)
    assert h["tail_x"][-1] > -100.0
    snap = result.snapshots[len(h["time"]) - 1]
    n = len(scene.model.tools[0].candidates) + len(scene.model.tools[1].candidates)
    x = snap["x"][np.asarray(scene.model.tools[2].candidates)] - np.array([0.0, -5.0])
    f = snap["rn"][n:, None] * snap["normal"][n:]
    assert np.sum(snap["rn"][n:]) > 1.0
    assert abs(np.sum(x[:, 0] * f[:, 1] - x[:, 1] * f[:, 0])) < 1e-9 * 5.0 * np.sum(snap["rn"][n:])


@pytest.mark.slow
def test_blankholder_short_run():
    """Frictionless shape 1 on a coarse sheet: the lower tool closes, is locked at F_clamp (force balance
    of the force-driven tool) and holds it while the sheet is pulled 1 mm. Slow: the close phase needs
    a few hundred cut steps at this mesh (reported)."""
    scene = make("blankholder", "shape1", overrides={
        "element_length": 1.0, "ds_close": 0.25, "n_lock": 2, "U_pull": 1.0, "dU": 0.25, "mu": 0.0})
    result, h = _run(scene)
    assert result.converged
    close = h["phase_name"] == "close"
    assert h["tool_position"][close][-1] == pytest.approx(6.0)
    locked = h["time"] >= 2.0
    np.testing.assert_allclose(h["clamping_force"][locked], 300.0, rtol=1e-8)
    assert h["drawing_displacement"][-1] == pytest.approx(1.0)


@pytest.mark.xla_optimized   # mostly run time (tests/conftest.py)
def test_blankholder_starts_closing_at_the_spec_mesh():
    """Shape 1 at its spec mesh (309 x 2): the first 12 steps of 'close' converge, and the run then ends
    on its 12-row history buffer (MAX_STEPS), not on a Newton failure. Guards the first-step line
    search (jaxfric.contact.system.linearize, the prescribed-values test): counting the lower tool's row
    q - q_presc in that test stopped this run at step 4 of 'close'. Twelve steps, three times that; the
    whole close at this mesh, with exact contact, is run by the slow
    tests/test_exact.py::test_lemke_runs_the_blankholder_lock_and_agrees_with_semismooth_newton."""
    scene = make("blankholder", "shape1")
    control = dataclasses.replace(scene.control, max_steps=12)
    result = run(scene.model, newton=scene.newton, control=control, observe=scene.observe, progress=False,
                 raise_on_failure=False)
    assert result.code == Result.MAX_STEPS, result.message
    h = result.history
    assert np.all(h["phase_name"] == "close") and h["tool_position"][-1] > 0


def test_a_scene_on_another_mesh_compiles_no_new_placement_check():
    """StripModel checks that no tool cuts into the sheet at rest by projecting the candidates on each tool,
    in calls of a fixed number of points: the Nine and the bead on another mesh (other candidate counts)
    compile no new projection; a compilation takes about a second per tool structure."""
    from jaxfric.loadpath.model import _project_all
    for scene, variant, meshes in (("nine", "mu017", ("40x2", "90x3")), ("bead", "th090_mu000", ("100x2", "60x3"))):
        make(scene, variant, overrides={"mesh": meshes[0]})
        compiled = _project_all._cache_size()
        make(scene, variant, overrides={"mesh": meshes[1]})
        assert _project_all._cache_size() == compiled, scene
