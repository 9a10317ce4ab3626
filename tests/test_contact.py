"""Contact with rigid tools: global Coulomb sliding, force-driven tool balance, penalty -> augmented
Lagrangian, penetration law, Hertz, capstan, objectivity, derivatives, bad input."""

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfric as jf
from jaxfric.contact.formulations import (
    AugmentedLagrangian,
    Complementarity,
    ExactStartPenalty,
    Penalty,
    StiffPenalty,
    exact_start_point,
    newton_step,
)
from jaxfric.contact.rigid import Force, Move, RigidTool
from jaxfric.contact.tools import Tool
from jaxfric.loadpath.model import tool_positions
from jaxfric.loadpath.step import StepContext, step_args, unknowns
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


@pytest.mark.slow  # two more flat-die runs: a validation run (make test-all)
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


# The fast suite keeps the penalty case; exact contact is checked fast on the flat die (test_exact.py).
@pytest.mark.parametrize("law", [Penalty(1e6, 0.0),
                                 pytest.param(Complementarity("ssn"), marks=pytest.mark.slow),
                                 pytest.param(Complementarity("lemke"), marks=pytest.mark.slow),
                                 pytest.param(AugmentedLagrangian(1e5, 0.0, target_gap=1e-7), marks=pytest.mark.slow)],
                         ids=["penalty", "lcp_ssn", "lcp_lemke", "auglag"])
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


# The frictionless case (and its zero-moment check) runs in make test-all; the fast suite keeps mu = 0.2.
@pytest.mark.parametrize("mu", [pytest.param(0.0, marks=pytest.mark.slow), 0.2])
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


def capstan_model(alpha=0.0, mu=0.2, radius=10.0, wrap=np.pi / 2):
    """The capstan problem rotated rigidly by ``alpha`` (rad) about the roller centre."""
    mesh0, _, d2 = wrapped_strip(radius=radius, wrap=wrap)
    Q = np.array([[np.cos(alpha), -np.sin(alpha)], [np.sin(alpha), np.cos(alpha)]])
    mesh = jf.StripMesh(mesh0.nodes @ Q.T, mesh0.nx, mesh0.ny)
    roller = RigidTool("roller", Tool.circle((0.0, 0.0), radius), drive=Q @ np.array([0.0, -1.0]),
                       candidates=mesh.bottom, controls=(Move(),), mu=mu)
    bcs = [jf.DirichletBC(mesh.left), jf.DirichletBC(mesh.right, motion=jf.Ramp((0, 0), tuple(Q @ (0.05 * d2))))]
    model = jf.StripModel(mesh, jf.J2Material.elastic(200000.0, 0.3), (jf.Phase("pull", bcs, n_steps=20),),
                          tools=(roller,), contact=Penalty(1e6, 1e6 * mu))
    return model, Q, d2


def test_objectivity_of_frictional_contact_under_rotation():
    """The frictional capstan problem rotated by 0.7 rad (sheet, tool, drive and loads together) gives
    the same contact forces and, rotated back, the same reactions (measured 1e-10 and 1e-12)."""
    (m0, _, _), (m1, Q, _) = capstan_model(0.0), capstan_model(0.7)
    r0, r1 = jf.run(m0, progress=False), jf.run(m1, progress=False)
    c0, c1 = r0.final.contact, r1.final.contact
    scale = float(jnp.max(c0.rn))
    np.testing.assert_allclose(c1.rn, c0.rn, rtol=0, atol=1e-8 * scale)
    np.testing.assert_allclose(c1.rt, c0.rt, rtol=0, atol=1e-8 * scale)
    np.testing.assert_allclose(Q.T @ r1.history["reaction_right"][-1], r0.history["reaction_right"][-1],
                               rtol=0, atol=1e-9 * scale)


TIGHT = jf.NewtonOptions(rtol=1e-12, atol=1e-10)


def _exit_tension(law, mu):
    """The sliding capstan's exit tension with the contact formulation ``law(mu)``, the run's result code
    and its Newton iterations."""
    model, _, d2 = capstan_model(mu=mu)
    sim = jf.simulate(dataclasses.replace(model, contact=law(mu)), newton=TIGHT)
    h = sim.history
    return h.observed["reaction_right"][h.n_rows - 1] @ jnp.asarray(d2), sim.code, jnp.sum(h.newton_iters)


@functools.cache
def _capstan_with_tangent(start: str):
    """The compiled exit tension (:func:`_exit_tension`) and its forward derivative in mu, with the capstan's
    penalty law (eps_n = 1e6, eps_t = mu eps_n) started from the load loop's guess ("plain") or from exact
    contact ("exact"): one program per law for the tests of this file (one pytest worker per file)."""
    law = {"plain": Penalty, "exact": ExactStartPenalty}[start]
    return jax.jit(lambda mu: jax.jvp(lambda m: _exit_tension(lambda k: law(1e6, 1e6 * k), m), (mu,),
                                      (jnp.ones_like(mu),)))


def test_jvp_of_sliding_force_with_respect_to_mu():
    """Exit tension of the fully sliding capstan: forward derivative in mu vs central differences."""
    # One compiled function (the primal and its tangent) serves the derivative and the differences.
    with_tangent = _capstan_with_tangent("plain")
    _, (tangent, _, _) = with_tangent(jnp.asarray(0.2))
    h = 1e-5
    fd = (with_tangent(jnp.asarray(0.2 + h))[0][0] - with_tangent(jnp.asarray(0.2 - h))[0][0]) / (2 * h)
    np.testing.assert_allclose(float(tangent), float(fd), rtol=1e-6)


def test_exact_start_gives_the_penalty_law_s_solution_and_derivative():
    """The sliding capstan (eps_n = 1e6, where the plain penalty law takes every nominal step): every step
    started from the compliant semismooth solve (ExactStartPenalty) converges to the plain law's solution,
    its exit tension within Newton's tolerance of the plain law's (measured 6e-14 relative), with the same
    forward derivative in mu (the implicit function theorem at the same solution; 2e-13), in 61 Newton
    iterations of both solves (lcp_ssn takes 41, and the penalty's Newton one a step) against the plain
    law's 223."""
    (plain, plain_code, plain_its), (plain_dot, _, _) = _capstan_with_tangent("plain")(jnp.asarray(0.2))
    (started, code, its), (started_dot, _, _) = _capstan_with_tangent("exact")(jnp.asarray(0.2))
    assert int(plain_code) == 0 and int(code) == 0
    np.testing.assert_allclose(float(started), float(plain), rtol=1e-9)
    np.testing.assert_allclose(float(started_dot), float(plain_dot), rtol=1e-8)
    assert int(its) < int(plain_its)


@pytest.mark.slow  # 25 s: the compliant solve and two penalty solves compiled beside a run
def test_compliant_solve_lands_on_the_penalty_law_s_step():
    """One step of the sliding capstan (eps_n = 1e6, eps_t = mu eps_n) from t = 0.4 of its pull: the
    compliant semismooth solve (exact_start_point) converges to the plain penalty Newton solve's solution
    (within Newton's tolerance: measured 2e-13 of the step's largest increment; 3 iterations against the
    plain solve's 4), and the penalty law's Newton solve from there converges on its first iteration."""
    model, _, _ = capstan_model(mu=0.2)
    law = Penalty(1e6, 2e5)
    model = dataclasses.replace(model, contact=law)
    state = jf.run(model, newton=TIGHT, control=jf.StepControl(max_steps=10), progress=False,
                   raise_on_failure=False).simulation.final
    assert 0.4 < float(state.time) < 0.6
    args, _, _ = step_args(model, state, int(state.phase), float(state.time) + 0.05, StepContext.build(model))
    x_ref = unknowns(model, state.u, tool_positions(state))

    @jax.jit
    def solve(a, x):
        start, penalty, exact = exact_start_point(law, a, x, x, TIGHT)
        return start, exact, newton_step(penalty, x, x, TIGHT), newton_step(penalty, start, x, TIGHT)

    start, compliant_sol, plain, started = solve(args, x_ref)
    assert int(compliant_sol.code) == 0 and int(plain.code) == 0 and int(started.code) == 0
    scale = float(jnp.max(jnp.abs(plain.x - x_ref)))
    np.testing.assert_allclose(np.asarray(start), np.asarray(plain.x), rtol=0, atol=1e-9 * scale)
    assert int(started.iterations) == 1 < int(plain.iterations)


@pytest.mark.slow  # 2 min: exact contact's and the AL's derivatives compiled
def test_auglag_exact_start_takes_exact_contact_s_step_and_derivative():
    """The sliding capstan: the augmented Lagrangian started from exact contact (``exact_start``) stops at
    exact contact's solution, its fixed point, without an augmentation: exit tension within 1e-10 of
    ``lcp_ssn``'s (measured 1e-13) in one Newton iteration a step more (61 against 41; the plain AL 168),
    and the forward derivative in mu that ``lcp_ssn``'s implicit derivative gives (measured 2e-12),
    carried by the multipliers into the AL's implicit function theorem; central differences agree."""
    exact = jax.jit(lambda mu: jax.jvp(lambda m: _exit_tension(lambda k: Complementarity("ssn"), m), (mu,),
                                       (jnp.ones_like(mu),)))
    (value, code, its), (tangent, _, _) = exact(jnp.asarray(0.2))
    started = jax.jit(lambda mu: jax.jvp(
        lambda m: _exit_tension(lambda k: AugmentedLagrangian(1e6, 1e6 * k, exact_start=True), m), (mu,),
        (jnp.ones_like(mu),)))
    (al_value, al_code, al_its), (al_tangent, _, _) = started(jnp.asarray(0.2))
    assert int(code) == 0 and int(al_code) == 0
    np.testing.assert_allclose(float(al_value), float(value), rtol=1e-10)
    np.testing.assert_allclose(float(al_tangent), float(tangent), rtol=1e-9)
    assert int(al_its) <= int(its) + 20   # one iteration in each of the 20 steps
    h = 1e-5
    fd = (started(jnp.asarray(0.2 + h))[0][0] - started(jnp.asarray(0.2 - h))[0][0]) / (2 * h)
    np.testing.assert_allclose(float(al_tangent), float(fd), rtol=1e-6)


@pytest.mark.slow  # 2 min: the exact solver compiled with the penalty's derivative
def test_stiff_penalty_finishes_where_the_plain_law_does_not_with_its_derivative():
    """The sliding capstan at eps_n = 1e9 (5e3 times the sheet's modulus): the plain penalty law does
    not finish; StiffPenalty (a failed attempt solved again from the compliant semismooth solve) does, its exit tension
    within 1e-5 of exact contact's (the penalty's elastic slip and penetration are 1e-9 of the forces
    per N/mm), and its forward derivative in mu equals central differences. No tangent reaches the
    compliant solve, which has none."""

    plain = jax.jit(lambda mu: _exit_tension(lambda m: Penalty(1e9, 1e9 * m), mu))(jnp.asarray(0.2))
    assert int(plain[1]) != 0
    exact = jax.jit(lambda mu: _exit_tension(lambda m: Complementarity("ssn"), mu))(jnp.asarray(0.2))
    assert int(exact[1]) == 0
    with_tangent = jax.jit(lambda mu: jax.jvp(lambda m: _exit_tension(lambda k: StiffPenalty(1e9, 1e9 * k), m),
                                              (mu,), (jnp.ones_like(mu),)))
    (value, code, _), (tangent, _, _) = with_tangent(jnp.asarray(0.2))
    assert int(code) == 0
    np.testing.assert_allclose(float(value), float(exact[0]), rtol=1e-5)
    h = 1e-5
    fd = (with_tangent(jnp.asarray(0.2 + h))[0][0] - with_tangent(jnp.asarray(0.2 - h))[0][0]) / (2 * h)
    np.testing.assert_allclose(float(tangent), float(fd), rtol=1e-6)


def test_jvp_of_indentation_with_respect_to_tool_radius():
    """Frictionless Hertz indentation: approach of the force-driven cylinder as a function of its
    radius, forward derivative vs central differences (status switches are far from this radius)."""
    xs = jf.graded_coordinates(0.0, 2.0, 20, 1.1)
    ys = jf.graded_coordinates(-2.0, 0.0, 8, 1 / 1.2)
    mesh = jf.StripMesh.from_coordinates(xs, ys)
    bcs = [jf.DirichletBC(mesh.left, components=(0,)), jf.DirichletBC(mesh.bottom)]

    @jax.jit
    def approach(radius):
        tool = RigidTool("cylinder", Tool.circle(jnp.stack([0.0, radius]), radius), drive=(0.0, -1.0),
                         candidates=mesh.top, controls=(Force(0.5, start=0.0),), mu=0.0)
        model = jf.StripModel(mesh, jf.J2Material.elastic(1000.0, 0.3), (jf.Phase("press", bcs, 4),),
                              tools=(tool,), contact=Penalty(1e6, 0.0))
        return jf.simulate(model, newton=TIGHT).final.contact.q[0]

    with_tangent = jax.jit(lambda r: jax.jvp(approach, (r,), (jnp.ones_like(r),)))
    value, tangent = with_tangent(jnp.asarray(5.0))
    h = 1e-4
    fd = (with_tangent(jnp.asarray(5.0 + h))[0] - with_tangent(jnp.asarray(5.0 - h))[0]) / (2 * h)
    assert float(value) > 0 and float(tangent) < 0  # a larger cylinder sinks in less
    np.testing.assert_allclose(float(tangent), float(fd), rtol=1e-5)


def test_force_driven_tool_loses_and_regains_contact():
    """A force-driven die (eps_n = 1e9) clamps a strip to 50 N/mm, is released to 0, the strip is
    lowered 0.01 mm away from it (the die, with nothing to push, seeks the sheet and rests on it with
    zero force), then the die presses again to 50 N/mm: every step converges and balances its force."""
    L, h = 6.0, 0.395
    mesh = jf.strip_mesh(0.0, L, 0.0, h, 30, 2)
    die = RigidTool("die", Tool.line((-2.0, h), (L + 2.0, h)), drive=(0.0, -1.0), candidates=mesh.top,
                    controls=(Force(FORCE, start=0.0), Force(0.0), Force(0.0, start=0.0), Force(FORCE)), mu=0.0)

    def bottom(v0, v1):
        return jf.DirichletBC(mesh.bottom, components=(1,), motion=jf.Ramp((0, v0), (0, v1)))

    hold = jf.DirichletBC(mesh.right, components=(0,))
    phases = (jf.Phase("clamp", [bottom(0, 0), hold], 5), jf.Phase("release", [bottom(0, 0), hold], 5),
              jf.Phase("drop", [bottom(0, -0.01), hold], 5), jf.Phase("press", [bottom(-0.01, -0.01), hold], 5))
    model = jf.StripModel(mesh, jf.J2Material.elastic(69004.0, 0.3), phases, tools=(die,),
                          contact=Penalty(1e9, 0.0))
    res = jf.run(model, progress=False)
    h_ = res.history
    t = h_["time"]
    prescribed = np.select([t <= 1, t <= 2, t <= 3], [FORCE * t, FORCE * (2 - t), 0.0], FORCE * (t - 3))
    np.testing.assert_allclose(h_["tool_force"][:, 0], prescribed, rtol=0, atol=1e-8 * FORCE)
    dropped = np.isclose(t, 3.0)
    assert abs(h_["tool_position"][dropped, 0][0] - 0.01) < 1e-8  # it followed the strip down
    assert h_["n_active"][-1] == mesh.top.size


def test_tool_placement_is_checked_before_any_computation():
    mesh = jf.strip_mesh(0.0, 4.0, 0.0, 1.0, 8, 2)
    mat = jf.J2Material(**STEEL)
    phase = (jf.Phase("p", [jf.DirichletBC(mesh.left)]),)

    def model(tool):
        return jf.StripModel(mesh, mat, phase, tools=(tool,), contact=Penalty(1e5, 0.0))

    cutting = RigidTool("punch", Tool.circle((2.0, 1.5), 1.0), (0.0, -1.0), mesh.top, (Move(),), 0.0)
    with pytest.raises(ValueError, match="'punch' intersects the sheet"):
        model(cutting)
    far_away = RigidTool("die", Tool.line((10.0, 1.0), (12.0, 1.0)), (0.0, -1.0), mesh.top, (Force(5.0),), 0.0)
    with pytest.raises(ValueError, match="'die' is force-driven but none of its candidate nodes"):
        model(far_away)
    touching = RigidTool("die", Tool.line((-1.0, 1.0), (5.0, 1.0)), (0.0, -1.0), mesh.top, (Force(5.0),), 0.0)
    model(touching)  # exactly touching is the spec's starting position


def test_pairs_on_the_coulomb_cone_count_as_slipping_for_newton():
    """Newton's "no status change" test sees a closed pair on the Coulomb cone as slipping whichever
    branch the law took: the law is continuous there, so a stick <-> slip flip at round-off moves the
    force by nothing (such flips stopped the Nine at eps_N = 1e6 with friction at U = 53.6 mm: residual
    2.4e-8 N/mm against a tolerance of 1.7e-6, some 20 pairs flipping at every iteration). Here: the
    flat die's converged, sliding end state re-linearised with mu 1e-12 (relative) larger, so that
    its slipping pairs take the law's stick branch at an unchanged force."""
    from jaxfric.contact.status import SLIP, STICK
    from jaxfric.loadpath.run import run
    from jaxfric.loadpath.step import linearize_step
    from jaxfric.scenes import make

    config = {"mesh": "12x1", "L": 4.8, "U_draw": 0.006}
    scene = make("flat_die", "const_force", "penalty", config)
    res = run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe, progress=False)
    state = res.simulation.final
    lin = linearize_step(scene.model, state, state.phase, state.time)
    slipping = np.asarray(lin.aux[2]["status"]) == SLIP
    assert slipping.sum() >= 3 and np.array_equal(np.asarray(lin.status)[slipping], np.full(slipping.sum(), SLIP))

    nudged = make("flat_die", "const_force", "penalty", {**config, "mu": scene.config.mu * (1.0 + 1e-12)})
    lin2 = linearize_step(nudged.model, state, state.phase, state.time)
    law = np.asarray(lin2.aux[2]["status"])
    assert np.all(law[slipping] == STICK)                      # the law's branch flipped ...
    assert np.all(np.asarray(lin2.status)[slipping] == SLIP)   # ... the convergence test sees no change
    np.testing.assert_allclose(np.asarray(lin2.residual), np.asarray(lin.residual), rtol=0, atol=1e-9)


def test_continuation_stages_soften_the_penalty_law_only_and_exactly():
    """StepControl.continuation: the first stage divides eps_n (and eps_t) by 10^m, m = ceil(log10(eps_n
    / E)) (4 for 1e9 N/mm on steel, E = 2.1e5 MPa; none at or below E, nor for AL or exact contact), and
    the last stage (m = 0) is the model's own law bit for bit."""
    import equinox as eqx

    from jaxfric.loadpath.step import continuation_stages, softened_args
    from jaxfric.scenes import make

    small = {"mesh": "10x1", "U_draw": 0.5}
    assert int(continuation_stages(make("nine", "mu017", "penalty", {**small, "eps_n": 1e9}).model)) == 4
    assert int(continuation_stages(make("nine", "mu017", "penalty", {**small, "eps_n": 1e12}).model)) == 7
    assert int(continuation_stages(make("nine", "mu017", "penalty", {**small, "eps_n": 1e5}).model)) == 0
    assert int(continuation_stages(make("nine", "mu017", "auglag", {**small, "eps_n": 1e9}).model)) == 0
    assert int(continuation_stages(make("nine", "mu017", "lcp_ssn", small).model)) == 0

    class Step(eqx.Module):
        law: Penalty

    class Args(eqx.Module):
        contact: Step

    args = Args(Step(Penalty(1e9, 1.7e8)))
    same = softened_args(args, 0)
    assert float(same.contact.law.eps_n) == 1e9 and float(same.contact.law.eps_t) == 1.7e8
    soft = softened_args(args, jnp.array(4))
    assert float(soft.contact.law.eps_n) == pytest.approx(1e5, rel=1e-15)
    assert float(soft.contact.law.eps_t) == pytest.approx(1.7e4, rel=1e-15)


def test_the_stabilised_attempts_damper_acts_on_the_free_dofs_with_its_exact_tangent():
    """StepControl.stabilize: with StepArgs.damping = eta the residual of every free dof gains eta (u - u_n)
    (u_n: the converged displacements of the step's start), prescribed rows and tool rows keep theirs,
    and the Jacobian gains eta on the free dofs' diagonal: the flat die's force-driven die (a bordered
    system) at a point off its converged state, against the undamped linearisation and the residual's
    own forward derivative."""
    from jaxfric.contact.system import linearize, residual
    from jaxfric.loadpath.model import tool_positions
    from jaxfric.loadpath.run import run
    from jaxfric.loadpath.step import StepContext, step_args, unknowns
    from jaxfric.scenes import make

    scene = make("flat_die", "const_force", "penalty", {"mesh": "6x1", "L": 4.8, "U_draw": 0.003})
    res = run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe, progress=False)
    state, model = res.simulation.final, scene.model
    ctx = StepContext.build(model)
    t = float(state.time) + 1e-3
    eta = 37.0
    # Compiled as one program each (evaluated op by op, the arguments and linearisations compile
    # hundreds of small programs).
    args = eqx.filter_jit(lambda damping: step_args(model, state, state.phase, t, ctx, damping=damping)[0])
    plain, damped = args(None), args(jnp.asarray(eta))
    x_n = unknowns(model, state.u, tool_positions(state))
    x = x_n + 1e-4 * jnp.sin(jnp.arange(x_n.size, dtype=float))
    n, free = model.mesh.n_dofs, ~np.asarray(plain.mask)
    compiled = eqx.filter_jit(linearize)
    lin0, lin1 = compiled(x, plain), compiled(x, damped)
    expected = np.zeros(x.size)
    expected[:n] = np.where(free, eta * np.asarray(x[:n] - x_n[:n]), 0.0)
    # Equal up to the round-off of the undamped residual's size (the difference cancels it).
    roundoff = 1e-13 * float(jnp.max(jnp.abs(lin0.residual)))
    np.testing.assert_allclose(np.asarray(lin1.residual - lin0.residual), expected, rtol=0, atol=roundoff)
    extra = np.zeros((x.size, x.size))
    extra[np.arange(n), np.arange(n)] = np.where(free, eta, 0.0)
    np.testing.assert_allclose(np.asarray(lin1.jacobian.to_dense() - lin0.jacobian.to_dense()), extra,
                               rtol=0, atol=1e-9 * eta)
    forward = eqx.filter_jit(jax.jacfwd(lambda y: residual(y, damped)[0]))(x)
    np.testing.assert_allclose(np.asarray(lin1.jacobian.to_dense()), np.asarray(forward), rtol=1e-8,
                               atol=1e-8 * float(jnp.max(jnp.abs(forward))))
