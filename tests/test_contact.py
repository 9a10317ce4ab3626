"""Contact with rigid tools: global Coulomb sliding, force-driven tool balance, penalty -> augmented
Lagrangian, penetration law, bad input."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxfric as jf
from jaxfric.contact import AugmentedLagrangian, Force, Move, Penalty, RigidTool
from jaxfric.tools import Tool
from models import STEEL, flat_die_strip, wrapped_strip

MU, FORCE = 0.15, 50.0


@pytest.fixture(scope="module")
def stiff_penalty_run():
    """The benchmark's stiff penalties (eps_n = 1e9, eps_t = 1.5e8 N/mm)."""
    return jf.run(flat_die_strip(Penalty(1e9, 1.5e8)), progress=False)


@pytest.fixture(scope="module")
def augmented_run():
    return jf.run(flat_die_strip(AugmentedLagrangian(1e5, 1.5e4, target_gap=1e-8)), progress=False)


def drawing_curve(res):
    h = res.history
    draw = h["phase"] == 1
    return (h["time"][draw] - 1.0) * 0.03, h["reaction_right"][draw, 0]


def test_global_coulomb_sliding(stiff_penalty_run):
    """Once every closed pair slides, the drawing force is mu times the clamping force and the
    tangential resultant is mu times the normal resultant (to solver tolerance)."""
    res = stiff_penalty_run
    c = res.final.contact
    assert res.converged
    assert int(res.history["n_slip"][-1]) == int(res.history["n_active"][-1]) == c.rn.size
    np.testing.assert_allclose(-float(jnp.sum(c.rt)), MU * float(jnp.sum(c.rn)), rtol=1e-9)
    np.testing.assert_allclose(res.history["reaction_right"][-1, 0], MU * FORCE, rtol=1e-8)
    # The stick-slip transition: the drawing force rises from 0 to mu P through partial slip.
    U, F = drawing_curve(res)
    partial = (res.history["n_slip"] < res.history["n_active"])[res.history["phase"] == 1]
    assert partial[:20].any() and np.all(np.diff(F[: np.argmax(F >= MU * FORCE * (1 - 1e-9))]) > 0)


@pytest.mark.parametrize("which", ["penalty", "auglag"])
def test_force_driven_die_balance_at_every_step(which, stiff_penalty_run, augmented_run):
    """|clamping force - P(t)| within Newton's tolerance at every converged step of force-driven phases."""
    res = stiff_penalty_run if which == "penalty" else augmented_run
    h = res.history
    prescribed = np.where(h["phase"] == 0, FORCE * h["time"], FORCE)
    tol = 1e-10 + 1e-8 * np.maximum(np.abs(h["tool_force"][:, 0]), 1e-6) * 10
    assert np.all(np.abs(h["tool_force"][:, 0] - prescribed) <= tol + 1e-8 * FORCE)


def test_penalty_penetration_law_and_auglag_target(stiff_penalty_run, augmented_run):
    """Penalty: a closed pair penetrates by R_N / eps_n exactly. AL: every step meets its target gap."""
    c = stiff_penalty_run.final.contact
    closed = np.asarray(c.status) > 0
    np.testing.assert_allclose(-np.asarray(c.gap)[closed], np.asarray(c.rn)[closed] / 1e9, rtol=1e-8)
    assert augmented_run.history["max_penetration"].max() <= 1e-8
    assert augmented_run.history["augmentations"].sum() > 0


def test_penalty_approaches_the_augmented_lagrangian(stiff_penalty_run, augmented_run):
    """As eps_n grows, the penalty drawing-force curve and die position approach the AL solution."""
    U_ref, F_ref = drawing_curve(augmented_run)
    q_ref = augmented_run.history["tool_position"][-1, 0]
    errors = []
    for eps_n in (1e5, 1e7):
        res = jf.run(flat_die_strip(Penalty(eps_n, MU * eps_n)), progress=False)
        U, F = drawing_curve(res)
        errors.append((np.max(np.abs(np.interp(U_ref, U, F) - F_ref)) / (MU * FORCE),
                       abs(res.history["tool_position"][-1, 0] - q_ref) / q_ref))
    U, F = drawing_curve(stiff_penalty_run)
    errors.append((np.max(np.abs(np.interp(U_ref, U, F) - F_ref)) / (MU * FORCE),
                   abs(stiff_penalty_run.history["tool_position"][-1, 0] - q_ref) / q_ref))
    curve, position = np.array(errors).T
    assert np.all(np.diff(curve) < 0) and np.all(np.diff(position) < 0), errors
    assert curve[-1] < 1e-2 and position[-1] < 1e-4, errors


def test_bad_contact_input_names_the_field():
    mesh = jf.strip_mesh(0.0, 1.0, 0.0, 1.0, 2, 2)
    line = Tool.line((-1.0, 1.0), (2.0, 1.0))
    ok = dict(name="die", geometry=line, drive=(0.0, -1.0), candidates=mesh.top, controls=(Move(),), mu=0.1)
    with pytest.raises(ValueError, match="mu"):
        RigidTool(**{**ok, "mu": -0.1})
    with pytest.raises(ValueError, match="drive"):
        RigidTool(**{**ok, "drive": (0.0, -2.0)})
    with pytest.raises(ValueError, match="candidates"):
        RigidTool(**{**ok, "candidates": []})
    with pytest.raises(ValueError, match="eps_n"):
        Penalty(-1.0, 0.0)
    with pytest.raises(ValueError, match="eps_n"):
        Penalty(0.0, 0.0)
    with pytest.raises(ValueError, match="target_gap"):
        AugmentedLagrangian(1e5, 0.0, target_gap=0.0)
    with pytest.raises(ValueError, match="force"):
        Force(-5.0)
    mat = jf.J2Material(**STEEL)
    phase = (jf.Phase("p", [jf.DirichletBC(mesh.left)]),)
    with pytest.raises(ValueError, match="contact"):
        jf.StripModel(mesh, mat, phase, tools=(RigidTool(**ok),))
    with pytest.raises(ValueError, match="controls"):
        jf.StripModel(mesh, mat, phase + (jf.Phase("q"),), tools=(RigidTool(**ok),), contact=Penalty(1e5, 0))
    with pytest.raises(ValueError, match="candidates"):
        jf.StripModel(mesh, mat, phase, tools=(RigidTool(**{**ok, "candidates": [99]}),),
                      contact=Penalty(1e5, 0))


@pytest.mark.parametrize("law", [Penalty(1e6, 0.0), AugmentedLagrangian(1e5, 0.0, target_gap=1e-7)],
                         ids=["penalty", "auglag"])
def test_hertz_line_contact(law):
    """A rigid cylinder (R = 10 mm) pressed with P = 1 N/mm on a thick elastic block (half model,
    graded mesh, 0.005 mm at the contact): half-width a = sqrt(4 P R / (pi E*)) and peak pressure
    p0 = 2 P / (pi a) within 5 % (measured: a 1.5 % wide, half a node spacing; p0 within 0.2 %)."""
    E, nu, R, P = 1000.0, 0.3, 10.0, 1.0
    xs = jf.graded_coordinates(0.0, 5.0, 60, 1.075)
    ys = jf.graded_coordinates(-5.0, 0.0, 30, 1 / 1.12)
    mesh = jf.StripMesh.from_coordinates(xs, ys)
    tool = RigidTool("cylinder", Tool.circle((0.0, R), R), drive=(0.0, -1.0), candidates=mesh.top,
                     controls=(Force(P / 2, start=0.0),), mu=0.0)
    bcs = [jf.DirichletBC(mesh.left, components=(0,)), jf.DirichletBC(mesh.bottom)]
    model = jf.StripModel(mesh, jf.J2Material.elastic(E, nu), (jf.Phase("press", bcs, n_steps=5),),
                          tools=(tool,), contact=law)
    res = jf.run(model, progress=False)
    rn = np.asarray(res.final.contact.rn)
    x = np.asarray(mesh.nodes[mesh.top, 0] + res.final.u[mesh.top, 0])
    X = np.asarray(xs)
    tributary = np.r_[(X[1] - X[0]) / 2, (X[2:] - X[:-2]) / 2, (X[-1] - X[-2]) / 2]
    a = np.sqrt(4 * P * R / (np.pi * E / (1 - nu**2)))
    p0 = 2 * P / (np.pi * a)
    last = np.max(np.nonzero(rn > 1e-9)[0])
    a_fe = 0.5 * (x[last] + x[last + 1])  # the contact edge lies between the last closed and first open node
    assert abs(a_fe / a - 1) < 0.05, (a_fe, a)
    assert abs(rn[0] / tributary[0] / p0 - 1) < 0.05, (rn[0] / tributary[0], p0)
    np.testing.assert_allclose(res.history["tool_force"][-1, 0], P / 2, rtol=1e-8)


@pytest.mark.parametrize("mu", [0.0, 0.2])
def test_capstan_over_a_fixed_roller(mu):
    """A thin elastic strip wrapped 90 degrees over a fixed roller, one end held, the other pulled
    along its leg until the whole wrap slides: T_out / T_in = exp(mu theta) (measured 1.3672 vs
    1.3691). Frictionless: the strip dissipates nothing (T_out = T_in, measured to 3e-4, the strip's
    bending at the tangent points) and the roller forces have zero moment about its centre."""
    radius, wrap = 10.0, np.pi / 2
    mesh, d1, d2 = wrapped_strip(radius=radius, wrap=wrap)
    roller = RigidTool("roller", Tool.circle((0.0, 0.0), radius), drive=(0.0, -1.0),
                       candidates=mesh.bottom, controls=(Move(),), mu=mu)
    bcs = [jf.DirichletBC(mesh.left), jf.DirichletBC(mesh.right, motion=jf.Ramp((0, 0), tuple(0.05 * d2)))]
    model = jf.StripModel(mesh, jf.J2Material.elastic(200000.0, 0.3), (jf.Phase("pull", bcs, n_steps=20),),
                          tools=(roller,), contact=Penalty(1e6, mu * 1e6))
    res = jf.run(model, progress=False)
    h = res.history
    t_in, t_out = -h["reaction_left"][-1] @ d1, h["reaction_right"][-1] @ d2
    assert t_in > 30.0 and h["n_slip"][-1] == h["n_active"][-1] > 100
    assert abs(t_out / t_in / np.exp(mu * wrap) - 1) < 0.01, (t_out / t_in, np.exp(mu * wrap))
    if mu == 0.0:
        c = res.final.contact
        n = np.asarray(c.normal)
        f = np.asarray(c.rn)[:, None] * n
        x = np.asarray(mesh.nodes[mesh.bottom] + res.final.u[mesh.bottom])
        moment = np.sum(x[:, 0] * f[:, 1] - x[:, 1] * f[:, 0])
        assert abs(moment) < 1e-9 * t_in * radius
