"""Pair pre-selection (jaxfric.contact.preselection): the distance bound is a lower bound of the distance
to the tool; a run evaluating only the selected pairs gives the run evaluating every pair, step by step,
with exact contact and with the penalty law; a capacity too small for the contact zone stops the run
with PRESELECTION instead of missing a contact; and the scenes pre-select by default only where it leaves out
enough pairs to repay its compilation."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfric as jf
from jaxfric.contact.formulations import Complementarity
from jaxfric.contact.preselection import PAYS_FROM, distance_bound, tool_capacity
from jaxfric.contact.rigid import Move, RigidTool
from jaxfric.contact.tools import Arc, Segment, Tool
from jaxfric.loadpath.simulate import simulate
from jaxfric.numerics.results import Result, describe
from jaxfric.scenes import make
from models import STEEL

CONTROL = jf.StepControl(max_steps=400)


def _chain():
    """A land, a convex edge, a wall and a concave groove, sheet on the left of the walk (above the land)."""
    return Tool((Segment((-20.0, 0.0), (-6.0, 0.0)), Arc((-6.0, -2.0), 2.0, 0.5 * math.pi, 0.0),
                 Segment((-4.0, -2.0), (-4.0, -6.0)), Arc((0.0, -6.0), 4.0, math.pi, 2.0 * math.pi, concave=True)),
                "left")


@pytest.mark.parametrize("tool", [Tool.circle((0.0, 0.0), 5.5), _chain()], ids=["circle", "chain"])
def test_distance_bound_is_a_lower_bound_of_the_distance_to_the_tool(tool):
    rng = np.random.default_rng(7)
    # Points on the chain every 0.01 mm or closer: a distance to them is the distance to the chain within 5e-3.
    dense = np.concatenate([np.asarray(p.outline(4001)) if isinstance(p, Arc) else
                            np.asarray(p.start) + np.linspace(0, 1, 2001)[:, None] * np.asarray(p.end - p.start)
                            for p in tool.primitives])
    points = rng.uniform(-12.0, 12.0, size=(300, 2))
    bound = np.asarray(jax.vmap(lambda y: distance_bound(tool, y))(jnp.asarray(points)))
    true = np.min(np.linalg.norm(points[:, None, :] - dense[None, :, :], axis=-1), axis=1)
    assert np.all(bound <= true + 1e-9)
    if len(tool.primitives) == 1:   # a full circle: the bound is the distance (to the sampling's resolution)
        np.testing.assert_allclose(bound, true, atol=5e-3)


def _pressed_and_drawn(law, capacity, nx=120, mu=0.1):
    """A strip on a frictionless support (v = 0 on its bottom), indented 0.15 mm by a roller from above
    (its pairs evaluated on ``capacity`` candidates), then drawn 3 mm under it with the roller held."""
    length, t = 60.0, 1.0
    mesh = jf.strip_mesh(0.0, length, 0.0, t, nx, 2)
    roller = Tool.circle((20.0, t + 3.0), 3.0, seam=0.5 * math.pi)
    tool = RigidTool("roller", roller, (0.0, -1.0), mesh.top, (Move(0.0, 0.15), Move(0.0, 0.0)), (0.0, mu),
                     frictional=True, capacity=capacity)
    support = jf.DirichletBC(mesh.bottom, components=(1,))
    hold = jf.DirichletBC(mesh.right, components=(0,))
    pull = jf.DirichletBC(mesh.right, components=(0,), motion=jf.Ramp((0.0, 0.0), (3.0, 0.0)))
    phases = (jf.Phase("press", [support, hold], 6), jf.Phase("draw", [support, pull], 15))
    return jf.StripModel(mesh, jf.J2Material(**STEEL), phases, tools=(tool,), contact=law, formulation="ans")


@pytest.mark.parametrize("algorithm", ["lcp_ssn", "penalty"])
def test_a_run_on_the_selected_pairs_is_the_run_on_every_pair(algorithm):
    """The Nine (its seven tools: rollers, guide rollers, the entry guide's faces), clamped and drawn 3 mm:
    the contact zones move along the candidates, and every step's forces and contact counts, and the
    final contact state, are those of the run that evaluates every pair, to round-off."""
    runs = []
    for preselect in (True, False):
        scene = make("nine", "mu017", algorithm, {"mesh": "40x2", "U_draw": 3.0, "preselect": preselect})
        runs.append(eqx.filter_jit(lambda m, s=scene: simulate(m, control=s.control, observe=s.observe))(scene.model))
        if preselect:
            evaluated = sum(t.capacity or len(t.candidates) for t in scene.model.tools)
            assert evaluated < 0.5 * sum(len(t.candidates) for t in scene.model.tools)
    a, b = runs
    assert int(a.code) == int(b.code) == Result.SUCCESS
    n = int(a.history.n_rows)
    assert n == int(b.history.n_rows)
    oa, ob = a.history.observed, b.history.observed
    for name in ("drawing_force", "clamping_force"):
        scale = float(np.max(np.abs(ob[name][:n])))
        assert scale > 100.0
        np.testing.assert_allclose(oa[name][:n], ob[name][:n], rtol=0, atol=1e-9 * scale, err_msg=name)
    np.testing.assert_array_equal(oa["n_active"][:n], ob["n_active"][:n])
    ca, cb = a.final.contact, b.final.contact
    np.testing.assert_array_equal(ca.status, cb.status)
    # The left-out pairs' geometry is that of their evaluation: the state does not depend on the selection.
    np.testing.assert_allclose(ca.gap, cb.gap, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(ca.zeta, cb.zeta, rtol=1e-9, atol=1e-9)


def test_the_scenes_preselect_by_default_where_enough_pairs_are_left_out():
    """``preselect`` None (the default) selects where the capacities leave out PAYS_FROM pairs or more: not on the
    Nine's spec mesh (about 1250 left out), on 1200 x 3 (about 5000); True and False force either way."""
    def left_out(mesh, preselect="none"):
        tools = make("nine", "mu017", "lcp_ssn", {"mesh": mesh, "preselect": preselect}).model.tools
        return sum(len(t.candidates) - (t.capacity or len(t.candidates)) for t in tools)

    assert left_out("300x3") == 0 < left_out("300x3", True) < PAYS_FROM
    assert left_out("1200x3") == left_out("1200x3", True) >= PAYS_FROM
    assert left_out("1200x3", False) == 0


def test_a_capacity_too_small_for_the_contact_zone_stops_the_run_with_preselection():
    # Three nodes of the strip touch the roller at once (the run on every pair): one cannot hold them.
    sim = eqx.filter_jit(lambda m: simulate(m, control=CONTROL))(_pressed_and_drawn(Complementarity("ssn"), capacity=1))
    assert int(sim.code) == Result.PRESELECTION
    assert "capacity" in describe(int(sim.code))


def test_tool_capacity_keeps_every_candidate_of_a_tool_as_long_as_the_strip():
    mesh = jf.strip_mesh(0.0, 60.0, 0.0, 1.0, 120, 2)
    top = np.asarray(mesh.nodes)[np.asarray(mesh.top)]
    assert tool_capacity(Tool.line((-2.0, 1.0), (62.0, 1.0)), top) is None
    # A roller of radius 3: half a turn, two approaches within 1.5 mm, 2 x 1.5 mm (19.1 mm), on 0.5 mm.
    assert tool_capacity(Tool.circle((20.0, 4.0), 3.0), top) == math.ceil(1.1 * (3 * math.pi + 2 * math.sqrt(
        2 * 3 * 1.5 + 1.5**2) + 3.0) / 0.5) + 4
