"""Exact contact in the global Newton loop (spec 1.7, 1.8): lcp_ssn and lcp_lemke against each other
and against a tight augmented Lagrangian, the force-driven die's balance, zero penetration, global
Coulomb sliding, the proximity band, and derivatives on the converged active set."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfric as jf
from jaxfric.contact.formulations import AugmentedLagrangian, Complementarity
from jaxfric.loadpath.step import solve_step
from jaxfric.numerics.results import Result
from models import flat_die_strip

MU, FORCE, DRAW = 0.15, 50.0, 0.01
SMALL = dict(nx=20, length=4.0, draw=DRAW, clamp_steps=5, increments=((0.25, 20), (1.0, 30)))


@pytest.fixture(scope="module")
def runs():
    laws = {"auglag": AugmentedLagrangian(1e9, 1.5e8, target_gap=1e-10),
            "lcp_ssn": Complementarity("ssn"), "lcp_lemke": Complementarity("lemke")}
    return {name: jf.run(flat_die_strip(law, **SMALL), progress=False) for name, law in laws.items()}


def test_lemke_and_semismooth_newton_give_the_same_forces_and_displacements(runs):
    """Spec 1.7: (a) Lemke and (b) semismooth Newton agree to solver tolerance, step by step."""
    a, b = runs["lcp_lemke"], runs["lcp_ssn"]
    assert a.history["time"].shape == b.history["time"].shape
    np.testing.assert_allclose(a.history["reaction_right"], b.history["reaction_right"], atol=1e-8 * FORCE)
    np.testing.assert_allclose(a.history["tool_position"], b.history["tool_position"], atol=1e-12)
    np.testing.assert_allclose(a.final.u, b.final.u, atol=1e-12)
    np.testing.assert_allclose(a.final.contact.rn, b.final.contact.rn, atol=1e-8 * FORCE)
    np.testing.assert_allclose(a.final.contact.rt, b.final.contact.rt, atol=1e-8 * FORCE)
    assert np.array_equal(a.final.contact.status, b.final.contact.status)
    # Each solver did the work it reports.
    assert a.history["lcp_pivots"].sum() > 0 and a.history["ssn_iters"].sum() == 0
    assert b.history["ssn_iters"].sum() > 0 and b.history["ssn_fallbacks"].sum() == 0


def test_exact_contact_matches_a_tight_augmented_lagrangian(runs):
    """The AL run with a 1e-10 mm target converges on the same solution: drawing forces within 1e-6
    of mu P over the whole stroke, die positions within the AL's residual penetration."""
    ref, lcp = runs["auglag"], runs["lcp_ssn"]
    # The AL run cut its first drawing steps (its stiff tangential penalty): compare at the times both
    # runs reached, which include the clamp and the last three quarters of the stroke.
    common, i, j = np.intersect1d(lcp.history["time"], ref.history["time"], return_indices=True)
    assert common.size > 30
    np.testing.assert_allclose(lcp.history["reaction_right"][i, 0], ref.history["reaction_right"][j, 0],
                               atol=1e-6 * MU * FORCE)
    np.testing.assert_allclose(lcp.history["tool_position"][i], ref.history["tool_position"][j], atol=1e-9)


@pytest.mark.parametrize("name", ["lcp_ssn", "lcp_lemke"])
def test_exact_contact_balance_penetration_and_coulomb(runs, name):
    """At every converged step the force-driven die carries exactly P; no pair penetrates; at the end
    every closed pair slides and the drawing force is mu P (global Coulomb)."""
    h = runs[name].history
    clamp = h["phase"] == 0
    P = FORCE * np.clip(h["time"], 0.0, 1.0)
    np.testing.assert_allclose(h["tool_force"][1:, 0], P[1:], atol=1e-8 * FORCE)
    assert np.all(h["max_penetration"] <= 1e-10)
    assert h["n_slip"][-1] == h["n_active"][-1] == 21
    np.testing.assert_allclose(h["reaction_right"][-1, 0], MU * FORCE, rtol=1e-7)
    assert np.all(np.abs(h["reaction_right"][clamp, 0]) < 1e-8)   # frictionless clamping


def test_a_band_too_small_is_widened_and_the_run_is_the_run_with_every_candidate(runs):
    """21 die candidates all close at the first clamp step: a band of 11 cannot hold them (the band
    bounds the condensed problem of "lemke"; the in-loop "ssn" solver works on every candidate), and
    the attempt ends with CONTACT_BAND. The driver then widens the band (Result.BAND_FULL), doubling it up
    to every candidate node: here at once, at the first clamp step, which it tries again at the same
    increment; the run is then the run with every candidate from the start: the same steps, forces to
    1e-8 of the clamping force, the same die position. A resumed run takes the widened band from its
    checkpoint."""
    model = flat_die_strip(Complementarity("lemke", band=11), **SMALL)
    assert [Complementarity("lemke", band=b).widened(model.tools).band for b in (5, 10)] == [10, 20]
    assert Complementarity("lemke", band=21).widened(model.tools) is None
    assert Complementarity("ssn", band=5).widened(model.tools) is None
    res = jf.run(model, progress=False)
    ref = runs["lcp_lemke"]
    assert res.band_widened == ((res.history["time"][1], None),) and res.model.contact.band is None
    assert res.converged and res.history["cut_codes"][1] == 1 << Result.CONTACT_BAND
    np.testing.assert_array_equal(res.history["time"], ref.history["time"])
    np.testing.assert_allclose(res.history["reaction_right"], ref.history["reaction_right"], atol=1e-8 * FORCE)
    np.testing.assert_allclose(res.history["tool_position"], ref.history["tool_position"], atol=1e-12)
    stopped = jf.run(model, progress=False, stop=lambda calls=iter(range(3)): next(calls, 9) >= 2,
                     raise_on_failure=False)
    assert stopped.code == Result.STOPPED and len(stopped.band_widened) == 1
    resumed = jf.run(model, progress=False, resume=stopped.checkpoint)
    assert resumed.band_widened == res.band_widened
    np.testing.assert_allclose(resumed.history["reaction_right"], res.history["reaction_right"], atol=1e-12)


def _die_outputs(solver, p):
    """The die's reaction and position at the end of the draw, for (mu, clamping force) ``p``."""
    model = flat_die_strip(Complementarity(solver), mu=p[0], force=p[1], **SMALL)
    sim = jf.simulate_fixed(model, newton=jf.NewtonOptions(rtol=1e-12, atol=1e-10))
    last = sim.history.n_rows - 1
    return jnp.stack([sim.history.observed["reaction_right"][last, 0],
                      sim.history.observed["tool_position"][last].reshape(-1)[0]]), sim.code


@pytest.mark.parametrize("solver", ["ssn", pytest.param("lemke", marks=pytest.mark.slow)])
def test_exact_contact_derivatives_match_central_differences(solver):
    """Forward mode through exact-contact steps (implicit function theorem on the converged active set,
    jaxfric.contact.exact_derivative) against central differences, with respect to mu and the clamping
    force. The right-end corner slips under the die with its x prescribed (its rows taken apart, see the
    module). The reaction is mu F in closed form, so d/dmu = F and d/dF = mu exactly. One compiled
    program serves the derivatives and the differences (the values of the same forward pass).
    Measured: 1e-9 of each row (h = 1e-4 |p|)."""
    jvp = jax.jit(lambda p, v: jax.jvp(lambda q: _die_outputs(solver, q)[0], (p,), (v,)))
    p0 = jnp.array([MU, FORCE])
    jac = np.stack([np.asarray(jvp(p0, jnp.eye(2)[i])[1]) for i in range(2)], axis=1)
    assert np.all(np.isfinite(jac))
    np.testing.assert_allclose(jac[0], [FORCE, MU], rtol=1e-8)
    fd = np.zeros_like(jac)
    for i in range(2):
        h = 1e-4 * float(p0[i])
        fd[:, i] = (np.asarray(jvp(p0.at[i].add(h), jnp.eye(2)[i])[0])
                    - np.asarray(jvp(p0.at[i].add(-h), jnp.eye(2)[i])[0])) / (2 * h)
    scale = np.max(np.abs(jac), axis=1, keepdims=True)
    np.testing.assert_allclose(jac / scale, fd / scale, atol=1e-7)


@pytest.mark.slow  # two more compiled programs (100 s): reverse mode through the checkpointed fixed-step scan
def test_exact_contact_reverse_mode_equals_forward_mode():
    p0 = jnp.array([MU, FORCE])
    grad = np.asarray(jax.jit(jax.grad(lambda p: _die_outputs("ssn", p)[0][0]))(p0))
    jac = np.asarray(jax.jit(jax.jacfwd(lambda p: _die_outputs("ssn", p)[0][0]))(p0))
    np.testing.assert_allclose(grad, jac, rtol=1e-10)
    np.testing.assert_allclose(grad, [FORCE, MU], rtol=1e-8)


@pytest.mark.slow  # two compiled programs (90 s)
def test_derivative_of_a_sticking_node_with_a_prescribed_dof_is_reported_not_wrong():
    """The die clamps with friction while the strip's right end is held in x: the corner sticks with a
    prescribed dof, so its contact force cannot be told from the constraint's reaction, and the
    derivative comes out NaN in forward and reverse mode (jaxfric.contact.exact_derivative)."""
    from jaxfric.contact.rigid import Force, RigidTool
    from jaxfric.contact.tools import Tool

    def reaction(force):
        mesh = jf.strip_mesh(0.0, 4.0, 0.0, 0.395, 20, 2)
        material = jf.J2Material(E=69004.0, nu=0.3, sigma_y=80.55923, A=10000.0, n=0.216)
        die = Tool.line((-2.0, 0.395), (6.0, 0.395), normal_side="right")
        tool = RigidTool("die", die, drive=(0.0, -1.0), candidates=mesh.top, controls=(Force(force, start=0.0),),
                         mu=(MU,))
        bcs = [jf.DirichletBC(mesh.bottom, components=(1,)), jf.DirichletBC(mesh.right, components=(0,))]
        model = jf.StripModel(mesh, material, (jf.Phase("clamp", bcs, 5),), tools=(tool,),
                              contact=Complementarity("ssn"))
        return jf.simulate_fixed(model).history.observed["reaction_right"][5, 0]

    value, tangent = jax.jit(lambda f: jax.jvp(reaction, (f,), (1.0,)))(FORCE)
    assert np.isfinite(float(value)) and np.isnan(float(tangent))
    assert np.isnan(float(jax.jit(jax.grad(reaction))(FORCE)))


def _at_common_times(a, b, name):
    common, i, j = np.intersect1d(a.history["time"], b.history["time"], return_indices=True)
    return common, a.history[name][i], b.history[name][j]


@pytest.mark.slow  # about 30 s: three penalty runs and an AL run with 135 augmentations (make test-all)
def test_penalty_converges_to_the_exact_solution_and_the_augmented_lagrangian_reaches_it(runs):
    """Spec 8, algorithm limits: as eps_n grows (eps_t = mu eps_n), the penalty run approaches the
    exact one, its errors falling like 1/eps_n (the penetration P / (n eps_n) and the elastic slip of
    sticking pairs scale so); the augmented Lagrangian reaches the exact answer at the moderate
    eps_n = 1e5 by augmenting (target gap 1e-9 mm, which also bounds the stick slip)."""
    exact = runs["lcp_ssn"]
    errors = []
    for eps_n in (1e5, 1e6, 1e7):
        pen = jf.run(flat_die_strip(jf.Penalty(eps_n, MU * eps_n), **SMALL), progress=False)
        common, q_pen, q_ref = _at_common_times(pen, exact, "tool_position")
        _, f_pen, f_ref = _at_common_times(pen, exact, "reaction_right")
        assert common.size > 30
        errors.append((np.max(np.abs(q_pen - q_ref)), np.max(np.abs(f_pen[:, 0] - f_ref[:, 0]))))
    errors = np.array(errors)
    # Die position: the mean penetration P / (21 eps_n) at the end of the clamp, exactly 1/eps_n.
    assert errors[0, 0] == pytest.approx(FORCE / (21 * 1e5), rel=0.05)
    ratios = errors[:-1] / errors[1:]
    assert np.all(ratios > 5.0), errors     # one decade of eps_n: about one decade of error
    assert errors[-1, 1] < 1e-3 * MU * FORCE, errors
    al = jf.run(flat_die_strip(AugmentedLagrangian(1e5, MU * 1e5, target_gap=1e-9, max_augmentations=60), **SMALL),
                progress=False)
    common, q_al, q_ref = _at_common_times(al, exact, "tool_position")
    _, f_al, f_ref = _at_common_times(al, exact, "reaction_right")
    assert common.size > 30 and al.history["augmentations"].sum() > 0
    # Measured: 1.4e-11 mm and 3.1e-6 N/mm (4e-7 mu P), 135 augmentations in all.
    np.testing.assert_allclose(q_al, q_ref, atol=1e-10)
    np.testing.assert_allclose(f_al[:, 0], f_ref[:, 0], atol=1e-6 * MU * FORCE)


@pytest.mark.slow  # a clamp run and two step compilations, about a minute (make test-all)
def test_lemke_and_in_loop_semismooth_newton_agree_on_curved_tools():
    """The in-loop solver's node frames turn with the node on an arc (the derivative of (n, t) enters
    its rows): one frictional draw step over three cylinders, from the same clamped state, gives
    Lemke's displacements, forces and statuses."""

    from jaxfric.contact.rigid import Move, RigidTool
    from jaxfric.contact.tools import Tool

    R, pitch, t = 5.5, 11.97, 0.97
    mesh = jf.strip_mesh(-20.0, 40.0, 0.0, t, 60, 2)
    steel = jf.J2Material(E=200000.0, nu=0.3, sigma_y=171.0, A=121.74485, n=0.23)

    def tools(controls_b):
        below = dict(drive=(0.0, 1.0), candidates=mesh.bottom, controls=(Move(),) * len(controls_b), mu=0.17)
        return (RigidTool("A", Tool.circle((0.0, -R), R), **below),
                RigidTool("B", Tool.circle((pitch, t + R), R, seam=np.pi / 2), drive=(0.0, -1.0),
                          candidates=mesh.top, controls=controls_b, mu=0.17),
                RigidTool("C", Tool.circle((2 * pitch, -R), R), **below))

    clamp = jf.Phase("clamp", [jf.DirichletBC(mesh.right)], n_steps=15)
    draw = jf.Phase("draw", [jf.DirichletBC(mesh.right, motion=jf.Ramp((0.0, 0.0), (0.5, 0.0)))], n_steps=5)
    clamped = jf.run(jf.StripModel(mesh, steel, (clamp,), tools=tools((Move(0.0, 1.5),)),
                                   contact=Complementarity("ssn")), progress=False).final
    out = {}
    for solver in ("lemke", "ssn"):
        model = jf.StripModel(mesh, steel, (clamp, draw), tools=tools((Move(0.0, 1.5), Move())),
                              contact=Complementarity(solver))
        sol, new = jax.jit(lambda m, s: solve_step(m, s, 1, 1.2))(model, clamped)
        assert int(sol.code) == Result.SUCCESS
        out[solver] = new
    a, b = out["lemke"], out["ssn"]
    assert np.sum(np.asarray(a.contact.status) == 2) >= 2       # slipping pairs on the arcs
    np.testing.assert_allclose(a.u, b.u, atol=1e-10)
    scale = float(np.max(a.contact.rn))
    np.testing.assert_allclose(a.contact.rn, b.contact.rn, atol=1e-9 * scale)
    np.testing.assert_allclose(a.contact.rt, b.contact.rt, atol=1e-9 * scale)
    assert np.array_equal(a.contact.status, b.contact.status)


@pytest.mark.slow  # two blankholder runs of about 100 s each plus their compilations (make test-all)
def test_lemke_runs_the_blankholder_lock_and_agrees_with_semismooth_newton():
    """The blankholder's force-driven lock puts the sheet on its lands at zero gap and zero force and
    leaves stick-slip pairs at |R_T| = mu R_N: Lemke's answers there lay on piece boundaries within
    their round-off (and some failed their check), and its Newton loop stopped at t = 1.2 of 'lock'
    (iteration limit at the smallest increment). Refined (:func:`jaxfric.contact.alart_curnier.polish`), it runs
    close, lock and a 2 mm pull, with the tool balanced and the forces of semismooth Newton in the loop."""
    from jaxfric import scenes

    out = {}
    for algorithm in ("lcp_lemke", "lcp_ssn"):
        sc = scenes.make("blankholder", "shape1", algorithm, {"band": 256, "U_pull": 2.0})
        out[algorithm] = jf.run(sc.model, newton=sc.newton, control=sc.control, observe=sc.observe,
                                progress=False)
    a, b = out["lcp_lemke"], out["lcp_ssn"]
    assert a.converged and b.converged
    draw_a, draw_b = a.history["phase_name"] == "draw", b.history["phase_name"] == "draw"
    # The force-driven lower tool carries F_clamp = 300 N/mm throughout the draw.
    np.testing.assert_allclose(a.history["clamping_force"][draw_a], 300.0, rtol=1e-7)
    assert a.history["max_penetration"].max() < 1e-8
    # Same end of stroke: drawing force and the tool's position.
    np.testing.assert_allclose(a.history["drawing_force"][draw_a][-1], b.history["drawing_force"][draw_b][-1],
                               rtol=1e-3)
    np.testing.assert_allclose(a.history["tool_position"][-1], b.history["tool_position"][-1], atol=1e-4)
    assert a.history["lcp_pivots"].sum() > 0


def test_a_penetrating_node_whose_stick_piece_pulls_slips_instead_of_cycling():
    """Nine 60 x 2 at half the nominal clamp increment: at B's first touch a node penetrates by 3e-5
    mm; closed and sticking it would need a tensile force (-1.5e-4 N/mm), opened it keeps penetrating.
    The active set read off the prediction then cycled stick <-> open at every outer iteration and
    every cut step, and the run stopped in its fifth step. It now releases the node tangentially
    first (slip), and the run completes with every step settled."""
    from jaxfric import scenes

    sc = scenes.make("nine", "mu017", "lcp_ssn", {"mesh": "60x2", "stroke": 0.5, "dq_clamp": 0.05,
                                                  "U_draw": 0.2, "dU": 0.05})
    res = jf.run(sc.model, newton=sc.newton, control=sc.control, observe=sc.observe, progress=False,
                 raise_on_failure=False)
    assert res.converged, res.message
    assert res.history["max_penetration"].max() < 1e-10
    assert res.history["n_active"][-1] > 0          # B presses on the strip at the end of the clamp


def test_a_cycle_of_active_sets_ends_with_the_increment_of_all_its_passes(monkeypatch):
    """The blankholder's sheet pressed between its lands cycles through active sets within one
    linearised problem (semismooth Newton, ``lcp_ssn``). Recognised in the window of the last sets
    (:data:`jaxfric.contact.exact_active_set.CYCLE_WINDOW`), a cycle is cut short with the increment that
    all ``ssn_max_iter`` passes end on: the run is the run without the window (a window of one set sees
    no cycle) in every step's Newton iterations and every column, in fewer passes, with the same
    iterations left cycling. The columns and the final state agree to round-off, not bit for bit: the two
    runs are two XLA programs, which may fuse and round differently. Measured on one core at little
    optimisation with XLA's while-loop invariant code motion kept: 1.3e-13 of a force column's largest
    value from row 8 on, long before the first cycle (row 146); bit for bit with the fast suite's flags."""
    import equinox as eqx

    from jaxfric import scenes
    from jaxfric.contact import exact_active_set
    from jaxfric.loadpath.simulate import simulate

    sc = scenes.make("blankholder", "shape1", "lcp_ssn", {"nx": 40, "U_pull": 3.0})
    runs = []
    for window in (exact_active_set.CYCLE_WINDOW, 1):   # read when the program is traced
        monkeypatch.setattr(exact_active_set, "CYCLE_WINDOW", window)
        runs.append(eqx.filter_jit(lambda m: simulate(m, newton=sc.newton, control=sc.control,
                                                      observe=sc.observe))(sc.model))
    cut, full = runs
    assert int(cut.code) == int(full.code) == Result.SUCCESS
    n = int(full.history.n_rows)
    assert int(cut.history.n_rows) == n
    for name, column in full.history.observed.items():
        column = np.asarray(column[:n])
        np.testing.assert_allclose(cut.history.observed[name][:n], column, rtol=0,
                                   atol=1e-11 * np.max(np.abs(column)) + 1e-12, err_msg=name)
    np.testing.assert_allclose(cut.final.u, full.final.u, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(cut.history.newton_iters[:n], full.history.newton_iters[:n])
    passes_cut, passes_full = (np.asarray(r.history.solver_stats[:n]) for r in runs)
    np.testing.assert_array_equal(passes_cut[:, 2], passes_full[:, 2])     # iterations left cycling
    # Measured at the fast suite's XLA settings: 118 iterations left cycling, in the pull's last steps
    # (rows 146 to 167 of 172); 1723 passes against 6994.
    assert passes_full[:, 2].sum() > 0
    assert passes_cut[:, 1].sum() < 0.6 * passes_full[:, 1].sum()


@pytest.mark.slow  # the Nine at 300 x 3 to the end of its draw, about a minute (make test-all)
def test_line_search_merit_of_accepted_iterates_does_not_jump_up_between_directions():
    """The in-loop line search measures a trial with the forces its direction predicts, the hint the
    next direction's merit starts from. Measured with the direction's own hint, the merit of the same
    iterate rises 5 to 20 times at each new direction once a candidate node with a prescribed dof
    reaches shoulder A (the tail held by the left-end constraint, ``entry_guide_kind=end_nodes``), the
    iterates drift along the draw-in mode, and this run stops at U = 43.7 mm (Newton's limit at the
    smallest increment). It must complete."""
    from jaxfric.scenes import make

    scene = make("nine", "mu017", "lcp_ssn", {"dU": 0.4, "dq_clamp": 0.4, "entry_guide_kind": "end_nodes"})
    result = jf.run(scene.model, newton=jf.NewtonOptions(rtol=1e-5), control=scene.control,
                    observe=scene.observe, progress=False, raise_on_failure=False)
    assert result.converged, result.message
    assert result.history["drawing_displacement"][-1] == pytest.approx(70.0)


# Small curved-tool cases: the Nine's clamp and 1 mm of draw, the bead's wrap and 0.5 mm of draw, the
# blankholder's close, lock and 0.5 mm of pull (coarse meshes; one Lemke band holding every candidate
# near a tool).
COMMON_STEPS = {
    "nine": ("mu017", {"mesh": "60x2", "stroke": 3.0, "dq_clamp": 0.2, "U_draw": 1.0, "dU": 0.1}),
    "bead": ("th090_mu017", {"mesh": "120x2", "s_draw": 0.5, "ds": 0.1, "dtheta": 2.0}),
    "blankholder": ("shape1", {"element_length": 1.0, "U_pull": 0.5, "band": 256}),
}


# The bead's wind: at t = 1.0444 (history row 12) semismooth Newton cuts once (the iteration limit, 25) and
# takes the shorter step in 9 iterations. Lemke's full Newton steps invert an element there; line-searched
# (Complementarity(search=True), jaxfric.contact.exact step 6) it takes that step in 28 iterations. The
# replays search Lemke's steps and allow it 40 iterations, so that it takes the steps semismooth Newton
# took: what is compared is the solution, not the path to it.
LEMKE_ITERATIONS = 40


@pytest.mark.slow  # three scenes, two algorithms each: about four minutes of runs and compilations
@pytest.mark.parametrize("scene_name", list(COMMON_STEPS))
def test_semismooth_newton_equals_lemke_on_a_common_step_sequence(scene_name):
    """Spec 1.7 on whole paths: Lemke replays the accepted steps of the semismooth Newton run (their
    times become its nominal steps, :func:`jaxfric.fem.loading.with_steps`). It takes every step without a
    cut (its proximity band never saturates: a pair outside it that closes fails the attempt with
    CONTACT_BAND), and on every step the forces, the tool positions and the number of closed and slipping
    pairs equal semismooth Newton's to the solver tolerance. The steps where Lemke's answer needed the
    semismooth refinement (:func:`jaxfric.contact.alart_curnier.polish`) are counted in its ``ssn_iters``."""
    import equinox as eqx

    from jaxfric import scenes
    from jaxfric.fem.loading import with_steps

    variant, overrides = COMMON_STEPS[scene_name]
    ssn = scenes.make(scene_name, variant, "lcp_ssn", overrides)
    a = jf.run(ssn.model, newton=ssn.newton, control=ssn.control, observe=ssn.observe, progress=False)
    lemke = scenes.make(scene_name, variant, "lcp_lemke", overrides)
    h = a.history
    model = eqx.tree_at(lambda m: m.phases, lemke.model,
                        with_steps(lemke.model.phases, np.asarray(h["time"][1:]), np.asarray(h["phase"][1:])))
    model = eqx.tree_at(lambda m: m.contact, model, Complementarity("lemke", model.contact.band, search=True))
    newton = dataclasses.replace(lemke.newton, max_iterations=max(lemke.newton.max_iterations, LEMKE_ITERATIONS))
    b = jf.run(model, newton=newton, control=lemke.control, observe=lemke.observe, progress=False)
    g = b.history
    assert g["cutbacks"].sum() == 0 and np.array_equal(g["time"], h["time"])
    scale = float(np.max(np.abs(h["drawing_force"]))) + float(np.max(np.abs(h["clamping_force"])))
    for column in ("drawing_force", "clamping_force"):
        np.testing.assert_allclose(g[column], h[column], rtol=0, atol=1e-6 * scale, err_msg=column)
    np.testing.assert_allclose(g["tool_position"], h["tool_position"], rtol=0, atol=1e-8)
    np.testing.assert_array_equal(g["n_active"], h["n_active"])
    np.testing.assert_array_equal(g["n_slip"], h["n_slip"])
    assert g["lcp_pivots"].sum() > 0 and h["ssn_iters"].sum() > 0
    gap = max(float(np.max(np.abs(g[c] - h[c]))) for c in ("drawing_force", "clamping_force")) / scale
    print(f"{scene_name}: {len(h['time']) - 1} common steps, largest force difference {gap:.1e} of the "
          f"force scale; Lemke refined its answer on {int(np.sum(g['ssn_iters'] > 0))} of them")


@pytest.mark.parametrize("solver", ["ssn", "lemke"])
def test_the_exact_solvers_solve_the_damped_equilibrium_of_the_stabilised_attempt(runs, solver):
    """StepControl.stabilize with exact contact: with StepArgs.damping = eta the iterate's internal force
    gains eta (u - u_n) on the free dofs (u_n: the step's start) and its tangent eta on the diagonal,
    and a step solved that way is the damped problem's solution: at it the undamped residual of every
    free dof is -eta (u - u_n), with the contact forces the solver found; both solvers find the same one.
    The flat die's final state taken back to the middle of its draw, so that the step pushes the drawn
    end back by half the stroke (0.005 mm, on which the damper's force is 5 N/mm)."""
    import equinox as eqx

    from jaxfric.contact.exact_iterate import iterate_residual, linearize_iterate
    from jaxfric.loadpath.model import tool_positions
    from jaxfric.loadpath.step import StepContext, step_args, unknowns

    eta = 1e3
    model = flat_die_strip(Complementarity(solver), **SMALL)
    final = runs["lcp_ssn"].simulation.final
    state = eqx.tree_at(lambda s: s.time, final, jnp.asarray(1.5))
    ctx, t = StepContext.build(model), 1.51
    args = eqx.filter_jit(lambda damping: step_args(model, state, 1, t, ctx, damping=damping)[0])
    plain, damped = args(None), args(jnp.asarray(eta))
    x_n = unknowns(model, state.u, tool_positions(state))
    n, free = model.mesh.n_dofs, ~np.asarray(plain.mask)

    x = x_n + 1e-4 * jnp.sin(jnp.arange(x_n.size, dtype=float))
    # Both iterates from one program, so that their element forces round alike and the difference is the
    # damper's term alone: compiled apart, at the fast suite's XLA settings, the two programs' element forces
    # differed by 1.5e-13 of the largest force, above the tolerance below.
    it0, it1 = eqx.filter_jit(lambda x: (linearize_iterate(x, plain), linearize_iterate(x, damped)))(x)
    expected = np.where(free, eta * np.asarray(x[:n] - x_n[:n]), 0.0)
    np.testing.assert_allclose(np.asarray(it1.f_int - it0.f_int).reshape(-1), expected, rtol=0,
                               atol=1e-13 * float(jnp.max(jnp.abs(it0.f_int))))
    np.testing.assert_allclose(np.asarray(it1.K.to_dense() - it0.K.to_dense()), eta * np.eye(n), rtol=0,
                               atol=1e-9 * eta)

    sol, new = eqx.filter_jit(lambda s: solve_step(model, s, 1, t, ctx=ctx, damping=eta))(state)
    assert int(sol.code) == Result.SUCCESS
    x_new = unknowns(model, new.u, tool_positions(new))
    du = np.asarray(x_new[:n] - x_n[:n])
    assert np.max(np.abs(du)) > 4e-3
    p = jnp.stack([new.contact.rn, new.contact.rt], -1)
    residual = eqx.filter_jit(lambda y: iterate_residual(y, linearize_iterate(y, plain), p, plain)[0])(x_new)
    tol = 1e-7 * float(jnp.max(jnp.abs(new.f_int)))
    np.testing.assert_allclose(np.asarray(residual[:n])[free], -eta * du[free], rtol=0, atol=tol)
    other = flat_die_strip(Complementarity("lemke" if solver == "ssn" else "ssn"), **SMALL)
    _, new_other = eqx.filter_jit(lambda s: solve_step(other, s, 1, t, ctx=StepContext.build(other),
                                                       damping=eta))(state)
    np.testing.assert_allclose(np.asarray(new_other.u), np.asarray(new.u), rtol=0, atol=1e-10)
