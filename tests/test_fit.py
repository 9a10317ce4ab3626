"""Identification (``jaxfric fit`` and :func:`jaxfric.identification.fit.fit`) and differentiable scene parameters.

The fast case is the flat die at 24 x 1 (0.7 s a run): drawing the clamped sheet, the force rises
through the elastic stick range (slope set by E) to the sliding plateau mu F_clamp. The measurement is
the run's own ``history.csv``, so the fit must return the values it was made with. The Nine
identification of the issue (mu = 0.17 from synthetic data, with and without noise) is
``experiments/identify_nine.py`` (results in docs/results.md, identification); the slow test below runs
its noise-free case.
"""

import json
import os

import numpy as np
import pytest

from jaxfric import scenes
from jaxfric.cli import main
from jaxfric.identification.fit import bin_means, fit, read_measurement
from jaxfric.identification.params import parameterize

FLAT = ["flat_die", "--variant", "const_force", "--mesh", "24x1"]


@pytest.fixture(scope="module")
def flat_history(tmp_path_factory):
    out = tmp_path_factory.mktemp("flat_run")
    # The fit's model (exact contact, the default of "run" and "fit") generates the data.
    assert main(["run", *FLAT, "--quiet", "--out", str(out)]) == 0
    return os.path.join(out, "history.csv")


def test_cli_fit_recovers_mu_from_a_run_history(flat_history, tmp_path, capsys):
    # With a global stage (one fit serves both checks: the fit is the slow part): three runs at
    # mu = 0.04, 0.17, 0.3, none of them the truth 0.15. The plateau force is mu F_clamp, linear in mu,
    # so the interpolated misfit has its minimum near the truth; not at it, since the force before
    # full sliding is not linear in mu (measured start: 0.1525).
    out = tmp_path / "fit"
    code = main(["fit", *FLAT, "--data", flat_history, "--param", "mu", "--set", "mu=0.1", "--quiet",
                 "--bounds", "mu=0:1", "--grid", "mu=0.04:0.3:3", "--starts", "2", "--model-error", "mesh",
                 "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    summary = json.loads((out / "fit.json").read_text())
    assert summary["converged"]
    # Noise-free data from the same model: the misfit vanishes at the true value, to solver tolerance.
    assert abs(summary["params"]["mu"] - 0.15) < 1e-7
    assert summary["stderr"]["mu"] < 1e-6
    assert summary["n_simulations"] >= 3 + 3 and summary["wall_s"] > 0
    assert (out / "fit.png").stat().st_size > 10_000
    assert "mu = 0.15" in capsys.readouterr().out
    stage = summary["global_stage"]
    assert {k: stage[k] for k in ("points", "failed", "file")} == {"points": 3, "failed": 0, "file": "fit_grid.csv"}
    # One basin: --starts 2 finds one minimum of the interpolated misfit, so one local fit.
    assert len(stage["local_fits"]) == 1 and stage["local_fits"][0]["end"]["mu"] == summary["params"]["mu"]
    grid = (out / "fit_grid.csv").read_text().splitlines()
    assert grid[0] == "mu,cost,converged" and len(grid) == 4
    assert all(float(line.split(",")[1]) > 0 for line in grid[1:])
    assert summary["start"]["mu"] not in (0.04, 0.17, 0.3) and abs(summary["start"]["mu"] - 0.15) < 0.01
    assert summary["start"]["mu"] != pytest.approx(0.15, abs=1e-6)  # interpolated, not the truth itself
    # The model's error, from the run at twice the elements along: the sliding plateau, mu F_clamp, does
    # not depend on the mesh, so the error in mu is tiny (measured 3e-8 with data from 48 x 2), and
    # the widened interval holds the noise-free one.
    error = summary["model_error"]
    assert set(error["components"]) == {"mesh"} and abs(error["bias"]["mu"]) < 1e-6
    (lo, hi), (mlo, mhi) = summary["ci95"]["mu"], error["ci95"]["mu"]
    assert mlo <= lo < hi <= mhi and error["max_observation_error"] > 0


def test_interpolated_minimum_follows_a_narrow_valley_between_grid_points():
    # Observations linear in (a, b) and nearly compensating (a valley along a = 0.15 b): multilinear
    # interpolation is exact for them, so the polished minimum is the truth, which lies on no grid line
    # and between the evaluation points; a grid-point minimum would miss it by half a cell.
    from jaxfric.identification.fit_global import surrogate_minima

    axes = [np.linspace(0.10, 0.25, 7), np.linspace(5.07, 5.97, 9)]
    A = np.array([[900.0, -130.0], [1000.0, -160.0], [800.0, -100.0]])
    truth = np.array([0.1713, 5.4987])
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 2)
    (best, cost), = surrogate_minima(axes, pts @ A.T, A @ truth, 1)
    np.testing.assert_allclose(best, truth, atol=1e-6)
    assert cost < 1e-6
    # A failed run (NaN) removes the cells around it, never the whole grid.
    obs = pts @ A.T
    obs[0] = np.nan
    np.testing.assert_allclose(surrogate_minima(axes, obs, A @ truth, 1)[0][0], truth, atol=1e-6)


def test_interpolated_minima_of_two_basins_lowest_first():
    # Observations with two basins of the misfit in a, at 0.3 (misfit 0) and near 0.74 (the second
    # observation lifts it), both at b = 0.5: lowest first, each polished to its own minimum.
    from jaxfric.identification.fit_global import surrogate_minima

    axes = [np.linspace(0.0, 1.0, 21), np.linspace(0.0, 1.0, 11)]
    a, b = np.meshgrid(*axes, indexing="ij")
    obs = np.stack([(a - 0.3) * (a - 0.75), 0.1 * (a - 0.3) ** 2, b - 0.5], -1).reshape(-1, 3)
    minima = surrogate_minima(axes, obs, np.zeros(3), 3)
    assert len(minima) == 2
    (p1, c1), (p2, c2) = minima
    assert c1 <= c2 and c1 < 1e-8
    np.testing.assert_allclose(p1, [0.3, 0.5], atol=2e-3)
    assert abs(p2[0] - 0.74) < 0.01 and abs(p2[1] - 0.5) < 2e-3 and c2 > 1e-4
    # One start asked for: the lowest only.
    np.testing.assert_allclose(surrogate_minima(axes, obs, np.zeros(3), 1)[0][0], p1)


def test_several_starts_are_written_and_the_kept_one_is_plotted(tmp_path):
    # write_fit on a result of two local fits (built by hand: a real one costs two planned fits).
    from jaxfric.identification.fit import FitResult, Measurement, write_fit

    x = np.linspace(0.1, 1.0, 10)
    rows = [{"iteration": i, "accepted": True, "cost": c, "damping": 1e-3, "mu": m, "start": n}
            for n, track in ((1, [(2.0, 0.2), (1.0, 0.18)]), (2, [(0.5, 0.16), (1e-3, 0.15)]))
            for i, (c, m) in enumerate(track)]
    local = [{"number": 1, "start": {"mu": 0.2}, "end": {"mu": 0.18}, "cost": 1.0, "converged": True,
              "message": "converged"},
             {"number": 2, "start": {"mu": 0.16}, "end": {"mu": 0.15}, "cost": 1e-3, "converged": True,
              "message": "converged"}]
    grid = [{"mu": v, "cost": c, "converged": True} for v, c in ((0.1, 3.0), (0.2, 2.0), (0.3, 5.0))]
    res = FitResult(scene="flat_die", variant="const_force", algorithm="penalty", overrides={}, names=("mu",),
                    params={"mu": 0.15}, stderr={"mu": 1e-3}, ci95={"mu": (0.148, 0.152)}, start={"mu": 0.16},
                    bounds={"mu": (0.0, 1.0)}, window=None, covariance=np.array([[1e-6]]), residual_rms=0.01,
                    cost=1e-3, n_points=10, n_simulations=9, n_replans=0, wall_s=1.0, converged=True,
                    message="converged", iterations=rows, measurement=Measurement(x, 7.5 * x), fitted_force=7.5 * x,
                    start_force=7.0 * x, grid=grid, local_fits=local)
    summary = write_fit(res, str(tmp_path))
    assert [lf["number"] for lf in summary["global_stage"]["local_fits"]] == [1, 2]
    assert json.loads((tmp_path / "fit.json").read_text())["global_stage"]["local_fits"][1]["cost"] == 1e-3
    history = (tmp_path / "fit_history.csv").read_text().splitlines()
    assert history[0].split(",")[-1] == "start" and len(history) == 5
    assert (tmp_path / "fit.png").stat().st_size > 10_000


@pytest.mark.slow
def test_fit_with_noise_reports_an_interval_that_holds_the_truth(flat_history):
    meas = read_measurement(flat_history)
    rng = np.random.default_rng(3)
    noisy = {"drawing_displacement": meas.displacement,
             "drawing_force": meas.force + 0.01 * 7.5 * rng.standard_normal(meas.force.size)}
    res = fit("flat_die", noisy, ["mu"], variant="const_force", overrides={"mesh": "24x1", "mu": 0.1},
              progress=False)
    assert res.converged
    lo, hi = res.ci95["mu"]
    assert lo < 0.15 < hi
    # 1 % noise on ~380 points: the interval is narrow.
    assert hi - lo < 2e-3
    assert res.residual_rms == pytest.approx(0.075, rel=0.2)


def test_one_parameter_jacobian_is_the_jacfwd_one():
    """The curve's Jacobian for one parameter (a JVP, not ``jax.jacfwd``'s vmap of it) has jacfwd's shape
    (m, 1), values and aux; for two parameters it is jacfwd's."""
    import jax
    import jax.numpy as jnp

    from jaxfric.identification.fit_curve import forward_jacobian

    def curve(p, scale):
        obs = jnp.stack([scale * p[0] ** 2, jnp.sin(p[0]), p[0] * p[-1]])
        return obs, (obs, scale)

    for p in (jnp.array([0.3]), jnp.array([0.3, 2.0])):
        jac, (obs, scale) = forward_jacobian(curve, p.shape[0])(p, 2.0)
        ref, (obs_ref, _) = jax.jacfwd(curve, has_aux=True)(p, 2.0)
        assert jac.shape == ref.shape == (3, p.shape[0])
        np.testing.assert_allclose(jac, ref, rtol=1e-14)
        np.testing.assert_allclose(obs, obs_ref, rtol=0)
        assert scale == 2.0
    np.testing.assert_allclose(forward_jacobian(curve, 1)(jnp.array([0.3]), 2.0)[0][:, 0],
                               [1.2, np.cos(0.3), 0.6], rtol=1e-14)


def test_the_curve_traces_the_exact_steps_derivative_once(monkeypatch):
    """The replay's loop carry is anchored to the parameters' tangents (``tangent_anchor``), so that JAX's
    while-loop JVP finds its nonzero tangents in one pass and traces the step's derivative (the exact
    path's implicit tangents) once, not twice; the anchor changes no value, signed zeros included."""
    import jax
    import jax.numpy as jnp

    from jaxfric.contact import exact
    from jaxfric.identification.fit_curve import curve_function, forward_jacobian, replay_options
    from jaxfric.identification.params import plan_steps
    from jaxfric.loadpath.simulate import tangent_anchor

    anchor = tangent_anchor(jnp.array([0.3, -2.0]))
    assert float(anchor) == 0.0 and np.signbit(anchor)
    x = jnp.array([-0.0, 0.0, 1e-300, -3.5])
    assert np.array_equal(np.signbit(x + anchor), np.signbit(x)) and np.array_equal(x + anchor, x)

    traced = []
    tangents = exact.exact_step_tangents
    monkeypatch.setattr(exact, "exact_step_tangents", lambda *a: traced.append(1) or tangents(*a))
    par = parameterize("flat_die", ["mu"], variant="const_force", algorithm="lcp_ssn",
                       overrides={"mesh": "6x1", "U_draw": 0.003})
    plan = {"time": np.array([0.0, 0.5, 1.0, 1.5, 2.0]), "phase": np.array([0, 0, 0, 1, 1])}
    curve = curve_function(par, np.array([0.001, 0.002]), None, replay_options(par))
    jax.make_jaxpr(forward_jacobian(curve, 1))(jnp.asarray(par.p0), plan_steps(par, plan))
    assert len(traced) == 1


def test_bin_means_are_exact_for_a_piecewise_linear_curve():
    x = np.array([0.0, 0.0, 1.0, 3.0])
    f = np.array([5.0, 0.0, 2.0, 2.0])
    # Mean over [0.5, 2.0]: integral of the interpolant (0.5 * (1 + 2) * 0.5 + 2 * 1) / 1.5.
    np.testing.assert_allclose(bin_means(x, f, np.array([0.5, 2.0, 3.0])), [2.75 / 1.5, 2.0])


@pytest.mark.parametrize("scene, variant, names", [
    ("nine", "mu017", ["mu", "R1"]), ("nine", "mu017", ["stroke", "sigma_y"]),
    ("bead", "th090_mu017", ["R_r", "mu_roller", "F_clamp"]),
    ("blankholder", "shape3", ["R", "H", "mu", "F_clamp"]),
    ("flat_die", "const_force", ["mu", "F_clamp", "E"]),
])
def test_parameterized_model_equals_the_built_model(scene, variant, names):
    """The affine splice reproduces the scene built at other values exactly (every array leaf but the
    nominal increments, which the parameterization holds at the start values: a 3 % longer stroke of B
    would take one more closing step)."""
    import equinox as eqx
    import jax

    from jaxfric.identification.params import value_filter

    par = parameterize(scene, names, variant=variant, overrides={"mesh": "20x2"})
    p = par.p0 * (1.0 + 0.03 * np.arange(1, len(names) + 1))
    built = scenes.make(scene, variant, "penalty", {"mesh": "20x2", **dict(zip(names, p.tolist()))}).model
    spliced = par.model(p)
    for phase, start in zip(spliced.phases, par.scene.model.phases):
        assert phase.increments == start.increments
    a, b = (jax.tree_util.tree_leaves(eqx.filter(m, value_filter(m))) for m in (built, spliced))
    assert len(a) == len(b)
    for x, y in zip(a, b):
        np.testing.assert_allclose(np.asarray(y), np.asarray(x), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("args, needle", [
    (["--param", "nx"], "not differentiable"),
    (["--param", "dU"], "changes the model's structure"),
    (["--param", "target_gap"], "does not enter"),
    (["--param", "bogus"], "unknown parameter 'bogus'"),
    (["--param", "mu,mu"], "twice"),
    (["--param", "mu", "--bounds", "mu=0.2:1"], "excludes the start value"),
    (["--param", "mu", "--bounds", "mu=1:0"], "low < high"),
    (["--param", "mu", "--bounds", "E=0:1"], "does not fit"),
    (["--param", "mu", "--bounds", "mu=a:b"], "must be numbers"),
    (["--param", "mu", "--window", "0"], "'window'"),
    (["--param", "mu", "--window", "1"], "fewer than the 1 parameter"),
    (["--param", "mu", "--set", "mu=x"], "must be a number"),
    (["--param", "mu", "--grid", "mu=0.1:0.2"], "NAME=LOW:HIGH:N"),
    (["--param", "mu", "--grid", "E=1:2:3"], "does not fit"),
    (["--param", "mu", "--grid", "mu=0.1:0.2:1"], "N must be at least 2"),
    (["--param", "mu", "--grid", "mu=0.2:0.1:3"], "increasing"),
    (["--param", "mu", "--grid", "mu=0.1:nan:3"], "finite"),
    (["--param", "mu", "--grid", "mu=0:2:3", "--bounds", "mu=0:1"], "leaves the bounds"),
    (["--param", "mu", "--starts", "2"], "needs a grid"),
    (["--param", "mu", "--model-error", "mesh,bogus"], "'model_error'"),
    (["--param", "mu", "--grid", "mu=0.1:0.2:3", "--starts", "0"], "'starts' must be an integer >= 1"),
])
def test_cli_fit_rejects_bad_input_in_one_line(flat_history, tmp_path, capsys, args, needle):
    code = main(["fit", *FLAT, "--data", flat_history, "--quiet", "--out", str(tmp_path / "o"), *args])
    err = capsys.readouterr().err
    assert code == 2
    assert needle in err and err.count("\n") == 1 and "Traceback" not in err
    assert not (tmp_path / "o" / "fit.json").exists()


@pytest.mark.parametrize("content, needle", [
    ("drawing_displacement,other\n0.1,1\n", "lacks the column(s) drawing_force"),
    ("drawing_displacement,drawing_force\n0.1,nan\n0.2,1\n", "non-finite"),
    ("drawing_displacement,drawing_force\n0.1,1\n0.3,1\n0.2,1\n", "increase strictly"),
    ("drawing_displacement,drawing_force\n0.0,1\n", "no row with drawing_displacement > 0"),
    ("drawing_displacement,drawing_force\n0.1,abc\n", "is not a number"),
    ("", "lacks the column(s)"),
])
def test_malformed_measurements(tmp_path, capsys, content, needle):
    path = tmp_path / "m.csv"
    path.write_text(content)
    code = main(["fit", *FLAT, "--data", str(path), "--param", "mu", "--quiet", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and needle in err and err.count("\n") == 1


def test_fewer_points_than_parameters_and_a_stroke_too_long(tmp_path):
    with pytest.raises(ValueError, match="fewer than the 2 parameter"):
        fit("flat_die", {"drawing_displacement": [0.01], "drawing_force": [1.0]}, ["mu", "E"],
            variant="const_force", overrides={"mesh": "24x1"}, progress=False)
    with pytest.raises(ValueError, match="beyond the simulated stroke"):
        fit("flat_die", {"drawing_displacement": [0.01, 0.5], "drawing_force": [1.0, 2.0]}, ["mu"],
            variant="const_force", overrides={"mesh": "24x1"}, progress=False)


def test_missing_data_file(tmp_path, capsys):
    code = main(["fit", *FLAT, "--data", str(tmp_path / "none.csv"), "--param", "mu", "--quiet"])
    assert code == 2 and "is not a file" in capsys.readouterr().err


def test_fit_caches_keep_the_most_recently_used_entries():
    """The caches kept between fits (compiled curves, grid runs) are bounded: a full cache drops its
    least recently used entry, and a hit makes an entry the most recent."""
    from jaxfric.identification.fit import CURVES, GRID_RUNS
    from jaxfric.numerics.lru import LRU

    made = []

    def make(key):
        return lambda: made.append(key) or key

    cache = LRU(2)
    assert [cache.get(k, make(k)) for k in ("a", "b", "a", "c")] == ["a", "b", "a", "c"]
    assert made == ["a", "b", "c"] and len(cache) == 2  # "b", the least recently used, was dropped
    cache.get("a", make("a"))
    cache.get("b", make("b"))
    assert made == ["a", "b", "c", "b"]
    assert CURVES.maxsize <= 8 and GRID_RUNS.maxsize <= 8


def test_refined_plan_splits_every_step_and_keeps_phase_ends():
    from jaxfric.identification.fit_curve import refined_plan

    plan = {"time": np.array([0.0, 0.5, 1.0, 1.25, 2.0, 2.5]), "phase": np.array([0, 0, 0, 1, 1, 1]),
            "cutbacks": np.array([0, 0, 2, 0, 1, 0]), "predicted": np.array([0, 0, 0, 0, 0, 0])}
    assert refined_plan(plan, 1) is plan
    r = refined_plan(plan, 2)
    np.testing.assert_array_equal(r["time"], [0.0, 0.25, 0.5, 0.75, 1.0, 1.125, 1.25, 1.625, 2.0, 2.25, 2.5])
    np.testing.assert_array_equal(r["phase"], [0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 1])
    # A step that started converged keeps the mark on its first part (the run's first step, a retry, a
    # phase's first step); its later parts are predicted, but where the run withheld the prediction
    # (the last step: same phase, not a retry, not predicted).
    np.testing.assert_array_equal(r["predicted"], [0, 0, 1, 0, 1, 0, 1, 0, 1, 0, 0])
    with pytest.raises(ValueError, match="substeps"):
        fit("flat_die", {"drawing_displacement": [1.0, 2.0], "drawing_force": [1.0, 2.0]}, ["mu"], substeps=0)


# ---- refused input: no simulation, no output directory ---------------------------------------------------

GOOD = "drawing_displacement,drawing_force\n0.001,1\n0.002,2\n0.003,3\n0.004,4\n0.005,5\n"


class _Started(Exception):
    """Raised by the stubbed simulation: the input got past validation."""


@pytest.fixture
def no_simulation(monkeypatch):
    import jaxfric.identification.fit as fit_module

    def refuse(*args, **kwargs):
        raise _Started("the input reached the simulation")

    monkeypatch.setattr(fit_module, "adaptive_run", refuse)


def _csv(tmp_path, content=GOOD, name="m.csv", encoding="utf-8"):
    path = tmp_path / name
    path.write_text(content, encoding=encoding)
    return str(path)


@pytest.mark.parametrize("args, needle", [
    (["--param", "mu", "--window", "1e-12"], "'window'"),
    (["--param", "mu", "--window", "1e-300"], "'window'"),
    (["--param", "mu", "--grid", "mu=0:1:1000000000"], "--grid"),
    (["--param", "mu,E", "--grid", "mu=0:1:1000", "--grid", "E=1:2:1000"], "--grid"),
    (["--param", "mu", "--bounds", "mu=0:1", "--bounds", "mu=0:2"], "--bounds gives 'mu' twice"),
    (["--param", "mu", "--grid", "mu=0:1:3", "--grid", "mu=0:1:4"], "--grid gives 'mu' twice"),
    (["--param", "mu", "--param", "E"], "--param: given twice"),
    (["--param", "mu", "--window", "1", "--window", "2"], "--window: given twice"),
    (["--param", "bogus"], "'bogus'"),
    (["--param", "mu", "--set", "mu=x"], "'mu'"),
    (["--param", "mu", "--starts", "2"], "'starts'"),
    (["--param", "mu", "--bounds", "mu=0.5:1"], "'mu'"),
    (["--param", "mu", "--set", "steady_window=1,2"], "'steady_window'"),
])
def test_cli_fit_refuses_before_making_its_directory(no_simulation, tmp_path, capsys, args, needle):
    out = tmp_path / "fits" / "o"
    code = main(["fit", *FLAT, "--data", _csv(tmp_path), "--quiet", "--out", str(out), *args])
    err = capsys.readouterr().err
    assert code == 2, err
    assert needle in err and err.count("\n") == 1 and "Traceback" not in err, err
    assert not (tmp_path / "fits").exists()


def test_cli_fit_refuses_an_out_path_with_a_nul_byte(no_simulation, tmp_path, capsys):
    code = main(["fit", *FLAT, "--data", _csv(tmp_path), "--quiet", "--param", "mu", "--out", "a\0b"])
    err = capsys.readouterr().err
    assert code == 2 and "--out" in err and err.count("\n") == 1, err


def test_cli_fit_default_directory_is_made_only_for_valid_input(no_simulation, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    data = _csv(tmp_path)
    assert main(["fit", *FLAT, "--data", data, "--quiet", "--param", "bogus"]) == 2
    assert not (tmp_path / "fits").exists()
    with pytest.raises(_Started):
        main(["fit", *FLAT, "--data", data, "--quiet", "--param", "mu"])
    assert (tmp_path / "fits" / "flat_die" / "const_force").is_dir()


@pytest.mark.parametrize("content, needle", [
    ("drawing_displacement,drawing_force,drawing_force\n0.001,1,5\n0.002,2,6\n", "column 'drawing_force' twice"),
    ("drawing_displacement,drawing_force\n0.001,1e308\n0.002,1e308\n", "'drawing_force'"),
    ("drawing_displacement,drawing_force\n0.001,1\n1e300,2\n", "'drawing_displacement'"),
])
def test_measurements_with_duplicate_columns_or_unphysical_values(tmp_path, content, needle):
    with pytest.raises(ValueError) as info:
        read_measurement(_csv(tmp_path, content))
    assert needle in str(info.value) and "\n" not in str(info.value), str(info.value)


def test_measurement_with_a_byte_order_mark(tmp_path):
    meas = read_measurement(_csv(tmp_path, GOOD, encoding="utf-8-sig"))
    np.testing.assert_array_equal(meas.force, [1, 2, 3, 4, 5])


@pytest.mark.parametrize("kwargs, field", [
    ({"params": None}, "'params'"),
    ({"params": [1]}, "'params'"),
    ({"bounds": "mu"}, "'bounds'"),
    ({"window": "abc"}, "'window'"),
    ({"window": [1]}, "'window'"),
    ({"window": 1e-12}, "'window'"),
    ({"grid": [1, 2]}, "'grid'"),
    ({"grid": {"mu": [0.0, 0.1]}, "max_iter": 0}, "'max_iter'"),
    ({"overrides": [("mu", 0.1)]}, "'overrides'"),
    ({"xtol": float("nan")}, "'xtol'"),
    ({"xtol": "a"}, "'xtol'"),
    ({"xtol": -1.0}, "'xtol'"),
    ({"newton": "x"}, "'newton'"),
])
def test_fit_api_bad_input_names_the_field(no_simulation, tmp_path, kwargs, field):
    args = {"params": ["mu"], "overrides": {"mesh": "4x1"}, "progress": False, **kwargs}
    with pytest.raises((ValueError, TypeError)) as info:
        fit("flat_die", _csv(tmp_path), args.pop("params"), **args)
    assert field in str(info.value) and "\n" not in str(info.value), str(info.value)


class _ExponentialCurve:
    """A stand-in for :class:`jaxfric.identification.fit_curve.Curve`: F(x) = A exp(-k x), its Jacobian
    in (A, k), and a staircase of height ``step`` added to F (the discretisation noise of a replay,
    which no Jacobian sees). Counts its evaluations."""

    def __init__(self, x, step=0.0):
        self.x, self.step, self.calls = x, step, 0

    def __call__(self, p):
        self.calls += 1
        a, k = p
        e = np.exp(-k * self.x)
        f = a * e
        if self.step:
            f = f + self.step * (np.floor(1e4 * a) % 2)
        return f, np.stack([e, -a * self.x * e], axis=1), f, 0, 0


def _problem(observed, **kwargs):
    from jaxfric.identification import fit as fitting

    defaults = dict(scene="test", algorithm="lcp_ssn", overrides={}, names=("A", "k"), par=None, meas=None,
                    edges=None, observed=observed, lo=np.zeros(2), hi=np.full(2, np.inf), newton=None,
                    max_iter=30, xtol=1e-7, max_replans=0, substeps=1, model_key=(), say=lambda text: None)
    return fitting.Problem(**{**defaults, **kwargs})


@pytest.mark.parametrize("step", [0.0, 1e-3])
def test_least_squares_stops_within_a_tenth_of_the_standard_error(step):
    """The local stage (scipy's least_squares) on a nonlinear model with noisy data: it ends within a
    tenth of a standard error of the least-squares optimum (scipy run to 1e-12 on the smooth model) in
    a few evaluations, also when the model carries a staircase the Jacobian does not see (then by the
    solver's trial steps shrinking below that tolerance, not by running out of trials)."""
    from scipy.optimize import least_squares

    from jaxfric.identification import fit as fitting

    x = np.linspace(0.0, 2.0, 40)
    rng = np.random.default_rng(5)
    data = 3.0 * np.exp(-1.3 * x) + 0.02 * rng.standard_normal(x.size)
    problem = _problem(data)
    curve = _ExponentialCurve(x, step)
    cur = fitting._evaluate(problem, curve, np.array([1.0, 0.5]))
    rows = []
    end, message = fitting._trials(problem, curve, cur, rows)
    assert message == ""
    smooth = _ExponentialCurve(x)
    best = least_squares(lambda p: smooth(p)[0] - data, [1.0, 0.5], jac=lambda p: smooth(p)[1], xtol=1e-12,
                         ftol=1e-12, gtol=1e-12).x
    err = np.sqrt(np.diag(fitting._covariance(end["jac"], end["r"])))
    assert np.all(np.abs(end["p"] - best) <= 0.1 * err + 2 * step), (end["p"], best, err)
    assert curve.calls <= 10 and len(rows) == curve.calls - 1


# ---- design (jaxfric design, jaxfric.identification.design) -------------------------------------------

def test_cli_design_meets_a_target_curve(flat_history, tmp_path, capsys):
    """A target curve (the run at F_clamp = 50 N/mm, every point) from F_clamp = 40: the design is the
    clamping force that made it."""
    out = tmp_path / "curve"
    code = main(["design", *FLAT, "--target-curve", flat_history, "--param", "F_clamp", "--set", "F_clamp=40",
                 "--bounds", "F_clamp=10:100", "--quiet", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    summary = json.loads((out / "design.json").read_text())
    assert summary["converged"] and summary["target"] is None and summary["steady_window"] is None
    assert summary["params"]["F_clamp"] == pytest.approx(50.0, rel=1e-4)
    assert "largest difference from the target curve" in capsys.readouterr().out


def test_cli_design_meets_a_target_force_and_names_the_reachable_range(tmp_path, capsys):
    """The flat die's steady force, once the sheet slides, is mu F_clamp (a closed form, not the model):
    a target of 9 N/mm needs F_clamp = 60 N/mm at mu = 0.15, with dF/dF_clamp = mu. A target of 20 N/mm
    lies beyond the bounds 10 to 100 N/mm (1.5 to 15 N/mm): the design says so, with that range."""
    out = tmp_path / "design"
    code = main(["design", *FLAT, "--target", "9", "--param", "F_clamp", "--bounds", "F_clamp=10:100", "--quiet",
                 "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    summary = json.loads((out / "design.json").read_text())
    assert summary["converged"] and summary["message"] == "target met"
    assert abs(summary["force"] / 9.0 - 1) <= 1e-3 and summary["steady_window"] == [0.02, 0.03]
    assert summary["params"]["F_clamp"] == pytest.approx(60.0, rel=1e-3)
    assert summary["sensitivity"]["F_clamp"] == pytest.approx(0.15, rel=1e-6)
    assert summary["start_force"] == pytest.approx(7.5, rel=1e-6)
    assert (out / "design.png").stat().st_size > 10_000
    assert "N/mm for a target of 9 (" in capsys.readouterr().out
    far = tmp_path / "far"
    code = main(["design", *FLAT, "--target", "20", "--param", "F_clamp", "--bounds", "F_clamp=10:100", "--quiet",
                 "--out", str(far)])
    err = capsys.readouterr().err
    assert code == 1 and "outside the range reachable within the bounds" in err and err.count("\n") == 1, err
    summary = json.loads((far / "design.json").read_text())
    assert not summary["converged"] and summary["params"]["F_clamp"] == pytest.approx(100.0, rel=1e-3)
    assert summary["reachable"]["low"] == pytest.approx(1.5, rel=1e-6)
    # At 100 N/mm the force still rises through the elastic stick range early in the window (measured
    # 14.97 N/mm, 0.2 % under the plateau).
    assert summary["reachable"]["high"] == pytest.approx(15.0, rel=5e-3)


@pytest.mark.parametrize("args, needle", [
    (["--target", "9", "--param", "F_clamp"], "'bounds'"),
    (["--target", "9", "--param", "F_clamp,mu", "--bounds", "F_clamp=10:100"], "'mu'"),
    (["--target", "-1", "--param", "F_clamp", "--bounds", "F_clamp=10:100"], "'target'"),
    (["--target", "9", "--param", "F_clamp", "--bounds", "F_clamp=10:100", "--window", "0.01"], "A:B"),
    (["--target", "9", "--param", "F_clamp", "--bounds", "F_clamp=10:100", "--window", "0:1"], "'window'"),
    (["--target", "9", "--param", "F_clamp", "--bounds", "F_clamp=10:100", "--rtol", "2"], "'rtol'"),
    (["--target", "9", "--param", "F_clamp", "--bounds", "F_clamp=60:100"], "excludes the start value"),
    (["--target-curve", "none.csv", "--param", "F_clamp", "--bounds", "F_clamp=10:100"], "is not a file"),
])
def test_cli_design_refuses_before_making_its_directory(no_simulation, tmp_path, capsys, args, needle):
    out = tmp_path / "designs" / "o"
    code = main(["design", *FLAT, "--quiet", "--out", str(out), *args])
    err = capsys.readouterr().err
    assert code == 2, err
    assert needle in err and err.count("\n") == 1 and "Traceback" not in err, err
    assert not (tmp_path / "designs").exists()


class _TwoDimensionForce:
    """A stand-in for a bead's restraining force in (R, H), nonlinear and with a cross term: one
    target, two parameters (a curve of designs meets it)."""

    def __init__(self):
        self.calls = 0

    def __call__(self, p):
        self.calls += 1
        R, H = p
        f = np.array([100.0 + 12.0 * H - 4.0 * R + 0.3 * H * R - 0.2 * H**2])
        jac = np.array([[-4.0 + 0.3 * H, 12.0 + 0.3 * R - 0.4 * H]])
        return f, jac, f, 0, 0


def test_design_with_more_parameters_than_targets_stops_once_the_target_is_met():
    """One restraining force, two dimensions: no standard errors exist (as many parameters as
    observations or more), so a design stops on its tolerance on the target, in a few evaluations."""
    from jaxfric.identification import fit as fitting

    target = 165.0
    problem = _problem(np.array([target]), names=("R", "H"), lo=np.array([3.0, 6.0]), hi=np.array([9.0, 9.7]),
                       rtol=1e-3, task="design")
    curve = _TwoDimensionForce()
    cur = fitting._evaluate(problem, curve, np.array([6.0, 9.0]))
    end, message = fitting._trials(problem, curve, cur, [])
    assert message == "" and abs(end["r"][0]) <= 1e-3 * target
    assert np.all(end["p"] >= problem.lo) and np.all(end["p"] <= problem.hi)
    assert curve.calls <= 6


def test_a_target_curve_is_met_relative_to_its_largest_value():
    """A drawing-force curve starts at zero force: the design's tolerance is relative to the curve's
    largest value, not pointwise (which no design could meet where the target is 0)."""
    from jaxfric.identification.fit import met

    targets = np.array([0.0, 50.0, 100.0])
    assert met(np.array([0.05, -0.09, 0.1]), targets, 1e-3)
    assert not met(np.array([0.0, 0.0, 0.11]), targets, 1e-3)


def test_replays_of_step_sequences_of_about_the_same_length_share_one_program():
    """A fit's curve takes its step sequence as data, padded per phase to a power of two: the adaptive run's
    own sequence and one with a step split in two replay in one compiled program (traced once), the first
    reproducing the adaptive run's forces and the second ending where the load path does."""
    import jax
    import jax.numpy as jnp

    from jaxfric.identification.params import adaptive_run, plan_steps, replay_function

    par = parameterize("flat_die", ["mu"], variant="const_force", overrides={"mesh": "24x1", "U_draw": 0.01})
    run = adaptive_run(par, par.p0).history
    g = replay_function(par)

    @jax.jit
    def replay(p, steps):
        h, code = g(p, steps)
        return h.observed["drawing_force"], h.n_rows, code

    time, phase = np.asarray(run["time"]), np.asarray(run["phase"])
    k = int(np.flatnonzero(phase == 1)[3])               # a drawing step, split at its middle
    split = {"time": np.insert(time, k, 0.5 * (time[k - 1] + time[k])), "phase": np.insert(phase, k, 1)}
    steps = [plan_steps(par, plan) for plan in (run, split)]
    shapes = [[ends.shape for ends, _ in s] for s in steps]
    assert shapes[0] == shapes[1]            # one more drawing step, within the same power of two
    (force, rows, code), (force2, rows2, code2) = (replay(jnp.asarray(par.p0), s) for s in steps)
    assert replay._cache_size() == 1
    assert int(code) == int(code2) == 0 and int(rows) == len(time) and int(rows2) == len(time) + 1
    np.testing.assert_allclose(np.asarray(force)[:int(rows)], run["drawing_force"], rtol=1e-9, atol=1e-9)
    assert abs(float(force2[int(rows2) - 1]) - run["drawing_force"][-1]) < 1e-3 * abs(run["drawing_force"][-1])
