"""The experiment scripts run at a tiny size (they compute when called, write only under __main__)."""


import csv
import math
import os
import traceback

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


def test_the_agreement_shares_the_blankholder_shapes_runs_only_at_equal_settings(tmp_path, monkeypatch):
    """The agreement's blankholder penalty rows are read from study ``blankholder_shapes``'s run directories
    where both studies run at the same settings, and only runs made at them (read back as they are, never
    run again into the shapes study's directory); a stale one is left to its own study."""
    monkeypatch.setattr(studies, "ROOT", str(tmp_path))
    summary = tmp_path / "blankholder_shapes" / "runs" / "shape1" / "summary.json"
    summary.parent.mkdir(parents=True)
    summary.write_text("{}")
    shapes = studies.study_settings("blankholder", "blankholder_shapes")
    assert studies.study_settings("blankholder", "algorithm_agreement") == shapes == {}
    read = []
    monkeypatch.setattr(studies, "run_case", lambda *args, **kwargs: read.append((args, kwargs)) or {"dir": args[0]})
    monkeypatch.setattr(studies, "stale", lambda path, overrides, variant, algorithm: "element 'fbar', not 'anst'")
    assert studies._shared_run("blankholder", "shape1", "penalty") is None and not read
    monkeypatch.setattr(studies, "stale", lambda path, overrides, variant, algorithm: None)
    assert studies._shared_run("blankholder", "shape1", "penalty") == {"dir": str(summary.parent)}
    (args, kwargs), = read
    assert args[4] == shapes and kwargs["rerun"] is False and kwargs["rerun_stale"] is False
    assert studies._shared_run("blankholder", "shape1", "lcp_ssn") is None and len(read) == 1
    monkeypatch.setattr(studies, "AT_DEFAULTS", ("blankholder_shapes",))  # the two studies' settings differ
    assert studies._shared_run("blankholder", "shape1", "penalty") is None and len(read) == 1


def _one_step_run(force):
    """A stubbed study case: one drawing step to ``force`` (N/mm), converged unless ``force`` is None."""
    h = {"time": np.array([0.0, 1.0]), "phase": np.array(["draw", "draw"]),
         "drawing_displacement": np.array([0.0, 1.0]), "drawing_force": np.array([0.0, force or 0.0]),
         "clamping_force": np.array([0.0, 1.0])}
    return {"summary": {"converged": force is not None, "n_steps": 1, "steady_drawing_force": force},
            "history": h, "contact": {}, "dir": None}


def test_agreement_rows_of_other_settings_stay_until_their_cases_run_and_are_never_a_reference(tmp_path, monkeypatch):
    """Rows committed at the study's earlier settings (no ``settings`` column) stay in the table, marked
    ``study`` and listed as not yet run at the defaults, until their case is selected; a case run at the
    defaults is not compared with them, although the old Lemke row has its curves."""
    import argparse

    monkeypatch.setattr(studies, "ROOT", str(tmp_path))
    monkeypatch.setattr(studies, "RESULTS_MD", str(tmp_path / "results.md"))
    monkeypatch.setattr(studies, "_variants", lambda: iter([("nine", "mu017")]))
    study = tmp_path / "algorithm_agreement"
    (study / "curves").mkdir(parents=True)
    old = [{"case": f"nine_mu017_{a}", "scene": "nine", "variant": "mu017", "algorithm": a, "reference": "lcp_lemke",
            "converged": True, "n_steps": 800, "steady_drawing_force": 150.0, "rel_diff_steady": 1e-3}
           for a in ("penalty", "auglag", "lcp_lemke", "lcp_ssn", "auglag_gap1e-06")]
    studies.write_csv(str(study / "table.csv"), old)
    np.savez(study / "curves" / "nine_mu017_lcp_lemke.npz", phase=np.array(["draw", "draw"]),
             drawing_displacement=np.array([0.0, 1.0]), drawing_force=np.array([0.0, 150.0]))
    ran = []

    def fake_case(study_name, label, name, variant, algorithm, overrides, opts, steps=None):
        ran.append(label)
        return _one_step_run(140.0)

    monkeypatch.setattr(studies, "case", fake_case)
    studies.algorithm_agreement(argparse.Namespace(only=["nine_mu017_lcp_ssn"], rerun=False, collect=False,
                                                   missing=[], progress=False, run_figures=False))
    assert ran == ["nine_mu017_lcp_ssn"]
    rows = {r["case"]: r for r in studies._read_table("algorithm_agreement")}
    new = rows["nine_mu017_lcp_ssn"]
    assert new["settings"] == "defaults" and new["steady_drawing_force"] == "140.0"
    assert new["reference"] == "" and new["rel_diff_steady"] == ""
    for a in ("penalty", "auglag", "lcp_lemke"):
        assert rows[f"nine_mu017_{a}"]["settings"] == "study" and rows[f"nine_mu017_{a}"]["rel_diff_steady"] == "0.001"
    text = (tmp_path / "results.md").read_text()
    assert "**Not yet run at `defaults`** (4 of 5 rows" in text and "rows per group): nine mu017 (4)." in text
    # The AL reference is needed only where Lemke ran at these settings and failed: not missing yet.
    assert "Not run yet" not in text
    # Lemke converged at the defaults: the AL reference of the earlier settings is no longer needed.
    np.savez(study / "curves" / "nine_mu017_auglag_gap1e-06.npz", phase=np.array(["draw"]))
    studies.algorithm_agreement(argparse.Namespace(only=["nine_mu017_lcp_lemke"], rerun=False, collect=False,
                                                   missing=[], progress=False, run_figures=False))
    rows = {r["case"]: r for r in studies._read_table("algorithm_agreement")}
    assert "nine_mu017_auglag_gap1e-06" not in rows
    assert not (study / "curves" / "nine_mu017_auglag_gap1e-06.npz").exists()
    assert rows["nine_mu017_lcp_lemke"]["settings"] == "defaults" == rows["nine_mu017_lcp_ssn"]["settings"]


def test_agreement_falls_back_on_semismooth_newton_where_lemke_and_the_al_reference_fail(tmp_path, monkeypatch):
    """Where neither Lemke nor the AL reference (target gap 1e-6) finishes, the group is compared with
    ``lcp_ssn``, whose solution is Lemke's on common steps, instead of having no reference."""
    import argparse

    monkeypatch.setattr(studies, "ROOT", str(tmp_path))
    monkeypatch.setattr(studies, "RESULTS_MD", str(tmp_path / "results.md"))
    monkeypatch.setattr(studies, "_variants", lambda: iter([("nine", "mu017")]))
    force = {"penalty": 151.5, "auglag": 150.3, "lcp_ssn": 150.0}

    def fake_case(study_name, label, name, variant, algorithm, overrides, opts, steps=None):
        done = algorithm in force and "target_gap" not in overrides
        return _one_step_run(force[algorithm] if done else None)

    monkeypatch.setattr(studies, "case", fake_case)
    studies.algorithm_agreement(argparse.Namespace(only=["nine_mu017_"], rerun=False, collect=False,
                                                   missing=[], progress=False, run_figures=False))
    rows = {r["algorithm"]: r for r in studies._read_table("algorithm_agreement")}
    assert set(rows) == {"penalty", "auglag", "lcp_lemke", "lcp_ssn", "auglag_gap1e-06"}
    assert {r["reference"] for r in rows.values()} == {"lcp_ssn"}
    assert float(rows["penalty"]["rel_diff_steady"]) == pytest.approx(0.01)
    assert float(rows["lcp_ssn"]["rel_diff_steady"]) == 0.0


def test_mesh_convergence_tables_between_cases_compare_with_the_finest_mesh_finished(tmp_path, monkeypatch):
    """The table written after a case runs compares every row with the finest mesh finished (a committed row
    here, 600 x 6), not the finest the loop has reached: a study stopped after that case leaves a table
    whose rows agree with its last row."""
    import argparse

    monkeypatch.setattr(studies, "ROOT", str(tmp_path))
    monkeypatch.setattr(studies, "RESULTS_MD", str(tmp_path / "results.md"))
    (tmp_path / "mesh_convergence").mkdir()
    studies.write_csv(str(tmp_path / "mesh_convergence" / "table.csv"),
                      [{"case": "600x6", "nx": 600, "ny": 6, "n_elements": 3600, "steady_drawing_force": 81.0,
                        "converged": True, "wall_s": 1.0}])
    monkeypatch.setattr(studies, "case", lambda study, name, *a, **k: {"summary": {
        "converged": True, "steady_drawing_force": 82.0 if name == "150x3" else 80.0, "wall_s": 1.0}})
    partial = []
    monkeypatch.setattr(studies, "_write_partial", lambda study, rows: partial.append([dict(r) for r in rows]))
    studies.mesh_convergence(argparse.Namespace(only=["150x3", "1200x3"], rerun=False, collect=False, missing=[],
                                                progress=False, run_figures=False))
    first = {r["case"]: r for r in partial[0]}
    assert set(first) == {"150x3", "600x6"} and first["150x3"]["finest"] == "600x6"
    assert first["150x3"]["rel_diff_to_finest"] == pytest.approx(1 / 81, rel=1e-5)
    assert [r["finest"] for r in partial[1]] == ["600x6"] * 3  # 1200 x 3 has as many elements, fewer layers


def test_common_steps_row_compares_a_replay_with_its_plan_at_the_plan_s_step_ends():
    """A replay that cut one step has one row more than its plan; the comparison takes the rows that end
    where the plan's steps end, so the extra row does not enter the force or status differences."""
    t = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
    plan_h = {"time": t, "phase": np.array(["clamp"] * 3 + ["draw"] * 2),
              "drawing_force": np.array([0.0, 0.0, 0.0, 50.0, 100.0]),
              "clamping_force": np.array([0.0, 10.0, 20.0, 20.0, 20.0]),
              "n_active": np.array([0, 2, 3, 3, 3]), "n_slip": np.array([0, 0, 0, 3, 3])}
    plan = {"summary": {"n_steps": 4, "steady_drawing_force": 100.0}, "history": plan_h}
    cut = np.array([0.0, 0.5, 1.0, 1.25, 1.5, 2.0])  # the step to 1.5 cut in two
    h = {"time": cut, "drawing_force": np.array([0.0, 0.0, 0.0, 999.0, 50.0, 101.2]),
         "clamping_force": np.array([0.0, 10.0, 20.0, 999.0, 20.0, 20.0]),
         "n_active": np.array([0, 2, 3, 9, 3, 3]), "n_slip": np.array([0, 0, 0, 9, 2, 3]),
         "ssn_iters": np.array([0, 0, 3, 0, 0, 1])}
    run = {"summary": {"n_steps": 5, "steady_drawing_force": 101.0, "converged": True}, "history": h}
    row = studies._common_row("nine", "mu017", "lcp_lemke", run, plan)
    assert row["extra_steps"] == 1 and row["common_rows"] == 5
    assert row["rel_diff_steady"] == pytest.approx(0.01)
    assert row["force_diff"] == pytest.approx(1.2 / 120.0)  # over the plan's drawing + clamping scale
    assert row["status_differ"] == pytest.approx(1 / 5)  # n_slip differs at t = 1.5 only
    assert row["refined_steps"] == 2


def test_common_steps_row_of_two_committed_cases_keeps_their_committed_steady_difference():
    """A case and its plan both read back from committed rows (their steady forces to 6 digits there)
    keep the difference the invocation that ran them computed; a case run now against a committed plan
    is compared afresh."""
    t = np.array([0.0, 1.0, 2.0])
    h = {"time": t, "drawing_force": np.array([0.0, 5.0, 7.5]), "clamping_force": np.array([0.0, 50.0, 50.0]),
         "n_active": np.array([0, 3, 3]), "n_slip": np.array([0, 0, 3])}
    plan = {"summary": {"n_steps": 2, "steady_drawing_force": 7.5}, "history": h,
            "row": {"steady_drawing_force": 7.5}}
    run = {"summary": {"n_steps": 2, "steady_drawing_force": 7.5}, "history": h,
           "row": {"rel_diff_steady": -1.386e-14}}
    assert studies._common_row("flat_die", "const_force", "lcp_lemke", run, plan)["rel_diff_steady"] == -1.386e-14
    fresh = {k: v for k, v in run.items() if k != "row"}
    assert studies._common_row("flat_die", "const_force", "lcp_lemke", fresh, plan)["rel_diff_steady"] == 0.0
    # algorithm_agreement: only a row compared with the same reference keeps its difference.
    against_lemke = {**run, "row": {"rel_diff_steady": 1.4e-14, "reference": "lcp_lemke"}}
    assert studies._steady_difference(against_lemke, plan, signed=False, reference="lcp_lemke") == 1.4e-14
    assert studies._steady_difference(against_lemke, plan, signed=False, reference="auglag_gap1e-06") == 0.0


def test_union_of_accepted_steps_merges_step_ends_equal_to_round_off():
    a = {"time": np.array([0.0, 0.5, 1.0, 2.0])}
    b = {"time": np.array([0.0, 0.25, 0.5 + 1e-12, 1.0, 1.5, 2.0])}
    np.testing.assert_allclose(studies.union_steps([a, b]), [0.25, 0.5, 1.0, 1.5, 2.0], rtol=0, atol=1e-11)


@pytest.mark.parametrize("collect", [True, False])
def test_a_collecting_study_reads_a_stale_run_back_instead_of_running_it(monkeypatch, collect):
    """``--collect`` runs nothing: a case on disk made at other settings is read back as it is."""
    import argparse

    seen = {}
    monkeypatch.setattr(studies, "run_case", lambda *args, **kwargs: seen.update(kwargs) or {})
    opts = argparse.Namespace(only=[], rerun=False, collect=collect, progress=False, run_figures=False)
    studies.case("common_steps", "nine_mu017_lcp_lemke", "nine", "mu017", "lcp_lemke", {}, opts)
    assert seen["rerun_stale"] is not collect and seen["rerun"] is False


def _stubbed_common_steps(tmp_path, monkeypatch, cut: str, union: bool) -> list:
    """Study ``common_steps`` on the Nine's mu017 with its runs stubbed: each case converges on the steps it
    is given (the plan: 0.5, 1 and 2), except case ``cut``, which cuts the step to 1.0 in two. Returns the
    cases it ran as (label, algorithm, overrides, steps)."""
    import argparse

    monkeypatch.setattr(studies, "ROOT", str(tmp_path))
    monkeypatch.setattr(studies, "RESULTS_MD", str(tmp_path / "results.md"))
    monkeypatch.setattr(studies, "_variants", lambda: iter([("nine", "mu017")]))
    monkeypatch.setattr(studies, "_agreement_figure", lambda panels, study: None)
    calls = []

    def fake_case(study, label, name, variant, algorithm, overrides, opts, steps=None):
        calls.append((label, algorithm, overrides, None if steps is None else list(np.round(steps, 12))))
        t = np.array([0.0, 0.5, 1.0, 2.0]) if steps is None else np.concatenate([[0.0], steps])
        if label == cut:
            t = np.array([0.0, 0.5, 0.75, 1.0, 2.0])
        n = len(t)
        h = {"time": t, "phase": np.array(["clamp"] * n), "drawing_force": t * 10.0, "clamping_force": t,
             "n_active": np.ones(n, int), "n_slip": np.zeros(n, int), "ssn_iters": np.zeros(n, int)}
        return {"summary": {"converged": True, "n_steps": n - 1, "steady_drawing_force": 20.0,
                            "cutback_causes": {"inverted_element": 1}}, "history": h, "contact": {}, "dir": None}

    monkeypatch.setattr(studies, "case", fake_case)
    studies.common_steps(argparse.Namespace(only=[], rerun=False, collect=False, union=union, missing=[],
                                            progress=False, run_figures=False))
    return calls


def test_common_steps_study_replays_the_plan_then_the_union_where_a_replay_cut(tmp_path, monkeypatch):
    """The three replays get the plan's steps; one of them cut a step, so with ``--union`` all four
    algorithms run again on the union of the accepted steps, and the rows compare each pass with its own
    ``lcp_ssn``."""
    calls = _stubbed_common_steps(tmp_path, monkeypatch, "nine_mu017_penalty", union=True)
    plan, union = [0.5, 1.0, 2.0], [0.5, 0.75, 1.0, 2.0]
    assert [(c[0], c[3]) for c in calls] == (
        [("nine_mu017_lcp_ssn", None)] + [(f"nine_mu017_{a}", plan) for a in studies.COMMON_REPLAYS]
        + [(f"nine_mu017_{a}_union", union) for a in ("lcp_ssn", *studies.COMMON_REPLAYS)])
    rows = {r["case"]: r for r in studies._read_table("common_steps")}
    assert rows["nine_mu017_penalty"]["extra_steps"] == "1" and rows["nine_mu017_penalty_union"]["extra_steps"] == "0"
    assert rows["nine_mu017_lcp_lemke_union"]["steps"] == "union"


@pytest.mark.parametrize("lemke_cuts", [True, False])
def test_common_steps_study_replays_lemke_again_searched_where_it_left_the_plan(tmp_path, monkeypatch, lemke_cuts):
    """The ``lcp_lemke`` replay takes full Newton steps; where it took steps other than the plan's, Lemke
    replays the plan again with its Newton steps line-searched (``lemke_search``), in a row of its own;
    where it took the plan's steps, it does not. Rows name the cut steps' causes."""
    calls = _stubbed_common_steps(tmp_path, monkeypatch, "nine_mu017_lcp_lemke" if lemke_cuts else "", union=False)
    plan = [0.5, 1.0, 2.0]
    assert [c for c in calls if c[1] == "lcp_lemke"] == (
        [("nine_mu017_lcp_lemke", "lcp_lemke", {"lemke_search": False}, plan)]
        + ([(f"nine_mu017_{studies.SEARCHED}", "lcp_lemke", {"lemke_search": True}, plan)] if lemke_cuts else []))
    rows = {r["case"]: r for r in studies._read_table("common_steps")}
    assert (f"nine_mu017_{studies.SEARCHED}" in rows) == lemke_cuts
    assert rows["nine_mu017_lcp_lemke"]["cut_causes"] == "inverted_element:1"


def test_replayed_steps_become_the_nominal_increments_phase_by_phase():
    """:func:`jaxfric.io.batch.replay_steps`: a step ending at k + 1 belongs to phase k, the next to
    phase k + 1; the scene's schedule then has exactly the given steps."""
    from jaxfric import scenes
    from jaxfric.fem.loading import schedule
    from jaxfric.io.batch import replay_steps

    scene = scenes.make("flat_die", "const_position", "lcp_ssn", {"U_draw": 1.0})
    n_phases = len(scene.model.phases)
    times = np.concatenate([k + np.array([0.25, 0.75, 1.0]) for k in range(n_phases)])
    replayed = replay_steps(scene, times)
    ends, phase = schedule(replayed.model.phases).nominal_steps()
    np.testing.assert_allclose(ends, times, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(phase, np.repeat(np.arange(n_phases), 3))
    assert replayed.name == scene.name and replayed.algorithm == scene.algorithm


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


# ---- experiments/error_estimates.py: the reference and the comparison (no simulation) -----------------

def test_richardson_limit_uses_the_observed_ratio_and_stops_where_changes_do_not_shrink():
    import error_estimates

    # f = 10 + 3 h^2 at h = 1, 1/2, 1/4: changes 2.25 and 0.5625, ratio 4, limit 10.
    limit, q = error_estimates.richardson(13.0, 10.75, 10.1875)
    assert q == pytest.approx(4.0) and limit == pytest.approx(10.0)
    # Changes that grow or change sign: no extrapolation, the finest value.
    assert error_estimates.richardson(10.0, 10.5, 9.0) == (9.0, pytest.approx(-0.5 / 1.5))


def test_step_error_control_rows_measure_each_run_against_the_step_limit():
    import step_error_control

    # A first-order ladder F = 100 - 8 h (h: the increment's factor): limit 100.
    runs = {name: {"steady": 100.0 - 8.0 * f, "steps": int(10 / f), "newton": int(50 / f), "cutbacks": 0,
                   "cpu_s": 1.0 / f} for name, f in step_error_control.FIXED.items()}
    runs["error_0.01"] = {"steady": 99.5, "steps": 30, "newton": 120, "cutbacks": 1, "cpu_s": 3.0}
    rows = {r["run"]: r for r in step_error_control.rows_of("case", runs)}
    assert rows["fixed_1"]["step_limit"] == pytest.approx(100.0) and rows["fixed_1"]["q_step"] == pytest.approx(2.0)
    assert rows["fixed_1"]["error_pct"] == pytest.approx(-8.0)
    assert rows["error_0.01"]["error_pct"] == pytest.approx(-0.5) and rows["error_0.01"]["step_error"] == 0.01
    assert rows["error_0.01"]["error_over_tol"] == pytest.approx(0.5)
    assert math.isnan(rows["fixed_1/2"]["step_error"])
    # 0.5 % lies beyond the quarter (2 %, 200 iterations): along the half-quarter segment (4 %, 100),
    # iterations doubling with every halving of the error: 800
    assert rows["error_0.01"]["fixed_newton_same_error"] == pytest.approx(800.0)


def test_error_estimate_summary_compares_the_run_s_estimate_with_its_reference():
    import error_estimates

    # Along the strip first order (changes 2, 1), step first order (0.4, 0.2), layers +0.5.
    forces = {"run": 104.0, "coarse": 108.0, "fine2": 102.0, "fine4": 101.0, "half_step": 103.6,
              "quarter_step": 103.4, "layers": 104.5}
    runs = {k: {"steady": v, "n_steps": 1, "mesh": [100 if k != "coarse" else 50, 2]} for k, v in forces.items()}
    row = error_estimates.summarise("case", runs)
    assert row["along_limit"] == pytest.approx(100.0) and row["step_limit"] == pytest.approx(103.2)
    assert row["reference"] == pytest.approx(100.0 + 0.5 - 0.8)
    assert row["est_mesh_pct"] == pytest.approx(100 * 4.0 / 104.0)
    assert row["est_step_pct"] == pytest.approx(100 * 0.8 / 104.0)
    assert row["true_pct"] == pytest.approx(100 * (104.0 - 99.7) / 99.7)
    assert row["estimate_over_true"] == pytest.approx(
        np.hypot(4.0, 0.8) / 104.0 / ((104.0 - 99.7) / 99.7))
    # The finer companion (fine2) estimates twice its change; with an eighth of the increments the step
    # limit comes from the half, quarter and eighth (changes 0.2, 0.1: limit 103.2 again).
    assert row["est_mesh_fine_pct"] == pytest.approx(100 * 4.0 / 104.0)
    runs["eighth_step"] = {"steady": 103.3, "n_steps": 1, "mesh": [100, 2]}
    eighth = error_estimates.summarise("case", runs)
    assert eighth["step_limit"] == pytest.approx(103.2) and eighth["q_step"] == pytest.approx(2.0)
    assert eighth["F_eighth_step"] == 103.3
    # Four times the layers: their limit by Richardson (changes 0.5, 0.25: 105), the estimate twice the
    # first change.
    runs["layers4"] = {"steady": 104.75, "n_steps": 1, "mesh": [100, 8]}
    layered = error_estimates.summarise("case", runs)
    assert layered["q_layers"] == pytest.approx(2.0)
    assert layered["true_layers_pct"] == pytest.approx(-100 * 1.0 / 105.0)
    assert layered["est_layers_pct"] == pytest.approx(100 * 1.0 / 104.0)
    assert layered["reference"] == pytest.approx(100.0 + 1.0 - 0.8)


def test_error_estimate_table_keeps_the_committed_rows_of_cases_not_recorded(tmp_path):
    import error_estimates

    forces = {"run": 104.0, "coarse": 108.0, "fine2": 102.0, "fine4": 101.0, "half_step": 103.6,
              "quarter_step": 103.4, "layers": 104.5}
    runs = {k: {"steady": v, "n_steps": 1, "mesh": [100 if k != "coarse" else 50, 2]} for k, v in forces.items()}
    first, second, third = list(error_estimates.CASES)[:3]
    path = str(tmp_path / "table.csv")
    error_estimates.write_csv(path, [error_estimates.summarise(c, runs) for c in (first, third)])
    committed = error_estimates.committed_rows(path)
    assert set(committed) == {first, third} and committed[first]["force"] == "104"
    # The second case run now, the first run again with another force: both fresh, the third kept as written.
    runs["run"] = {**runs["run"], "steady": 105.0}
    rows = error_estimates.table([error_estimates.summarise(c, runs) for c in (second, first)], committed)
    assert [r["case"] for r in rows] == [first, second, third]
    assert rows[0]["force"] == 105.0 and rows[2] is committed[third]


def test_error_estimate_runs_refine_the_spec_configuration():
    import error_estimates
    from jaxfric import scenes

    bead = scenes.make("bead", "th090_mu017", "lcp_ssn")
    assert error_estimates._overrides(bead, "fine4") == {"nx": 4 * 725}
    assert error_estimates._overrides(bead, "coarse") == {"nx": 362}
    assert error_estimates._overrides(bead, "layers") == {"ny": 8}
    holder = scenes.make("blankholder", "shape1", "lcp_ssn")
    assert error_estimates._overrides(holder, "fine2") == {"element_length": 0.25}
    assert error_estimates._overrides(holder, "coarse") == {"element_length": 1.0}


def test_chunk_boundary_cost_is_the_extra_time_per_extra_chunk_plus_the_host_time():
    import bench_chunks

    # Chunks of one step: 100 more chunks, 1 s more inside the compiled calls -> 10 ms per boundary;
    # the default run's 10 boundaries cost 0.1 s there, plus 0.1 s on the host, of a 20 s single loop.
    rows = [{"driver": "chunks", "chunk_s": 19.9, "chunks": 10, "host_s": 0.1, "solve_s": 20.0},
            {"driver": "one loop", "solve_s": 20.0},
            {"driver": "1-step chunks", "chunk_s": 20.9, "chunks": 110, "host_s": 0.3, "solve_s": 21.2}]
    assert bench_chunks.boundary_cost(rows) == ("a chunk's boundary costs 10.0 ms inside the compiled calls; the "
                                                "default chunks' boundaries with the host's time between them "
                                                "1.00 % of the one loop's solve")


# ---- experiments/suite_files.py: the suite's files and the workers' schedule (no simulation) ----------

def test_suite_files_model_the_two_workers_and_name_existing_files(tmp_path):
    import suite_files

    report = tmp_path / "report.xml"
    cases = [("tests.test_a", 1.0)] * 3 + [("tests.test_b", 9.0), ("tests.test_c", 4.0), ("tests.test_c", 4.0)]
    rows = "".join(f'<testcase classname="{c}" name="t{k}" time="{t}"/>' for k, (c, t) in enumerate(cases))
    report.write_text(f"<testsuites><testsuite>{rows}</testsuite></testsuites>")
    seconds, count = suite_files.file_times(str(report))
    assert seconds == {"test_a.py": 3.0, "test_b.py": 9.0, "test_c.py": 8.0}
    assert count == {"test_a.py": 3, "test_b.py": 1, "test_c.py": 2}
    # Most tests first (a, c, b): b starts last, beside nothing; longest first (b, c, a) balances.
    assert suite_files.makespan(["test_a.py", "test_c.py", "test_b.py"], seconds) == 12.0
    assert suite_files.makespan(["test_b.py", "test_c.py", "test_a.py"], seconds) == 11.0
    # The order make test uses names files that exist (a renamed file would silently lose its place).
    tests = os.path.dirname(os.path.abspath(__file__))
    assert all(os.path.isfile(os.path.join(tests, name)) for name in suite_files.longest_first())


def test_suite_compile_reads_jax_s_compile_log_and_sorts_programs_by_kind():
    import suite_compile

    assert suite_compile.parse("Persistent compilation cache hit for jit(f)") is None
    assert suite_compile.parse("Finished tracing curve for jit in 2.5 sec") == ("trace", "curve", 2.5)
    assert suite_compile.parse("Finished XLA compilation of jit(<lambda>) in 0.125 sec") == \
        ("xla", "jit(<lambda>)", 0.125)
    assert suite_compile.parse("Finished jaxpr to MLIR module conversion jit(add) in 1e-3 sec") == \
        ("lower", "jit(add)", 1e-3)
    kinds = [suite_compile.kind(n) for n in ("jit(add)", "jit(broadcast_in_dim)", "jit(curve)", "jit(<lambda>)",
                                             "jit(_project_all)", "<lambda>")]
    assert kinds == ["op by op", "op by op", "curve", "other", "other", "other"]
    records = [("t", "xla", "jit(add)", 1.0, "jaxfric/numerics/tensor.py:inv2"), ("t", "trace", "jit(add)", 0.5, None),
               ("u", "xla", "jit(curve)", 2.0, None), ("u", "xla", "jit(mul)", 0.25, "jaxfric/numerics/tensor.py:inv2")]
    per_test, totals = suite_compile.summarise(records)
    assert per_test["t"][("op by op", "programs")] == 1 and totals[("curve", "xla")] == 2.0
    assert suite_compile.callers(records) == {"jaxfric/numerics/tensor.py:inv2": [2, 1.25]}
    # The caller is the package's innermost function on the stack, else the tests' or experiments'.
    frames = traceback.StackSummary.from_list([
        (suite_compile.ROOT + "tests/test_x.py", 1, "test_x", ""),
        (suite_compile.ROOT + "jaxfric/fem/element.py", 2, "gradients", ""),
        (suite_compile.ROOT + "jaxfric/numerics/tensor.py", 3, "inv2", ""),
        ("/somewhere/jax/_src/dispatch.py", 4, "apply_primitive", ""),
        (suite_compile.__file__, 5, "emit", "")])
    assert suite_compile.caller(frames) == "jaxfric/numerics/tensor.py:inv2"
    assert suite_compile.caller(frames[:1]) == "tests/test_x.py:test_x" and suite_compile.caller(frames[3:]) == "-"
    assert suite_compile.caller(frames[:1] + frames[4:]) == "tests/test_x.py:test_x"


def test_suite_programs_groups_one_computation_at_other_sizes_into_one_structure():
    import suite_programs

    def module(n, op="add"):
        return (f"func.func public @main(%arg0: tensor<{n}x2xf64>) -> tensor<{n}xf64> {{\n"
                f"  %0 = stablehlo.slice %arg0 [0:{n}, 1:2] : (tensor<{n}x2xf64>) -> tensor<{n}x1xf64>\n"
                f"  %1 = stablehlo.constant dense<{n}.5> : tensor<f64>\n"
                f"  %2 = stablehlo.{op} %0, %1 : tensor<{n}x1xf64>\n}}")

    (p20, s20), (p40, s40), (m20, t20) = (suite_programs.fingerprints(module(20)),
                                          suite_programs.fingerprints(module(40)),
                                          suite_programs.fingerprints(module(20, "multiply")))
    assert p20 != p40 and s20 == s40 and s20 != t20 and p20 != m20
    rows = suite_programs.by_structure([("tests/test_a.py::t", "main", p20, s20, 3, 1.0),
                                        ("tests/test_b.py::u", "main", p40, s40, 3, 3.0),
                                        ("tests/test_b.py::v", "main", m20, t20, 3, 0.5)])
    assert [(r["programs"], r["compile_s"], r["one_program_s"], r["beyond_one_s"], r["tests"]) for r in rows] == \
        [(2, 4.0, 3.0, 1.0, "test_a.py test_b.py"), (1, 0.5, 0.5, 0.0, "test_b.py")]


def test_suite_programs_tells_run_programs_apart_by_model_structure_and_options():
    """A scene on two meshes is two model structures; one structure run with other Newton options is one
    structure with two configurations, listed as differing in those options only."""
    import suite_programs
    from jaxfric import scenes
    from jaxfric.numerics.newton import NewtonOptions

    coarse, fine = (scenes.make("flat_die", None, "lcp_ssn", {"mesh": m}) for m in ("6x1", "8x1"))
    a = suite_programs.describe_run(coarse.model, coarse.newton, coarse.control, None)
    b = suite_programs.describe_run(coarse.model, NewtonOptions(rtol=1e-10), coarse.control, None)
    c = suite_programs.describe_run(fine.model, coarse.newton, coarse.control, None)
    assert (a["tools"], a["mesh"], a["formulation"], a["contact"], a["snapshot"]) == \
        ("die", "6x1", coarse.model.formulation, "Complementarity ssn", "-")
    assert a["structure"] == b["structure"] != c["structure"] and a["newton"] != b["newton"]
    runs = [{**r, "test": f"tests/test_{k}.py::t", "seconds": 1.0} for k, r in zip("abc", (a, b, c), strict=True)]
    (shared,) = suite_programs.shared_structures(runs)
    assert (shared["mesh"], shared["compilations"], shared["differ"], shared["tests"]) == \
        ("6x1", 2, ["newton"], ["test_a.py", "test_b.py"])


def test_blankholder_penalty_newton_counts_each_phase_and_names_the_cut_causes():
    """Row 0 (the initial state) is no step; a cut step's causes are read from its bit mask (bit k: Result k)."""
    import types

    import blankholder_penalty_newton
    from jaxfric.numerics.results import Result

    history = {"phase_name": np.array(["close", "close", "close", "draw", "draw"]),
               "newton_iters": np.array([0, 4, 30, 5, 6]), "cutbacks": np.array([0, 0, 2, 0, 1]),
               "cut_codes": np.array([0, 0, (1 << Result.MAX_ITERATIONS) | (1 << Result.INVERTED_ELEMENT), 0,
                                      1 << Result.MAX_ITERATIONS]),
               "drawing_force": np.array([0.0, 0.0, 0.0, 1.0, 2.0]), "clamping_force": np.full(5, 3.0)}
    result = types.SimpleNamespace(history=history, wall_s=1.5, converged=True)
    rows = blankholder_penalty_newton.phase_rows("penalty", result)
    assert [(r["phase"], r["steps"], r["newton_iterations"], r["cut_steps"], r["cut_causes"]) for r in rows] == \
        [("close", 2, 34, 1, "inverted_element:1 max_iterations:1"), ("draw", 2, 11, 1, "max_iterations:1")]
    assert rows[0]["drawing_force_end"] == 2.0


def test_bench_preselection_times_the_pairs_with_and_without_the_selection():
    import bench_preselection

    (row,) = bench_preselection.geometry("40x2", "lcp_ssn")
    assert 0 < row["evaluated"] < row["candidates"] and row["ms_on"] > 0 and row["ms_off"] > 0


def test_bench_scaling_times_each_part_of_every_mesh_in_every_round(tmp_path):
    import bench_scaling

    out = tmp_path / "scaling.csv"
    bench_scaling.main(["--mesh", "30x2", "--u0", "0.2", "--rounds", "2", "--calls", "1", "--out", str(out)])
    with open(out, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["part"] for r in rows] == ["elements", "pairs", "solve"]
    assert all(float(r["ms"]) > 0 and r["rounds"] == "2" for r in rows)
    assert {(r["elements"], r["blocks"], r["block_size"]) for r in rows} == {("60", "31", "6")}


def test_nine_tool_forces_averages_the_steady_window_and_takes_the_change_between_meshes(tmp_path):
    import nine_tool_forces as ntf

    u = np.linspace(0.0, 36.0, 73)   # rows every 0.5 mm: the window [20, 35] holds 31 of them
    history = {"drawing_displacement": u, **{c: u + i for i, c in enumerate(ntf.COLUMNS)}}
    means = ntf.steady_means(history, (20.0, 35.0))
    assert means == pytest.approx({c: 27.5 + i for i, c in enumerate(ntf.COLUMNS)}, rel=1e-14)
    with pytest.raises(ValueError, match="no history row"):
        ntf.steady_means({**history, "drawing_displacement": u / 10.0}, (20.0, 35.0))
    rows = [{"variant": "mu017", "mesh": "300x3", **means},
            {"variant": "mu017", "mesh": "600x3", **{c: v - 1.5 for c, v in means.items()}},
            {"variant": "mu000", "mesh": "300x3", **means}]   # no finer mesh: no change row
    (change,) = ntf.changes(rows)
    assert change["variant"] == "mu017" and all(change[c] == pytest.approx(-1.5) for c in ntf.COLUMNS)
    # The split at an instant: a normal force n = (0.6, 0.8) of 10 N/mm and a friction force of 2 along
    # t = (-0.8, 0.6) give x components 6 and -1.6; an open pair of another tool counts for nothing.
    path = tmp_path / "contact.npz"
    np.savez(path, tool_names=np.array(["A", "B", "C"]), pair_tool=np.array([0, 1, 2]),
             steady__rn=np.array([10.0, 0.0, 4.0]), steady__rt=np.array([2.0, 0.0, 0.0]),
             steady__normal=np.array([[0.6, 0.8], [0.0, 1.0], [1.0, 0.0]]))
    a, b, c = ntf.split_at_instant(str(path))
    assert (a["closed_pairs"], a["normal_force"]) == (1, 10.0)
    assert a["normal_x"] == pytest.approx(6.0) and a["friction_x"] == pytest.approx(-1.6)
    assert a["normal_tilt_deg"] == pytest.approx(np.degrees(np.arctan2(6.0, 8.0)))
    assert b["closed_pairs"] == 0 and b["normal_x"] == 0.0 and c["normal_x"] == pytest.approx(4.0)


def test_nine_tool_forces_finds_a_curvature_reversal_and_splits_a_tools_pairs_along_the_strip(tmp_path):
    import nine_tool_forces as ntf

    # A strip of 3 rows (the middle one not a face) whose centre line turns with curvature -k up to
    # s = 3 mm, then +k from s = 4 mm, linearly in between: the reversal from -0.9 k to +0.9 k is 0.9 mm
    # long, centred on s = 3.5 mm.
    h, k, cols = 0.1, 0.2, 81
    s = h * np.arange(cols)
    mid = s[:-1] + 0.5 * h

    def turned(a):   # the centre line's angle: the integral of the curvature
        return np.where(a < 3.0, -k * a, np.where(a < 4.0, -3 * k + k * ((a - 3.0) ** 2 - (a - 3.0)),
                                                  -3 * k + k * (a - 4.0)))
    chord = h * np.stack([np.cos(turned(mid)), np.sin(turned(mid))], axis=1)
    c = np.concatenate([[[0.0, 0.0]], np.cumsum(chord, axis=0)])
    normal = np.stack([-np.sin(turned(s)), np.cos(turned(s))], axis=1)
    x0 = np.concatenate([np.stack([s, np.full(cols, y)], axis=1) for y in (0.0, 0.5, 1.0)])
    x = np.concatenate([c - 0.5 * normal, c, c + 0.5 * normal])
    column, bottom, top = ntf.strip_columns(x0)
    assert list(bottom) == list(range(cols)) and list(top) == list(range(2 * cols, 3 * cols))
    assert list(column[cols:2 * cols]) == list(range(cols))
    arc, kappa = ntf.centreline(x, bottom, top)
    assert arc == pytest.approx(s, abs=1e-12) and np.isnan(kappa[[0, -1]]).all()
    assert kappa[5:25] == pytest.approx(-k, rel=1e-9) and kappa[45:75] == pytest.approx(k, rel=1e-9)
    (turn,) = ntf.reversals(arc, kappa, 0.9 * k)
    assert turn["to"] == "+" and turn["s_mid"] == pytest.approx(3.5, abs=0.01)
    assert turn["length"] == pytest.approx(0.9, abs=0.02)
    assert ntf.reversals(arc, -kappa, 0.9 * k)[0]["to"] == "-" and ntf.reversals(arc, kappa, 1.1 * k) == []

    # Tool A closed at the bottom nodes of columns 0, 1, 2 (the entry end, within 0.5 mm of the first),
    # 10 (the middle) and 20, 21 (the exit end); a pair of column 15 open, one of tool B elsewhere.
    cols_a = [0, 1, 2, 10, 20, 21, 15]
    path = tmp_path / "contact.npz"
    rn = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 0.0, 7.0])
    np.savez(path, tool_names=np.array(["A", "B"]), pair_tool=np.array([0] * 7 + [1]),
             pair_node=np.array(cols_a + [40]), x0=x0, steady__x=x0, steady__rn=rn, steady__rt=0.5 * rn,
             steady__normal=np.tile([[0.6, 0.8]], (8, 1)))
    parts = {(r["tool"], r["part"]): r for r in ntf.split_by_patch(str(path), tools=("A", "B"), end_arc=0.5)}
    assert [parts[("A", p)]["closed_pairs"] for p in ("entry", "middle", "exit")] == [3, 1, 2]
    assert [parts[("A", p)]["normal_force"] for p in ("entry", "middle", "exit")] == [6.0, 4.0, 11.0]
    assert parts[("A", "exit")]["normal_x"] == pytest.approx(6.6)
    assert parts[("A", "exit")]["friction_x"] == pytest.approx(-0.8 * 0.5 * 11.0)   # t = (-0.8, 0.6)
    assert (parts[("A", "exit")]["arc_from"], parts[("A", "exit")]["arc_to"]) == pytest.approx((2.0, 2.1))
    assert parts[("B", "entry")]["normal_force"] == 7.0 and ("B", "exit") not in parts


def test_plastic_integration_takes_each_rules_limit_and_the_errors_against_the_midpoint_rules():
    import plastic_integration as pi

    # Forces of a first-order (radial) and a second-order (midpoint) ladder towards 100 and 100.5 N/mm.
    rows = [{"case": f"{v}_{i}_{d:g}", "variant": v, "integration": i, "increment": d, "steps": 1,
             "newton_iterations": 1, "cutbacks": 0,
             "steady_force": (100.0 + 20.0 * d) if i == "radial" else (100.5 - 50.0 * d * d)}
            for v in ("mu017",) for i in pi.INTEGRATIONS for d in pi.INCREMENTS]
    out = {r["case"]: r for r in pi.with_errors(rows)}
    assert out["mu017_radial_0.1"]["limit"] == pytest.approx(100.0)
    assert out["mu017_radial_0.1"]["q"] == pytest.approx(2.0)
    assert out["mu017_midpoint_0.1"]["limit"] == pytest.approx(100.5)
    assert out["mu017_midpoint_0.1"]["q"] == pytest.approx(4.0)
    assert out["mu017_midpoint_0.1"]["step_error_pct"] == pytest.approx(-0.5 / 100.5 * 100.0)
    assert out["mu017_radial_0.05"]["step_error_pct"] == pytest.approx((101.0 / 100.5 - 1.0) * 100.0)
    assert pi.with_errors([r for r in rows if r["integration"] == "radial"]) == []   # no midpoint ladder


def test_ssn_passes_sorts_each_status_change_by_kind():
    import ssn_passes
    from jaxfric.contact.alart_curnier import OPEN, SLIP_NEG, SLIP_POS, STICK

    before = np.array([OPEN, OPEN, STICK, STICK, SLIP_POS, SLIP_POS, SLIP_NEG, STICK])
    after = np.array([STICK, OPEN, OPEN, SLIP_NEG, STICK, SLIP_NEG, OPEN, STICK])
    kinds = {k: np.flatnonzero(m).tolist() for k, m in ssn_passes.changes(before, after).items()}
    assert kinds == {"open_to_closed": [0], "closed_to_open": [2, 6], "stick_to_slip": [3],
                     "slip_to_stick": [4], "slip_reversed": [5]}
    assert set(kinds) == set(ssn_passes.KINDS)


# ---- experiments/nine_quadratic.py: the corner-node contact and the case table (no simulation) ----------

def test_nine_quadratic_corner_contact_and_empty_table(tmp_path, capsys):
    """``corners_only`` keeps the tools' candidates on the corner columns of a six-node mesh (every tool
    keeps some), and a table read from an empty folder writes no CSV (it once truncated the one there)."""
    import nine_quadratic
    from jaxfric import scenes

    scene = scenes.make("nine", "mu017", "lcp_ssn", {"mesh": "40x2", "element": "anst", "element_order": 2})
    model = nine_quadratic.corners_only(scene.model)
    for before, after in zip(scene.model.tools, model.tools, strict=True):
        columns = [n // 3 for n in after.candidates]
        assert after.candidates and all(c % 2 == 0 for c in columns)
        assert set(after.candidates) == {n for n in before.candidates if (n // 3) % 2 == 0}
    csv_path = tmp_path / "table.csv"
    assert nine_quadratic.run_cases_main(["--root", str(tmp_path / "none"), "--table"], nine_quadratic.__doc__,
                                         nine_quadratic.CASES, nine_quadratic.run_one, "", str(csv_path)) == 0
    assert not csv_path.exists()
