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
