"""The accuracy-cost report (jaxfric.identification.accuracy): error measures, the Pareto front, the sweep's plan, and
(slow) the quick report end to end."""

from __future__ import annotations

import csv
import os

import numpy as np
import pytest

from jaxfric import scenes
from jaxfric.cli import main
from jaxfric.identification import accuracy, accuracy_report


def _run(u, force, converged=True, contact=None, **summary):
    phase = np.array(["clamp"] + ["draw"] * (len(u) - 1))
    s = {"converged": converged, "steady_drawing_force": None, "peak_drawing_force": float(np.max(force)),
         "final_clamping_force": 50.0, **summary}
    return {"summary": s, "history": {"phase": phase, "drawing_displacement": np.asarray(u, float),
                                      "drawing_force": np.asarray(force, float)}, "contact": contact or {}}


def _contact(x, rn, instant="final"):
    x = np.asarray(x, float)
    return {"pair_tool": np.zeros(len(x), int), "pair_node": np.arange(len(x)),
            f"{instant}__x": np.stack([x, np.zeros_like(x)], axis=1), f"{instant}__rn": np.asarray(rn, float)}


def test_pareto_front_keeps_the_points_nothing_beats():
    pts = [(1.0, 0.5, "a"), (2.0, 0.1, "b"), (3.0, 0.2, "c"), (0.5, 1.0, "d"), (2.5, 0.1, "e")]
    assert [p[2] for p in accuracy_report.pareto_front(pts)] == ["d", "a", "b"]


def test_error_measures_against_the_reference():
    u = np.linspace(0.0, 1.0, 21)
    ref = _run(u, 10 + u, steady_drawing_force=10.5, contact=_contact([0.0, 2.0], [1.0, 1.0]))
    same = accuracy.error_measures(ref, ref, "final")
    assert all(v == 0 for v in same.values()), same
    # 1 % higher everywhere: steady, peak and curve errors are 1 %; the clamping force did not change.
    run = _run(u, 1.01 * (10 + u), steady_drawing_force=1.01 * 10.5,
               contact=_contact([0.0, 1.0, 2.0], [1.0, 1.0, 0.0]))
    err = accuracy.error_measures(run, ref, "final")
    for key in ("err_steady", "err_peak", "err_curve_l2"):
        assert err[key] == pytest.approx(0.01, rel=1e-9), key
    assert err["err_clamp"] == 0
    # The second unit force moved from x = 2 to x = 1: cumulative forces differ by 1 over [1, 2), an
    # area of 1, over total force 2 x contact length 2.
    assert err["err_pressure"] == pytest.approx(0.25, rel=1e-12)


def test_pressure_distance_ignores_round_off_in_positions():
    rng = np.random.default_rng(0)
    x = np.sort(rng.uniform(0, 10, 40))
    rn = rng.uniform(0, 5, 40)
    shifted = _contact(x + 1e-13 * rng.standard_normal(40), rn)
    assert accuracy._cumulative_difference(shifted, _contact(x, rn), "final") < 1e-12


def test_a_stopped_run_has_no_curve_error():
    u = np.linspace(0.0, 1.0, 11)
    ref = _run(u, 10 + u)
    assert accuracy.error_measures(_run(u[:5], 10 + u[:5], converged=False), ref, "final")["err_curve_l2"] is None


def _check_rows(check_change, sweep_errors):
    rows = [{"test": "t", "family": "ref_check", "converged": True, **{m: check_change for m in accuracy.MEASURES}}]
    rows += [{"test": "t", "family": "penalty", "converged": True, **{m: e for m in accuracy.MEASURES}}
             for e in sweep_errors]
    return accuracy_report.reference_checks(rows)["t"]["err_steady"]


def test_reference_check_needs_a_resolved_error_or_round_off():
    """The reference is converged when its checks move a measure by less than a tenth of the smallest
    resolved error; with no error resolved, only if the checks agree to round-off (a reference whose
    own mesh halving moves it 5 % verifies nothing, even if every run is "within" that)."""
    assert _check_rows(1e-4, [1e-2, 5e-2])["converged"]
    partly = _check_rows(2e-3, [1e-2, 5e-2])   # 1e-2 is below the resolution 2e-2: unresolved
    assert partly["converged"] and partly["n_unresolved"] == 1 and partly["smallest_error"] == 5e-2
    unresolved = _check_rows(0.05, [0.1, 0.2])
    assert unresolved["smallest_error"] is None and unresolved["n_unresolved"] == 2
    assert not unresolved["converged"]
    assert _check_rows(2e-13, [1e-13, 3e-13])["converged"]


@pytest.mark.parametrize("test", accuracy.TESTS + accuracy.QUICK_TESTS, ids=lambda t: t.name)
def test_plan_of_each_test(test):
    plan = accuracy.cases(test)
    labels = [p[0] for p in plan]
    assert len(labels) == len(set(labels))
    families = {p[1] for p in plan}
    assert {"penalty", "auglag", "step", "reference", "ref_check"} <= families
    assert ("mesh" in families) == bool(test.meshes)
    assert [p[0] for p in plan if p[1] == "reference"] == [test.reference]
    ref = next(p[3] for p in plan if p[1] == "reference")
    nx_ref, ny_ref = map(int, ref["mesh"].split("x"))
    for label, family, _, ov in plan:
        nx, ny = map(int, ov["mesh"].split("x"))
        if family != "ref_check":
            assert nx <= nx_ref and ny <= ny_ref, label  # no sweep run finer than the reference
    # The reference takes ref_step times the nominal increments (half by default); its step check half that.
    check = next(p[3] for p in plan if p[0] == f"ref_check_step{test.tag}")
    base = next(p[3] for p in plan if p[0] == "step_x2")
    for field in scenes.SCENES[test.scene].STEP_FIELDS:
        if isinstance(ref[field], float):
            assert ref[field] == pytest.approx(base[field] / 2 * test.ref_step)
            assert check[field] == pytest.approx(base[field] / 4 * test.ref_step)
    assert ref.get("target_gap") == (test.ref_gap if test.ref_algorithm == "auglag" else None)
    # Each mesh check halves the reference's elements as named, with the reference's algorithm and steps.
    for name in {"mesh", "mesh_x", "mesh_y"} & set(test.ref_checks):
        label, family, algorithm, ov = next(p for p in plan if p[0] == f"ref_check_{name}{test.tag}")
        nx, ny = map(int, ov["mesh"].split("x"))
        assert (nx / nx_ref, ny / ny_ref) == {"mesh": (2, 2), "mesh_x": (2, 1), "mesh_y": (1, 2)}[name]
        assert algorithm == test.ref_algorithm and {k: v for k, v in ov.items() if k != "mesh"} == \
            {k: v for k, v in ref.items() if k != "mesh"}


def test_the_same_mesh_test_shares_its_parents_sweep_runs():
    """``nine_mu017_at_100x2`` measures the contact algorithm and the step size on the sweep's own mesh:
    its sweep runs are the parent's (same overrides, same directories), its reference and check are its
    own (on the sweep's mesh, only the step check), and it has no mesh family."""
    by = {t.name: t for t in accuracy.TESTS}
    parent, same = by["nine_mu017"], by["nine_mu017_at_100x2"]
    assert same.run_dir == parent.run_dir == "nine_mu017"
    mine = {p[0]: p for p in accuracy.cases(same)}
    theirs = {p[0]: p for p in accuracy.cases(parent)}
    sweep = [label for label, p in mine.items() if p[1] not in ("reference", "ref_check")]
    assert sweep and all(mine[label] == theirs[label] for label in sweep)
    own = [label for label in mine if label not in sweep]
    assert own == ["reference_at_100x2", "ref_check_step_at_100x2"] and not set(own) & set(theirs)
    assert mine["reference_at_100x2"][3]["mesh"] == "100x2" == mine["penalty_eps1e+05"][3]["mesh"]


def _fake_run_case(path, scene, variant, algorithm, ov, **_):
    """A stand-in for :func:`jaxfric.io.batch.run_case`: writes a summary so the run is "on disk" and
    returns a run whose steady force depends on the penalty."""
    import json

    os.makedirs(path, exist_ok=True)
    force = 10.0 * (1.0 + 1.0 / ov.get("eps_n", 1e12))
    s = {"converged": True, "steady_drawing_force": force, "peak_drawing_force": force,
         "final_clamping_force": 50.0, "wall_s": 1.0, "n_steps": 3, "newton_iters_total": 7}
    with open(os.path.join(path, "summary.json"), "w") as fh:
        json.dump(s, fh)
    return {"summary": s, "history": None, "contact": None}


def test_a_report_keeps_the_rows_of_tests_whose_runs_are_gone(tmp_path, monkeypatch):
    """Run directories are not kept with the results: running one test, then another after the first's
    directories are gone, still reports both (the first from the CSV, with its types), and the CSV
    written between runs holds the first test's rows too."""
    import shutil

    base = accuracy.QUICK_TESTS[0]
    other = accuracy.Test(**{**{f: getattr(base, f) for f in base.__dataclass_fields__}, "tag": "_b"})
    monkeypatch.setattr(accuracy, "QUICK_TESTS", (base, other))
    monkeypatch.setattr(accuracy, "run_case", _fake_run_case)
    monkeypatch.setattr(accuracy_report, "_pareto_figure", lambda *a, **k: None)
    out = str(tmp_path)
    first = accuracy_report.accuracy_cost(out, quick=True, tests=[base.name])
    shutil.rmtree(os.path.join(out, "runs", base.name))
    seen = []
    real_write = accuracy_report.write_csv
    monkeypatch.setattr(accuracy_report, "write_csv",
                        lambda path, rows: seen.append({r["test"] for r in rows}) or real_write(path, rows))
    rows = accuracy_report.accuracy_cost(out, quick=True, tests=[other.name])
    assert [r for r in rows if r["test"] == base.name] == first
    assert {r["test"] for r in rows} == {base.name, other.name}
    assert seen and all(base.name in names for names in seen)
    assert isinstance(first[0]["n_steps"], int) and isinstance(first[0]["converged"], bool)
    assert "| flat_die_const_force_b |" in (tmp_path / "accuracy_cost.md").read_text()
    # Both tests again, their directories gone: while the first runs, the CSV still holds the second's
    # earlier rows.
    shutil.rmtree(os.path.join(out, "runs"))
    seen.clear()
    accuracy_report.accuracy_cost(out, quick=True)
    assert seen and all(names == {base.name, other.name} for names in seen)


def test_report_rejects_an_unknown_test(capsys, tmp_path):
    assert main(["report", "accuracy-cost", "--quick", "--test", "nine_mu017", "--out", str(tmp_path)]) == 2
    assert "--test" in capsys.readouterr().err


@pytest.mark.slow
def test_quick_report_end_to_end(tmp_path):
    """``jaxfric report accuracy-cost --quick``: every run converges, the CSV has one row per run with
    its errors, the figure and the recommendations are written, and the reference's curve is converged
    (its checks move it less than a tenth of the smallest error of the sweep). About 3 minutes."""
    out = tmp_path / "ac"
    assert main(["report", "accuracy-cost", "--quick", "--out", str(out), "--quiet"]) == 0
    with open(out / "accuracy_cost.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == len(accuracy.cases(accuracy.QUICK_TESTS[0]))
    assert all(r["converged"] == "True" for r in rows)
    assert all(r["err_curve_l2"] != "" for r in rows)
    assert os.path.exists(out / "pareto_flat_die_const_force.png")
    text = (out / "accuracy_cost.md").read_text()
    assert "What to pick" in text and "| flat_die_const_force | err_curve_l2 |" in text.replace("`", "")
    # A looser penalty penetrates more and errs more on the curve.
    by = {r["run"]: r for r in rows}
    assert float(by["penalty_eps1e+06"]["max_penetration"]) > float(by["penalty_eps1e+08"]["max_penetration"])
    assert float(by["penalty_eps1e+06"]["err_curve_l2"]) > float(by["penalty_eps1e+08"]["err_curve_l2"])


@pytest.mark.slow  # two runs and the replay's compilation: about a minute
def test_penalty_sensitivity_estimates_the_penalty_error_of_a_held_die(tmp_path, capsys):
    """``jaxfric run --error-estimate sensitivity``: with the die held in place the penalty's compliance,
    not the penetration, sets the clamping force and with it the drawing force. eps_N dF/d eps_N / F
    (forward mode along the run) must match the actual difference from exact contact on the same mesh
    and steps to within a factor 1.5 at eps_N = 1e6, where the basic estimate (penetration / thickness)
    is 1e-5 of it. (At eps_N = 1e5 the error is no longer first order in 1/eps_N: at 24 x 1 the
    estimate is 1.75 against 2.71 N/mm; at 120 x 1, 0.686 against 0.713.)"""
    import json

    common = ["run", "flat_die", "--variant", "const_position", "--mesh", "24x1", "--quiet",
              "--set", "steady_window=0.02,0.03"]
    assert main(common + ["--algorithm", "penalty", "--set", "eps_n=1e6", "--error-estimate", "sensitivity",
                          "--out", str(tmp_path / "pen")]) == 0
    assert main(common + ["--algorithm", "lcp_ssn", "--out", str(tmp_path / "ssn")]) == 0
    pen = json.loads((tmp_path / "pen" / "summary.json").read_text())
    ssn = json.loads((tmp_path / "ssn" / "summary.json").read_text())
    est = pen["error_estimate"]
    actual = abs(pen["steady_drawing_force"] - ssn["steady_drawing_force"])
    assert actual > 0.1 * ssn["steady_drawing_force"]          # a soft penalty: a large error to estimate
    penalty = est["components"]["penalty"] * abs(est["value"])
    assert actual / 1.5 <= penalty <= 1.5 * actual
    assert est["components"]["contact"] < 1e-3 * est["components"]["penalty"]
    assert "penalty" in capsys.readouterr().out          # printed among the components


def test_mesh_estimate_runs_the_coarser_companion_and_says_what_it_left_out(tmp_path, capsys):
    """``jaxfric run --error-estimate mesh``: the summary holds the companion's mesh (half the elements
    along, the same layers) and the component it gives, and names the step's and the layers' shares as not
    estimated; ``mesh_fine,layers`` runs the companions with twice the elements along and through; a basic
    run's printed line names the three discretisation components as not estimated."""
    import json

    common = ["run", "flat_die", "--variant", "const_position", "--mesh", "24x1", "--quiet", "--algorithm",
              "lcp_ssn", "--set", "steady_window=0.02,0.03"]
    assert main(common + ["--error-estimate", "mesh", "--out", str(tmp_path / "mesh")]) == 0
    est = json.loads((tmp_path / "mesh" / "summary.json").read_text())["error_estimate"]
    assert est["mesh_check"]["mesh"] == [12, 1] and est["mesh_check"]["ratio"] == 2.0
    assert est["components"]["mesh"] == pytest.approx(abs(est["value"] - est["mesh_check"]["value"]) / est["value"])
    assert est["not_estimated"] == ["step", "layers"]
    out = capsys.readouterr().out
    assert "mesh" in out and "not estimated: step and layers discretisation (--error-estimate step,layers)" in out
    assert main(common + ["--error-estimate", "mesh_fine,layers", "--out", str(tmp_path / "fine")]) == 0
    est = json.loads((tmp_path / "fine" / "summary.json").read_text())["error_estimate"]
    assert est["mesh_check"]["mesh"] == [48, 1] and est["mesh_check"]["ratio"] == 0.5
    assert est["layers_check"]["mesh"] == [24, 2] and est["layers_check"]["ratio"] == 0.5
    assert est["components"]["mesh"] == pytest.approx(2 * abs(est["value"] - est["mesh_check"]["value"]) / est["value"])
    assert est["not_estimated"] == ["step"]
    capsys.readouterr()
    assert main(common + ["--out", str(tmp_path / "basic")]) == 0
    basic = capsys.readouterr().out
    assert "not estimated: step, mesh and layers discretisation (--error-estimate step,mesh_fine,layers)" in basic


@pytest.mark.parametrize("text", ["mesh,mesh_fine", "step,step", "thickness", "basic,step"])
def test_error_estimate_options_are_checked_when_parsed(text, capsys):
    assert main(["run", "flat_die", "--mesh", "24x1", "--error-estimate", text]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert "--error-estimate" in err[-1] and text in err[-1]


def test_penalty_sensitivity_is_refused_for_other_algorithms(capsys):
    assert main(["run", "flat_die", "--algorithm", "lcp_ssn", "--error-estimate", "sensitivity",
                 "--mesh", "24x1"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--error-estimate" in err[0] and "penalty" in err[0]


def test_a_run_on_disk_made_with_other_parameters_is_not_read_back(tmp_path, monkeypatch):
    """``run_case`` reads a run back only if its recorded config matches the requested overrides (a
    changed reference step, for example, must not silently reuse the old run)."""
    import json

    from jaxfric.io import batch

    path = tmp_path / "summary.json"
    config = {"nx": 100, "ny": 2, "dU": 0.05, "eps_n": 1e5, "eps_t": None}
    path.write_text(json.dumps({"converged": True, "message": "", "parameters": {"config": config}}))
    assert batch.stale(str(path), {"mesh": "100x2", "dU": 0.1 * 0.5, "eps_n": 100000}) is None
    assert batch.stale(str(path), {"dU": 0.05 / 16}) == "dU = 0.05, not 0.003125"
    assert batch.stale(str(path), {"mesh": "200x4"}) == "nx = 100, not 200"
    assert batch.stale(str(path), {"unknown_field": 1}) is None  # not a config field: not compared
    # A field added after the run was made: the run had its default.
    path.write_text(json.dumps({"scene": "nine", "converged": True, "message": "", "parameters": {"config": config}}))
    assert batch.stale(str(path), {"max_steps": None}) is None
    assert batch.stale(str(path), {"max_steps": 30000}) == "max_steps = None, not 30000"
    assert batch.stale(str(path), {"max_augmentations": 60}) == "max_augmentations = 20, not 60"
    assert batch.stale(str(path), {"unknown_field": 1}) is None
    import importlib

    run_module = importlib.import_module("jaxfric.loadpath.run")

    class Reached(BaseException):  # not caught by run_case's handler of failed cases
        pass

    def refuse(*a, **k):
        raise AssertionError("a matching run was rerun")

    monkeypatch.setattr(run_module, "run", refuse)
    assert batch.run_case(str(tmp_path), "nine", "mu017", "auglag", {"mesh": "100x2", "dU": 0.05},
                          log=lambda m: None)["summary"]["converged"]

    def reached(*a, **k):
        raise Reached

    monkeypatch.setattr(run_module, "run", reached)
    with pytest.raises(Reached):
        batch.run_case(str(tmp_path), "nine", "mu017", "auglag", {"mesh": "100x2", "dU": 0.025},
                       log=lambda m: None)


def test_a_run_made_before_a_default_changed_is_not_read_back_as_the_new_default(tmp_path):
    """A summary that names its scene and variant is compared on every recorded field: one left out of
    the request must hold the variant's value or today's default (an F-bar run is not the default's)."""
    import json

    from jaxfric import scenes
    from jaxfric.io import batch

    defaults = {f[0]: f[1] for f in scenes.config_fields("blankholder")}
    variant = scenes.variant_values("blankholder", "shape3")
    assert any(defaults[k] != v for k, v in variant.items())  # the variant's values are not differences
    config = json.loads(json.dumps({k: list(v) if isinstance(v, tuple) else v
                                    for k, v in {**defaults, **variant}.items()}))
    path = tmp_path / "summary.json"

    def record(**fields):
        path.write_text(json.dumps({"scene": "blankholder", "variant": "shape3", "converged": True,
                                    "message": "", "parameters": {"config": {**config, **fields}}}))

    record()
    assert batch.stale(str(path), {}) is None
    record(element="fbar", lock_control="depth")
    assert batch.stale(str(path), {"lock_control": "depth"}) == "element = 'fbar', not 'anst'"
    assert batch.stale(str(path), {"lock_control": "depth", "element": "fbar"}) is None
    assert batch.stale(str(path), {"element": "fbar"}) == "lock_control = 'depth', not 'force'"
    record(removed_field=1)  # a field the config no longer has is not compared
    assert batch.stale(str(path), {}) is None


def test_collect_runs_nothing_and_skips_runs_made_with_other_parameters(tmp_path, monkeypatch):
    """Collecting a report never runs: a run on disk made with other parameters than the plan's counts as
    missing (for the reference, the test's rows then come from the CSV)."""
    import importlib
    import json

    monkeypatch.setattr(importlib.import_module("jaxfric.loadpath.run"), "run",
                        lambda *a, **k: pytest.fail("collect ran a simulation"))
    test = accuracy.QUICK_TESTS[0]
    plan = {p[0]: p[3] for p in accuracy.cases(test)}
    for label in (test.reference, "penalty_eps1e+06"):
        path = tmp_path / "runs" / test.run_dir / label
        path.mkdir(parents=True)
        nx, ny = (int(v) for v in plan[label]["mesh"].split("x"))
        config = {**{k: v for k, v in plan[label].items() if k != "mesh"}, "nx": nx, "ny": ny}
        if label == "penalty_eps1e+06":
            config["eps_n"] = 1.0  # made with another penalty
        (path / "summary.json").write_text(json.dumps({"converged": True, "message": "",
                                                       "parameters": {"config": config}}))
    assert [r["run"] for r in accuracy.collect(str(tmp_path), quick=True)] == [test.reference]


@pytest.mark.parametrize("recorded, requested, same", [
    ({"eps_t": None}, {"eps_t": None}, True),
    ({"eps_t": None}, {"eps_t": 1e4}, False),
    ({"eps_t": None}, {"eps_t": float("inf")}, True),      # summary.json stores inf as null
    ({"steady_window": [20.0, 35.0]}, {"steady_window": (20.0, 35.0)}, True),
    ({"steady_window": [20.0, 35.0]}, {"steady_window": (20.0, 30.0)}, False),
    ({"eps_n": 100000.0}, {"eps_n": "1e5"}, True),         # a --set value, as text
    ({"eps_n": 100000.0}, {"eps_n": "abc"}, False),
    ({"entry_guide": True}, {"entry_guide": "true"}, True),
    ({"entry_guide": True}, {"entry_guide": False}, False),
    ({"nx": 100, "ny": 2}, {"mesh": (100, 2)}, True),
    ({"nx": 100, "ny": 2}, {"mesh": "100X2"}, True),
    ({"nx": 100, "ny": 2}, {"mesh": "oops"}, False),
])
def test_stale_compares_values_as_summary_json_records_them(tmp_path, recorded, requested, same):
    import json

    from jaxfric.io import batch

    path = tmp_path / "summary.json"
    path.write_text(json.dumps({"variant": "mu017", "algorithm": "auglag", "parameters": {"config": recorded}}))
    assert (batch.stale(str(path), requested) is None) == same
    assert batch.stale(str(path), requested, variant="mu000") is not None  # another variant
    assert batch.stale(str(path), requested, algorithm="penalty") is not None


def test_a_failed_case_records_its_overrides(tmp_path):
    """A case that could not be built records its overrides, so a request with others runs it again."""
    from jaxfric.io import batch

    out = tmp_path / "case"
    run = batch.run_case(str(out), "nine", "mu017", "penalty", {"mesh": "10x1", "eps_n": -1.0}, log=lambda m: None)
    assert not run["summary"]["converged"] and "eps_n" in run["summary"]["message"]
    path = str(out / "summary.json")
    assert batch.stale(path, {"mesh": "10x1", "eps_n": -1.0}) is None
    assert batch.stale(path, {"mesh": "10x1", "eps_n": -2.0}) is not None
    assert batch.stale(path, {"mesh": "10x1"}) is not None


def test_rows_kept_from_the_csv_must_share_the_tests_reference():
    test = next(t for t in accuracy.TESTS if t.name == "nine_mu017_at_100x2")
    assert accuracy._same_reference({"ref_mesh": "100x2", "ref_step": 1 / 32}, test)
    assert accuracy._same_reference({}, test)  # written before the reference was recorded
    assert accuracy._same_reference({"ref_mesh": "", "ref_step": None}, test)  # such a row read from the CSV
    assert not accuracy._same_reference({"ref_mesh": "100x2", "ref_step": 0.5}, test)
    assert not accuracy._same_reference({"ref_mesh": "200x4", "ref_step": 1 / 32}, test)


def test_the_report_names_each_reference_law_and_check():
    """The reference table says which law each reference uses (AL with its gap, or exact contact) and
    every check with its mesh, so that a reader knows what the uncertainty was measured against."""
    rows = [{"test": name} for name in ("flat_die_const_force", "nine_mu017")]
    table = "\n".join(accuracy_report.reference_lines(rows, quick=False))
    assert "| flat_die_const_force | auglag, target gap 1e-08 mm | 240x2 |" in table
    assert "| nine_mu017 | lcp_ssn (exact contact) | 1200x3 | nominal / 2 | increments nominal / 4, mesh 2400x3, " \
           "mesh 1200x6 |" in table


def test_the_curve_error_starts_from_the_state_the_draw_starts_from():
    """A run whose first drawing increment is larger than the reference's is not extrapolated over the
    steep start of the draw: both curves start from the last clamping row (U = 0)."""
    def ramp(u):
        return 100.0 * np.minimum(u / 0.05, 1.0)

    fine = np.concatenate([[0.0], np.arange(1, 201) * 0.005])     # first draw row at U = 0.005
    coarse = np.concatenate([[0.0], np.arange(1, 21) * 0.05])     # first draw row at U = 0.05
    ref, run = _run(fine, ramp(fine)), _run(coarse, ramp(coarse))
    assert accuracy.error_measures(run, ref, "final")["err_curve_l2"] < 1e-3
    # Without the starting state the coarse curve would be held at 100 N/mm from U = 0.005 to 0.05.
    from jaxfric.io.batch import phase_curve

    assert phase_curve(run["history"], "drawing_displacement", "drawing_force", "draw")[0][0] == 0.05
    assert phase_curve(run["history"], "drawing_displacement", "drawing_force", "draw", start=True)[0][0] == 0.0


def test_step_component_is_twice_the_change_with_half_the_increments():
    """``error_estimate`` with a step check: 2 |F - F_half| / F on the main output (the steady force,
    else the peak), recorded with the check's value, steps and signed share."""
    from jaxfric.io import output
    from jaxfric.scenes import make

    scene = make("flat_die", "const_force", overrides={"mesh": "24x1"})
    values = {"drawing_force": [0.0, 10.0, 10.0, 10.0], "max_penetration": [0.0] * 4,
              "phase": ["clamp", "draw", "draw", "draw"], "drawing_displacement": [0.0, 0.02, 0.025, 0.03]}
    check = {"steady": 9.9, "peak": 12.0, "n_steps": 6, "mesh": (24, 1), "ratio": 0.5, "converged": True}
    est = output.error_estimate(scene, values, (0.02, 0.03), 10.0, checks={"step": check})
    assert est["components"]["step"] == pytest.approx(0.02, rel=1e-12)
    assert est["step_check"] == {"value": 9.9, "n_steps": 6, "mesh": [24, 1], "ratio": 0.5,
                                 "signed": pytest.approx(0.02, rel=1e-12)}
    assert est["relative"] >= est["components"]["step"]
    peak = output.error_estimate(scene, values, (0.02, 0.03), None, checks={"step": check})
    assert peak["quantity"] == "peak_drawing_force" and peak["components"]["step"] == pytest.approx(0.4)
    assert "step" not in output.error_estimate(scene, values, (0.02, 0.03), 10.0)["components"]


def test_mesh_and_layers_components_are_richardsons_first_order_estimates():
    """``error_estimate`` with a companion whose element length is r times the run's: |F - F_other| /
    |1 - r| / F, signed as the run minus the limit (a coarser companion r = 2, 3; a finer one r = 1/2);
    the components not estimated are named; an unknown component is refused in one line."""
    from jaxfric.io import output
    from jaxfric.scenes import make

    scene = make("flat_die", "const_force", overrides={"mesh": "24x1"})
    values = {"drawing_force": [0.0, 10.0, 10.0, 10.0], "max_penetration": [0.0] * 4,
              "phase": ["clamp", "draw", "draw", "draw"], "drawing_displacement": [0.0, 0.02, 0.025, 0.03]}
    check = {"steady": 10.4, "peak": 12.0, "n_steps": 6, "mesh": (12, 1), "ratio": 2.0, "converged": True}
    est = output.error_estimate(scene, values, (0.02, 0.03), 10.0, checks={"mesh": check})
    assert est["components"]["mesh"] == pytest.approx(0.04, rel=1e-12)
    assert est["mesh_check"]["signed"] == pytest.approx(0.04, rel=1e-12)   # coarser above: the run too
    assert est["not_estimated"] == ["step", "layers"]
    third = output.error_estimate(scene, values, (0.02, 0.03), 10.0, checks={"mesh": {**check, "ratio": 3.0}})
    assert third["components"]["mesh"] == pytest.approx(0.02, rel=1e-12)
    finer = {**check, "steady": 9.8, "mesh": (48, 1), "ratio": 0.5}
    layers = {**check, "steady": 10.1, "mesh": (24, 2), "ratio": 0.5}
    both = output.error_estimate(scene, values, (0.02, 0.03), 10.0, checks={"mesh": finer, "layers": layers})
    assert both["components"]["mesh"] == pytest.approx(0.04, rel=1e-12)
    assert both["mesh_check"]["signed"] == pytest.approx(0.04, rel=1e-12)
    assert both["components"]["layers"] == pytest.approx(0.02, rel=1e-12)
    assert both["layers_check"]["signed"] == pytest.approx(-0.02, rel=1e-12)
    assert both["not_estimated"] == ["step"]
    assert output.error_estimate(scene, values, (0.02, 0.03), 10.0)["not_estimated"] == ["step", "mesh", "layers"]
    with pytest.raises(ValueError, match="field 'checks'"):
        output.error_estimate(scene, values, (0.02, 0.03), 10.0, checks={"thickness": check})


def test_richardson_error_from_a_finer_companion_is_within_twice_the_error_beyond_first_order():
    """F = 1 + C h^p: the finer companion's first-order estimate is 2 (q - 1) / q of the true error, q = 2^p,
    so between 1 and 2 times it for p >= 1; the coarser companion's is q - 1 times it."""
    from jaxfric.io.output import richardson_error

    for p in (1.0, 1.5, 2.0, 3.0):
        q = 2.0 ** p
        f = lambda h: 1.0 + 0.3 * h ** p  # noqa: E731
        true = f(1.0) - 1.0
        fine = richardson_error(f(1.0), f(0.5), 0.5)
        coarse = richardson_error(f(1.0), f(2.0), 2.0)
        assert fine / true == pytest.approx(2 * (q - 1) / q) and 1.0 <= fine / true < 2.0
        assert coarse / true == pytest.approx(q - 1)
    with pytest.raises(ValueError, match="field 'ratio'"):
        richardson_error(1.0, 1.0, 1.0)


@pytest.mark.parametrize("scene, field, value", [("nine", "nx", 150), ("bead", "nx", 362), ("flat_die", "nx", 120),
                                                 ("blankholder", "element_length", 1.0)])
def test_coarser_along_halves_the_elements_along_the_strip(scene, field, value):
    """The mesh check's companion: half the elements along the strip (nx // 2, or the blankholder's
    element length doubled where nx is derived from it), the layers unchanged."""
    from jaxfric import scenes

    config = scenes.make(scene).config
    assert scenes.coarser_along(scene, config) == {field: value}


@pytest.mark.parametrize("scene", ["flat_die", "bead", "nine", "blankholder"])
def test_scaled_steps_halves_increments_and_doubles_step_counts(scene):
    from jaxfric import scenes

    config = scenes.config_class(scene)()
    half = scenes.scaled_steps(scene, config, 0.5)
    assert set(half) == set(scenes.SCENES[scene].STEP_FIELDS)
    for field, value in half.items():
        old = getattr(config, field)
        assert value == (2 * old if isinstance(old, int) else 0.5 * old)
    # The halved run has twice the nominal steps in every phase.
    built = scenes.make(scene, None, overrides=half)
    base = scenes.make(scene, None)
    def counts(s):
        return [sum(n for _, n in p.increments) for p in s.model.phases]

    assert counts(built) == [2 * n for n in counts(base)]
    with pytest.raises(ValueError, match="'factor'"):
        scenes.scaled_steps(scene, config, 0.0)


@pytest.mark.parametrize("scene, along, through", [("nine", {"nx": 600}, {"ny": 6}), ("bead", {"nx": 1450}, {"ny": 8}),
                                                   ("flat_die", {"nx": 480}, {"ny": 4}),
                                                   ("blankholder", {"element_length": 0.25}, {"ny": 4})])
def test_finer_companions_double_the_elements_along_or_through(scene, along, through):
    """The mesh_fine and layers companions: twice the elements along the strip (the blankholder's element
    length halved), or twice the layers."""
    from jaxfric import scenes

    config = scenes.make(scene).config
    assert scenes.finer_along(scene, config) == along
    assert scenes.finer_through(scene, config) == through
