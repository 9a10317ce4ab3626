"""Friction laws of pressure and speed (jaxfric.contact.friction): the laws, the pressure of a pair, the
pair force and its tangent, every formulation on the flat die, the speed's limits, the parameters'
derivatives, and the errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfric import scenes
from jaxfric.cards.friction import friction_csv, lsdyna_friction, radioss_friction
from jaxfric.contact.friction import Polynomial, VelocityDecay, sliding_speed, tributary_lengths
from jaxfric.contact.laws import augmented_pair
from jaxfric.identification.params import parameterize, path_function
from jaxfric.loadpath.run import run as run_model
from jaxfric.numerics.newton import NewtonOptions

LAW = {"friction_law": "polynomial", "mu_p": -0.004, "mu_pp": 2e-5}
SMALL = {"mesh": "24x2"}


def run(scene):
    return run_model(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe, progress=False)


def test_law_values_clip_and_frictionless_phase():
    law = Polynomial(c_p=-0.01, c_v=0.002, c_pv=1e-4, c_pp=1e-4, c_vv=-1e-5)
    p, v = jnp.array([0.0, 5.0, 50.0]), jnp.array([0.0, 10.0, 10.0])
    expected = [0.15, 0.15 - 0.05 + 0.02 + 0.005 + 0.0025 - 0.001, 0.0]
    np.testing.assert_allclose(law.coefficient(0.15, p, v), expected, atol=1e-15)
    # A phase without friction stays without it, whatever the law's terms.
    assert float(law.coefficient(0.0, 3.0, 1.0)) == 0.0
    assert Polynomial(0.002).describe() == {"law": "polynomial", "c_p": 0.002, "c_v": 0.0, "c_pv": 0.0,
                                             "c_pp": 0.0, "c_vv": 0.0, "period": 0.0}
    decay = VelocityDecay(0.1, 0.5)
    np.testing.assert_allclose(decay.coefficient(0.2, 7.0, jnp.array([0.0, 2.0, 1e3])),
                               [0.2, 0.1 + 0.1 * np.exp(-1.0), 0.1], rtol=1e-14)
    assert float(sliding_speed(-2e-4, 1e-4)) == pytest.approx(2.0) and float(sliding_speed(1e-3, 0.0)) == 0.0
    # The filter: a rate held over a step of one period closes 1 - 1/e of the way from the last speed.
    assert float(sliding_speed(-2e-4, 1e-4, 5.0, 1e-4)) == pytest.approx(2.0 + 3.0 / np.e, rel=1e-14)
    assert float(sliding_speed(1e-3, 0.0, 5.0, 1e-4)) == 0.0


@pytest.mark.xla_optimized   # mostly run time (tests/conftest.py)
def test_steady_sliding_reads_the_drawing_speed():
    """The flat die slides as a whole at the drawing speed, so its steady drawing force is mu(v) F_clamp
    with v = draw_speed, for a coefficient rising with speed (mu = 0.12 + 0.01 v). Through the default
    speed filter (5 ms) it is, at 0.5 and 2 mm/s, to 1e-4 (measured 5e-5 at 2 mm/s: the filter's approach
    after 0.1 mm of drawing); reading each step's raw rate instead (period 0),
    the stuck pairs alternate between rest and twice the speed, and the force between two values below
    mu(v) F_clamp (measured at 1 mm/s: 6.02 and 6.09 N/mm for 6.5; jaxfric.contact.friction)."""
    law = {**SMALL, "friction_law": "polynomial", "mu": 0.12, "mu_v": 0.01, "F_clamp": 50.0, "U_draw": 0.1}
    for v in (0.5, 2.0):
        force = run(scenes.make("flat_die", "const_force", "lcp_ssn", {**law, "draw_speed": v}))
        force = force.history["drawing_force"]
        assert force[-20:] == pytest.approx(np.full(20, (0.12 + 0.01 * v) * 50.0), rel=1e-4), v
    raw = run(scenes.make("flat_die", "const_force", "lcp_ssn", {**law, "draw_speed": 1.0, "speed_period": 0.0}))
    tail = np.asarray(raw.history["drawing_force"])[-20:]
    assert np.all(np.abs(np.diff(tail)) > 0.05) and np.max(tail) < 0.95 * 0.13 * 50.0


def test_tributary_lengths_of_a_graded_row():
    x = np.array([0.0, 1.0, 3.0, 6.0])
    X = np.stack([x, np.zeros_like(x)], -1)
    np.testing.assert_allclose(tributary_lengths(X), [0.5, 1.5, 2.5, 1.5])
    assert float(jnp.sum(tributary_lengths(X))) == 6.0


def test_pair_law_slips_at_the_pressure_coefficient_and_its_tangent_is_the_derivative():
    law, length, mu0 = Polynomial(c_p=-0.004, c_pp=2e-5), 0.5, 0.15
    eps_n, eps_t = 1e5, 1.5e4

    def force(gap, slip):
        out = augmented_pair(gap, slip, 0.0, 0.0, lambda rn: law.coefficient(mu0, rn / length, 0.0), eps_n, eps_t)
        return jnp.stack([out.normal, out.tangential])

    gap, slip = -2e-4, -1e-3                     # R_N = 20 N/mm, p = 40 MPa; slipping
    f = force(gap, slip)
    p = float(f[0]) / length
    assert float(f[1]) == pytest.approx((mu0 - 0.004 * p + 2e-5 * p * p) * float(f[0]), rel=1e-14)
    jac = jax.jacfwd(lambda z: force(z[0], z[1]))(jnp.array([gap, slip]))
    h = 1e-9
    fd = np.stack([(force(gap + h, slip) - force(gap - h, slip)) / (2 * h),
                   (force(gap, slip + h) - force(gap, slip - h)) / (2 * h)], -1)
    np.testing.assert_allclose(jac, fd, rtol=1e-6, atol=1e-6)
    # d R_T / d gap carries d mu / dp: it differs from Coulomb's mu0 d R_N / d gap.
    assert abs(float(jac[1, 0]) - np.sign(float(f[1])) * mu0 * float(jac[0, 0])) > 1e2


@pytest.fixture(scope="module")
def flat_die_runs():
    out = {}
    for algorithm in ("penalty", "auglag", "lcp_ssn", "lcp_lemke"):
        out[algorithm] = run(scenes.make("flat_die", None, algorithm, {**SMALL, **LAW}))
    out["coulomb"] = run(scenes.make("flat_die", None, "lcp_ssn", SMALL))
    return out


def _steady(res):
    return float(res.history["drawing_force"][-1])


def test_every_formulation_meets_the_law_at_its_forces(flat_die_runs):
    law = Polynomial(c_p=LAW["mu_p"], c_pp=LAW["mu_pp"])
    ref = _steady(flat_die_runs["lcp_ssn"])
    for algorithm in ("penalty", "auglag", "lcp_ssn", "lcp_lemke"):
        res = flat_die_runs[algorithm]
        assert res.converged, (algorithm, res.message)
        # The exact algorithms agree to the Newton tolerance, the regularised ones to their penalty's effect.
        assert _steady(res) == pytest.approx(ref, rel=1e-8 if algorithm.startswith("lcp") else 1e-3), algorithm
        final = res.final.contact
        X = np.asarray(res.model.mesh.nodes)[np.asarray(res.model.tools[0].candidates)]
        rn, rt = np.asarray(final.rn), np.asarray(final.rt)
        mu = np.asarray(law.coefficient(0.15, rn / np.asarray(tributary_lengths(X)), 0.0))
        slip = np.asarray(final.status) == 2
        assert slip.sum() > 10
        np.testing.assert_allclose(np.abs(rt[slip]), mu[slip] * rn[slip], rtol=1e-7, atol=1e-9, err_msg=algorithm)
    # The pressure terms are felt: the decreasing law draws with less force than Coulomb's mu0.
    assert _steady(flat_die_runs["coulomb"]) - ref > 0.05 * _steady(flat_die_runs["coulomb"])


def test_zero_pressure_terms_give_the_coulomb_run(flat_die_runs):
    res = run(scenes.make("flat_die", None, "lcp_ssn", {**SMALL, "friction_law": "polynomial"}))
    # Two programs (one evaluates the law) whose Newton solves stop at rtol 1e-8 of the force scale: they
    # agree to round-off, 1.2e-11 N/mm with XLA's multi-threaded reductions on 2 workers.
    np.testing.assert_allclose(res.history["drawing_force"], flat_die_runs["coulomb"].history["drawing_force"],
                               rtol=1e-9, atol=1e-10)


def test_speed_limits_of_the_decay_law_are_coulomb_runs():
    """A decay of 0 is Coulomb's mu; a decay far above 1 / v slides at mu_d (the flat die slides at about
    draw_speed): both equal Coulomb runs of those coefficients."""
    coulomb = {mu: _steady(run(scenes.make("flat_die", None, "lcp_ssn", {**SMALL, "mu": mu}))) for mu in (0.15, 0.09)}
    decay = {"friction_law": "velocity_decay", "mu_d": 0.09}
    static = _steady(run(scenes.make("flat_die", None, "lcp_ssn", {**SMALL, **decay, "decay": 0.0})))
    fast = _steady(run(scenes.make("flat_die", None, "penalty", {**SMALL, **decay, "decay": 20.0})))
    assert static == pytest.approx(coulomb[0.15], rel=1e-10)
    assert fast == pytest.approx(coulomb[0.09], rel=1e-3)
    # At a hundredth of the speed the same law has decayed less: the force lies between the two. The
    # phases' durations are data: the slower run is the faster one's program (compiled in seconds, found
    # in about a millisecond).
    slow_run = run(scenes.make("flat_die", None, "penalty", {**SMALL, **decay, "decay": 20.0, "draw_speed": 0.01}))
    assert coulomb[0.09] * 1.01 < _steady(slow_run) < coulomb[0.15]
    assert slow_run.compile_s < 0.05


def _last_force_derivatives(par, algorithm: str, steps) -> tuple[np.ndarray, np.ndarray]:
    """The last drawing force's derivatives by forward mode through the whole path, and by central
    differences with the steps ``steps`` (one per parameter); the exact path with Newton's increment test at
    1e-6 (the test below says why)."""
    f = path_function(par, newton=NewtonOptions(du_rtol=1e-6, max_iterations=60) if algorithm == "lcp_ssn" else None)

    def force(p):
        hist, _ = f(p)
        return hist.observed["drawing_force"][hist.n_rows - 1]

    # One compiled program gives both: the forward derivative along a unit vector, and the values at the
    # shifted parameters (along a zero tangent).
    with_tangent = jax.jit(lambda p, v: jax.jvp(force, (p,), (v,)))
    p0 = jnp.asarray(par.p0)
    unit = np.eye(len(steps))
    grad = np.array([float(with_tangent(p0, jnp.asarray(e))[1]) for e in unit])
    zero = jnp.zeros(len(steps))
    fd = [(float(with_tangent(p0 + h * e, zero)[0]) - float(with_tangent(p0 - h * e, zero)[0])) / (2 * h)
          for h, e in zip(steps, unit, strict=True)]
    return grad, np.array(fd)


DECAY = {"friction_law": "velocity_decay", "mu": 0.18, "mu_d": 0.1, "decay": 1.0, "F_clamp": 50.0, "U_draw": 0.1,
         "draw_speed": 1.0}


@pytest.mark.slow
@pytest.mark.parametrize("algorithm", ["penalty", "auglag", "lcp_ssn", "lcp_lemke"])
def test_every_formulation_slides_at_the_decay_law_s_coefficient(algorithm):
    """The speed law on every contact formulation: the flat die slides as a whole at 1 mm/s, so its steady
    drawing force is mu(1) F_clamp = (0.1 + 0.08 e^-1) 50 N/mm, to 1e-4 (the speed filter's approach, as
    for the pressure-and-speed polynomial above)."""
    res = run(scenes.make("flat_die", "const_force", algorithm, {**SMALL, **DECAY}))
    assert res.converged, res.message
    expected = (0.1 + 0.08 * np.exp(-1.0)) * 50.0
    assert res.history["drawing_force"][-20:] == pytest.approx(np.full(20, expected), rel=1e-4)


@pytest.mark.slow
@pytest.mark.parametrize("algorithm", ["penalty", "lcp_ssn"])
def test_derivatives_of_the_decay_law_s_parameters_match_central_differences(algorithm):
    """d(drawing force)/d(mu_0, mu_d, decay) at the end of the slide, forward mode through the whole path
    against central differences (the Newton increment test at 1e-6 on the exact path, as above)."""
    par = parameterize("flat_die", ["mu", "mu_d", "decay"], variant="const_force", algorithm=algorithm,
                       overrides={**SMALL, **DECAY})
    grad, fd = _last_force_derivatives(par, algorithm, (1e-6, 1e-6, 1e-6))
    for i, name in enumerate(par.names):
        assert grad[i] == pytest.approx(fd[i], rel=1e-5), name
    # At v = 1 mm/s: dF/dmu_0 = e^-1 F_clamp, dF/dmu_d = (1 - e^-1) F_clamp, dF/ddecay = -(mu_0 - mu_d) e^-1 F_clamp.
    np.testing.assert_allclose(grad, np.array([np.exp(-1.0), 1.0 - np.exp(-1.0), -0.08 * np.exp(-1.0)]) * 50.0,
                               rtol=1e-3)


@pytest.mark.parametrize("algorithm", ["penalty", "lcp_ssn"])
def test_derivatives_of_the_law_parameters_match_central_differences(algorithm):
    """Forward mode through the whole path against central differences, for the law's constant, pressure
    and speed terms; on the exact path the slip rows' derivative holds mu'(R_N) R_N, and the flat die's
    corner D (slipping with its prescribed dof) takes its force from its free dof's equilibrium
    (jaxfric.contact.exact_derivative). The exact solver takes each iteration's coefficients at the last
    iteration's forces, so at Newton's default increment test the converged force still lags mu(R_N)
    by the last correction, and central differences see that lag (measured: mu_v's derivative 2.1e-5
    from them, mu_p's 4e-6); with the increment test at 1e-6 they agree to 2e-6 and 3e-7."""
    par = parameterize("flat_die", ["mu", "mu_p", "mu_v"], algorithm=algorithm,
                       overrides={**SMALL, **LAW, "mu_v": -0.01, "U_draw": 0.01})
    grad, fd = _last_force_derivatives(par, algorithm, (1e-6, 1e-7, 1e-6))
    for i, name in enumerate(par.names):
        assert grad[i] == pytest.approx(fd[i], rel=1e-5), name
    assert np.all(np.abs(grad) > 1.0)    # every parameter is felt (N/mm per unit)


@pytest.mark.parametrize("overrides, field", [
    ({"mu_p": 0.01}, "mu_p"),
    ({"friction_law": "polynomial", "mu_pp": float("nan")}, "mu_pp"),
    ({"mu_d": 0.1}, "mu_d"),
    ({"friction_law": "velocity_decay", "decay": -1.0}, "decay"),
    ({"friction_law": "velocity_decay", "draw_speed": 0.0}, "draw_speed"),
    ({"friction_law": "velocity_decay", "speed_period": -1e-3}, "speed_period"),
    ({"friction_law": "stribeck"}, "friction_law"),
])
def test_bad_friction_fields_name_the_field(overrides, field):
    with pytest.raises(ValueError, match=field):
        scenes.make("flat_die", None, "penalty", {**SMALL, **overrides})


def _fields(line: str, widths) -> list[str]:
    out, at = [], 0
    for w in widths:
        out.append(line[at:at + w].strip())
        at += w
    return out


def test_openradioss_friction_card_reads_back_to_the_law():
    """/FRICTION with Ifric = 1 (OpenRadioss's generalised viscous law): the integers in fields of 10
    characters and Xfreq in 20, then C1 .. C5 and C6, Fric, VISF in fields of 20."""
    law = Polynomial(c_p=-0.004, c_v=0.0012, c_pv=-3e-5, c_pp=2e-5, c_vv=-1e-6)
    text = radioss_friction(law, 0.18, fric_id=7, title="test")
    lines = [line for line in text.splitlines() if not line.startswith("#")]
    assert lines[0] == "/FRICTION/7" and lines[1] == "test"
    ifric, ifiltr, xfreq, iform = _fields(lines[2], (10, 10, 20, 10))
    assert (int(ifric), int(ifiltr), xfreq, iform) == (1, 0, "", "")
    c = [float(v) for v in _fields(lines[3], (20,) * 5)]
    c6, fric, visf = _fields(lines[4], (20, 20, 20))
    assert float(c6) == 0.0 and float(fric) == 0.18 and visf == ""
    np.testing.assert_allclose(c, [-0.004, 0.0012, -3e-5, 2e-5, -1e-6], rtol=1e-12)
    # The card's law is the simulator's: mu = Fric + C1 p + C2 v + C3 p v + C4 p^2 + C5 v^2.
    p, v = 12.0, 3.0
    card_mu = float(fric) + c[0] * p + c[1] * v + c[2] * p * v + c[3] * p * p + c[4] * v * v
    assert card_mu == pytest.approx(float(law.coefficient(0.18, p, v)), rel=1e-12)


def test_openradioss_friction_card_of_the_decay_law_reads_back_to_the_law():
    """/FRICTION with Ifric = 4 (OpenRadioss's exponential decay mu = C1 + (Fric - C1) exp(-C2 v)): Fric the
    static coefficient, C1 the dynamic one, C2 the decay (s/mm); C3 .. C6 unused."""
    law = VelocityDecay(0.11, 0.35)
    lines = [line for line in radioss_friction(law, 0.17, fric_id=3).splitlines() if not line.startswith("#")]
    assert lines[0] == "/FRICTION/3"
    assert int(_fields(lines[2], (10, 10, 20, 10))[0]) == 4
    c = [float(v) for v in _fields(lines[3], (20,) * 5)]
    fric = float(_fields(lines[4], (20, 20, 20))[1])
    assert fric == 0.17 and c == [0.11, 0.35, 0.0, 0.0, 0.0]
    for v in (0.0, 1.0, 4.0):
        card_mu = c[0] + (fric - c[0]) * np.exp(-c[1] * v)
        assert card_mu == pytest.approx(float(law.coefficient(0.17, 20.0, v)), rel=1e-14)
    with pytest.raises(ValueError, match="law"):
        radioss_friction(object(), 0.18)


def test_lsdyna_friction_card_reads_back_to_the_decay_law():
    """Card 2 of *CONTACT_...: FS FD DC in fields of 10 (mu = FD + (FS - FD) exp(-DC v))."""
    law = VelocityDecay(0.11, 0.35)
    lines = [line for line in lsdyna_friction(law, 0.17).splitlines() if not line.startswith("$")]
    fs, fd, dc = (float(v) for v in _fields(lines[0], (10, 10, 10)))
    assert (fs, fd, dc) == (0.17, 0.11, 0.35)
    v = 2.5
    assert fd + (fs - fd) * np.exp(-dc * v) == pytest.approx(float(law.coefficient(0.17, 1.0, v)), rel=1e-14)
    with pytest.raises(ValueError, match="velocity decay only"):
        lsdyna_friction(Polynomial(c_p=0.01), 0.17)
    table = friction_csv(Polynomial(c_p=-0.004), 0.18, 20.0, n=5).splitlines()
    assert table[1] == "contact pressure (MPa),friction coefficient (-)"
    np.testing.assert_allclose([float(r.split(",")[1]) for r in table[2:]], [0.18, 0.16, 0.14, 0.12, 0.10])


def test_fits_let_a_friction_law_s_terms_go_negative():
    from jaxfric.identification.fit import check_bounds
    lo, hi = check_bounds(("mu", "mu_p", "mu_v"), np.array([0.15, 0.0, 0.0]), None)
    assert lo.tolist() == [0.0, -np.inf, -np.inf] and np.all(np.isinf(hi))
