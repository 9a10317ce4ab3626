"""The experiment scripts run at a tiny size (they compute when called, write only under __main__)."""


import bench_core  # experiments/ is on the tests' import path (pyproject.toml, pytest's pythonpath)


def test_bench_core_runs_at_a_tiny_size():
    row = bench_core.bench(nx=12, ny=2, repeat=1)
    assert row["converged"] and row["n_steps"] >= 30 and row["newton_iters"] >= row["n_steps"]
    assert row["ms_assembly"] > 0 and row["ms_solve"] > 0 and row["compile_s"] > 0


def test_bench_contact_iteration_timing_runs_for_exact_contact():
    """The exact-contact iteration timed by bench_contact (it broke once, unnoticed, when the contact
    iteration gained an argument)."""
    import bench_contact
    import jaxfric as jf
    from jaxfric.contact.formulations import Complementarity

    model = bench_contact.three_cylinders(Complementarity("ssn", 16), nx=40, ny=1)
    assert bench_contact.iteration_ms(model, jf.initial_state(model), 1) > 0


def test_bench_element_cores_runs_at_a_tiny_size(capsys):
    import bench_element_cores

    assert bench_element_cores.main(["--mesh", "20x1", "--calls", "2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split(" median")[0].strip() for line in lines] == ["as assembled", "one vmap", "two halves"]


# ---- experiments/studies.py: the table, section and comparison helpers (no simulation) -------------

import numpy as np  # noqa: E402
import pytest  # noqa: E402

import studies  # noqa: E402


def test_study_section_is_replaced_not_duplicated(tmp_path, monkeypatch):
    md = tmp_path / "results.md"
    md.write_text("# results\n\nhand-written text\n")
    monkeypatch.setattr(studies, "RESULTS_MD", str(md))
    studies.write_section("demo", "first body")
    studies.write_section("other", "other body")
    studies.write_section("demo", "second body")
    text = md.read_text()
    assert text.startswith("# results\n\nhand-written text\n")
    assert text.count("<!-- BEGIN study:demo -->") == 1 and "second body" in text and "first body" not in text
    assert text.index("second body") < text.index("other body")  # replaced in place


def test_study_curve_difference_and_mesh_reference():
    u = np.linspace(0.0, 10.0, 51)
    h = {"phase": np.array(["draw"] * 51), "drawing_displacement": u, "drawing_force": 100 + u}
    ref = {**h, "drawing_force": 100 + u + 1.1}
    diff = studies._curve_diff(h, ref, "drawing_displacement", "drawing_force", "draw")
    assert diff == pytest.approx(1.1 / 111.1, rel=1e-5)  # largest difference over the reference's largest value
    rows = [{"case": f"{nx}x{ny}", "nx": nx, "ny": ny, "n_elements": nx * ny, "converged": True,
             "steady_drawing_force": 100.0 + 300.0 / nx} for nx, ny in [(150, 3), (300, 3), (600, 6)]]
    rows.append({"case": "1200x6", "nx": 1200, "ny": 6, "n_elements": 7200, "converged": False,
                 "steady_drawing_force": None})
    out = studies._with_rel_diff(rows)
    assert out[2]["rel_diff_to_finest"] == 0 and out[0]["finest"] == "600x6"  # the finest that converged
    assert out[0]["rel_diff_to_finest"] == pytest.approx(1.5 / 100.5, rel=1e-5)
    assert out[3]["rel_diff_to_finest"] is None


def test_study_table_between_cases_keeps_the_rows_still_to_come(tmp_path, monkeypatch):
    """A table written after one case keeps the rows of the table on disk that the loop has not
    reached yet (committed, or read back by another process), so a study stopped there loses none."""
    monkeypatch.setattr(studies, "ROOT", str(tmp_path))
    studies.write_table("demo", [{"case": c, "value": v} for c, v in (("a", 1), ("b", 2), ("c", 3))])
    studies._write_partial("demo", [{"case": "a", "value": 10}, {"case": "d", "value": 4}])
    rows = studies._read_table("demo")
    assert [(r["case"], r["value"]) for r in rows] == [("a", "10"), ("d", "4"), ("b", "2"), ("c", "3")]


# ---- experiments/nine_plastic_work.py: the work per column and its staircase (no simulation) ------------

def test_plastic_work_of_a_column_is_the_dissipation_integrated_through_the_thickness():
    """A uniform plastic strain e gives every column W = w(e) t, w(e) = int_0^e sigma_Y, with either
    quadrature through the thickness."""
    import equinox as eqx
    import jax.numpy as jnp

    import nine_plastic_work
    from jaxfric import scenes
    from jaxfric.loadpath.model import initial_state

    for points in (2, 4):
        scene = scenes.make("nine", "mu000", "lcp_ssn", {"mesh": "30x2", "thickness_points": points})
        model, e = scene.model, 0.2
        state = initial_state(model)
        state = eqx.tree_at(lambda s: s.material.eqps, state, jnp.full_like(state.material.eqps, e))
        mid, W = nine_plastic_work.column_work(model, state)
        m = model.material
        sy, A, n = float(m.sigma_y), float(m.A), float(m.n)
        grid = np.linspace(0.0, e, 20001)
        w = np.trapezoid(sy * (1.0 + A * grid) ** n, grid)
        np.testing.assert_allclose(W, w * scene.config.t, rtol=1e-8)
        assert mid.shape == (30, 2)


def test_plastic_work_staircase_gives_the_levels_and_the_force_by_the_energy_balance():
    import nine_plastic_work

    X = -80.0 + (np.arange(390) + 0.5) / 3.0
    W = np.interp(X, [-80, -62, -60, -56, -54, -40, -38, -30, -28, 50], [0, 0, 10, 10, 40, 40, 75, 75, 90, 90])
    W = np.where(X > -15.0, 50.0, W)   # material that was in the tools when the run began
    s = np.cumsum(np.where(X > -28.0, 1.08, 1.0)) / 3.0   # stretched by 8 % after the last step
    out = nine_plastic_work.analyse({"x_left": -80.0}, s, W)
    assert [round(out[f"W_level_{k}"]) for k in (1, 2, 3, 4)] == [10, 40, 75, 90] and "W_level_5" not in out
    assert abs(out["stretch_end"] - 0.08) < 1e-9 and abs(out["force_from_work"] - 90.0 / 1.08) < 1e-9
