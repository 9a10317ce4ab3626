"""The run output contract (outputs spec): instants, steady force, writer, checker and command line."""

import dataclasses
import json
import os
import shutil

import numpy as np
import pytest

import jaxfric as jf
from jaxfric import cli
from jaxfric.contact.status import contact_status
from jaxfric.io import instants, output
from jaxfric.io.contract import check_run_dir
from jaxfric.numerics.results import Result

# A few-second flat die: 24 x 2 mesh, 2 clamp steps, 3 draw steps to U = 3 um (cf. spec section 2).
SHORT = ["--mesh", "24x2", "--set", "n_clamp=2", "--set", "U_draw=0.003", "--set", "U_fine=0.001",
         "--set", "dU_fine=0.0005", "--set", "dU=0.001", "--set", "steady_window=0.002,0.003"]
OVERRIDES = {"mesh": "24x2", "n_clamp": "2", "U_draw": "0.003", "U_fine": "0.001", "dU_fine": "0.0005",
             "dU": "0.001", "steady_window": "0.002,0.003"}
PNGS = ("forces.png", "contact.png", "mesh.png")


# ---- named instants ---------------------------------------------------------------------------------

def _history(phases, time, u=None, active=None, slip=None):
    n = len(phases)
    return {"phase_name": np.array(phases), "time": np.asarray(time, float),
            "drawing_displacement": np.zeros(n) if u is None else np.asarray(u, float),
            "n_active": np.zeros(n, int) if active is None else np.asarray(active),
            "n_slip": np.zeros(n, int) if slip is None else np.asarray(slip)}


def test_flat_die_instants():
    h = _history(["clamp", "clamp", "clamp", "draw", "draw", "draw", "draw"],
                 [0, 0.5, 1.0, 1.25, 1.5, 1.75, 2.0],
                 active=[0, 9, 9, 9, 9, 9, 9], slip=[0, 9, 9, 2, 5, 9, 9])
    names, rows, fallback = instants.select_instants("flat_die", h)
    assert names == ["clamped", "intermediate", "sliding", "final"]
    assert rows == [2, 4, 5, 6] and fallback == []


def test_flat_die_state_instants_fall_back_to_last_row():
    h = _history(["clamp", "clamp", "draw", "draw"], [0, 1, 1.5, 2], active=[0, 9, 9, 0], slip=[0, 9, 1, 0])
    names, rows, fallback = instants.select_instants("flat_die", h)
    assert names == ["clamped", "intermediate", "sliding", "final"]
    assert rows == [1, 3, 3, 3] and fallback == ["intermediate", "sliding"]


def test_instants_of_unreached_phases_are_omitted():
    # stopped in the middle of clamp: only `final`
    h = _history(["clamp", "clamp"], [0, 0.5], active=[0, 9], slip=[0, 9])
    assert instants.select_instants("flat_die", h) == (["final"], [1], [])
    # blankholder stopped during lock: closed and final; no drawing
    h = _history(["close", "close", "lock"], [0, 1.0, 1.5])
    assert instants.select_instants("blankholder", h) == (["closed", "final"], [1, 2], [])


def test_instant_rows_of_a_growing_history_equal_those_of_each_whole_history():
    """`InstantRows` rounds only the rows it has not seen; what it keeps is what a fresh call keeps,
    and a history whose earlier rows changed is read again from its start."""
    rng = np.random.default_rng(0)
    n = 60
    phases = ["clamp"] * 10 + ["draw"] * (n - 10)
    time = np.concatenate([np.linspace(0.0, 1.0, 10), 1.0 + np.cumsum(rng.uniform(0.001, 0.03, n - 10))])
    u = np.concatenate([np.zeros(10), 40.0 * (time[10:] - 1.0) / (time[-1] - 1.0)])
    h = _history(phases, time, u=u)
    keep = instants.InstantRows("nine")
    picked = []
    for m in (3, 11, 12, 30, 45, n):
        part = {k: v[:m] for k, v in h.items()}
        picked.append(keep(part))
        assert picked[-1] == instants.instant_rows("nine", part)
    assert len({tuple(r) for r in picked}) == len(picked)   # the steady and final rows moved as it grew
    changed = {k: v.copy() for k, v in h.items()}
    changed["drawing_displacement"][10:] *= 0.8
    assert keep(changed) == instants.instant_rows("nine", changed) != picked[-1]


def test_closest_and_end_of_phase_instants():
    u = [0, 0, 0, 0, 2.0, 3.9, 4.2, 8.0]
    h = _history(["clamp", "clamp", "wind", "wind", "draw", "draw", "draw", "draw"],
                 [0, 1, 1.5, 2, 2.25, 2.5, 2.6, 3], u=u)
    assert instants.select_instants("bead", h) == (["clamped", "folded", "drawing", "final"], [1, 3, 5, 7], [])
    h = _history(["clamp", "clamp", "draw", "draw", "draw"], [0, 1, 1.3, 1.4, 2], u=[0, 0, 20, 28, 70])
    assert instants.select_instants("nine", h) == (["clamped", "steady", "final"], [1, 3, 4], [])
    h = _history(["close", "close", "lock", "draw", "draw"], [0, 1, 2, 2.5, 3], u=[0, 0, 0, 27, 55])
    assert instants.select_instants("blankholder", h)[:2] == (["closed", "locked", "drawing", "final"],
                                                            [1, 2, 3, 4])
    with pytest.raises(ValueError, match="unknown scene"):
        instants.select_instants("cylinder", h)


# ---- steady drawing force -----------------------------------------------------------------------------

def test_steady_drawing_force_is_the_trapezoid_mean():
    u = np.array([0, 0, 10, 20, 25, 30, 35, 40])
    f = 3.0 + 0.1 * u  # linear: the trapezoid rule is exact, mean over [20, 35] = 3 + 0.1 * 27.5
    h = {"phase_name": np.array(["clamp", "clamp"] + ["draw"] * 6), "drawing_displacement": u,
         "drawing_force": f}
    assert instants.steady_drawing_force(h, (20, 35)) == pytest.approx(5.75, rel=1e-14)
    # the window is inclusive with a tolerance of 1e-9 mm
    h2 = dict(h, drawing_displacement=np.where(u == 35, 35 + 5e-10, u).astype(float))
    assert instants.steady_drawing_force(h2, (20, 35)) == pytest.approx(5.75, rel=1e-9)
    h3 = dict(h, drawing_displacement=np.where(u == 35, 35 + 5e-9, u).astype(float))
    assert instants.steady_drawing_force(h3, (20, 35)) == pytest.approx(3 + 0.1 * 25, rel=1e-12)


def test_steady_drawing_force_null_cases():
    h = {"phase_name": np.array(["draw"] * 4), "drawing_displacement": np.array([0.0, 10, 20, 26]),
         "drawing_force": np.ones(4)}
    assert instants.steady_drawing_force(h, (20, 35)) is None           # one row in the window
    h["drawing_displacement"] = np.array([0.0, 20, 25, 27])
    assert instants.steady_drawing_force(h, (20, 35)) is None           # covers 7 < 15/2 mm
    h["drawing_displacement"] = np.array([0.0, 20, 25, 27.5])
    assert instants.steady_drawing_force(h, (20, 35)) == pytest.approx(1.0)  # exactly half: kept
    h["phase_name"] = np.array(["clamp"] * 4)                          # no draw rows
    assert instants.steady_drawing_force(h, (20, 35)) is None


def test_nine_window_is_shortened_when_the_free_end_arrives():
    u = np.arange(0.0, 40.0, 5.0)
    tail = -50.0 + 1.5 * u  # reaches -1 mm at U = 32.7 mm
    h = {"phase": np.array(["draw"] * u.size), "drawing_displacement": u, "tail_x": tail}
    window, note = instants.steady_window("nine", h, (20.0, 35.0))
    assert window == (20.0, 30.0) and "shortened" in note
    h["tail_x"] = -50.0 + 0.5 * u
    assert instants.steady_window("nine", h, (20.0, 35.0)) == ((20.0, 35.0), "")
    assert instants.steady_window("bead", h, (4.0, 8.0)) == ((4.0, 8.0), "")


def test_contact_status_thresholds():
    rn = np.array([0.0, 1e-9, 1.0, 1.0, 1.0, 2.0])
    rt = np.array([0.0, 0.0, 0.1, 0.15, -0.15 * (1 - 5e-7), 0.0])
    mu = np.array([0.15, 0.15, 0.15, 0.15, 0.15, 0.0])
    assert np.asarray(contact_status(rn, rt, mu)).tolist() == [0, 0, 1, 2, 2, 2]


# ---- writer and checker on a real run -------------------------------------------------------------------

@pytest.fixture(scope="module")
def flat():
    from jaxfric import scenes

    scene = scenes.make("flat_die", None, "penalty", dict(OVERRIDES))
    result = jf.run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                    snapshot=scene.snapshot, progress=False, raise_on_failure=False)
    assert result.converged, result.message
    return scene, result


@pytest.fixture(scope="module")
def good_dir(flat, tmp_path_factory):
    scene, result = flat
    path = str(tmp_path_factory.mktemp("run") / "flat")
    summary = output.write_run(scene, result, path, tag="mesh24x2")
    return path, summary


def test_write_run_passes_the_checker(good_dir, flat):
    path, summary = good_dir
    assert check_run_dir(path) == []
    assert summary["converged"] and summary["message"] == "" and summary["tag"] == "mesh24x2"
    with open(os.path.join(path, "history.csv")) as f:
        header = f.readline().strip().split(",")
    assert header[:12] == list(output.REQUIRED_COLUMNS)
    assert {"sum_ft", "mu_sum_fn", "n_candidates", "cutbacks"} <= set(header[12:])
    assert "n_aug" not in header
    scene, result = flat
    assert summary["n_steps"] == len(result.history["time"]) - 1
    assert summary["steady_drawing_force"] is not None
    with np.load(os.path.join(path, "contact.npz"), allow_pickle=False) as data:
        assert data["instant_names"].tolist() == summary["instants"]
        assert data["tool_names"].tolist() == ["die"]
        assert data["final__status"].dtype == np.int8


def test_error_estimate_components(good_dir, flat):
    """The estimate is rebuilt from its definition: penetration / thickness, steady-window force
    scatter / mean, Newton tolerance, in quadrature."""
    path, summary = good_dir
    scene, result = flat
    est = summary["error_estimate"]
    assert est["quantity"] == "steady_drawing_force" and est["value"] == summary["steady_drawing_force"]
    t = scene.config.h  # the modelled (half) thickness of the flat die
    assert est["components"]["contact"] == pytest.approx(summary["max_penetration"] / t, rel=1e-12)
    hist = result.history
    rows = instants.steady_rows(hist["phase_name"], hist["drawing_displacement"], summary["steady_window"])
    scatter = np.std(hist["drawing_force"][rows]) / summary["steady_drawing_force"]
    assert est["components"]["scatter"] == pytest.approx(scatter, rel=1e-9, abs=1e-15)
    total = np.sqrt(sum(v**2 for v in est["components"].values()))
    assert est["relative"] == pytest.approx(total, rel=1e-12) and est["relative"] > 0
    assert est["absolute"] == pytest.approx(total * est["value"], rel=1e-12)


def test_partial_run_writes_a_conforming_directory(flat, tmp_path):
    """A run stopped in the middle of `clamp` still writes all six files; only `final` is stored."""
    scene, result = flat
    keep = 2
    partial = dataclasses.replace(
        result, history={k: v[:keep] for k, v in result.history.items()},
        snapshots={k: v for k, v in result.snapshots.items() if k < keep}, converged=False,
        message="stopped after step 1 at t = 0.5 (phase 'clamp'): test")
    summary = output.write_run(scene, partial, str(tmp_path))
    assert check_run_dir(str(tmp_path)) == []
    assert not summary["converged"] and summary["message"].startswith("stopped")
    assert summary["instants"] == ["final"] and summary["steady_drawing_force"] is None


def test_failed_run_writes_a_conforming_directory(flat, tmp_path):
    """A genuinely failed run (history buffer full in `draw`) writes all six files and passes."""
    scene, _ = flat
    scene = dataclasses.replace(scene, control=jf.StepControl(max_steps=5))
    result = jf.run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                    snapshot=scene.snapshot, progress=False, raise_on_failure=False)
    assert not result.converged
    summary = output.write_run(scene, result, str(tmp_path))
    assert check_run_dir(str(tmp_path)) == []
    assert not summary["converged"] and summary["message"]
    assert summary["instants"][0] == "clamped" and summary["instants"][-1] == "final"
    assert set(PNGS) <= set(os.listdir(tmp_path))


def test_algorithm_extra_columns(flat, tmp_path):
    scene, result = flat
    n = len(result.history["time"])
    cuts, codes = np.zeros(n, int), np.zeros(n, int)
    band = 1 << Result.CONTACT_BAND
    cuts[2:4], codes[2], codes[3] = 2, (1 << Result.MAX_ITERATIONS) | band, band
    history = dict(result.history, augmentations=np.arange(n) % 3, lcp_pivots=np.full(n, 7), cutbacks=cuts,
                   cut_codes=codes)
    params = json.loads(json.dumps(scene.parameters))
    params["contact"]["target_gap"] = 1e-5
    auglag = dataclasses.replace(scene, algorithm="auglag", parameters=params)
    summary = output.write_run(auglag, dataclasses.replace(result, history=history), str(tmp_path),
                               figures=False)
    with open(tmp_path / "history.csv") as f:
        header = f.readline().strip().split(",")
    assert header[-4:] == ["cutbacks", "cut_codes", "n_aug", "lcp_pivots"]
    assert summary["mean_augmentations"] == pytest.approx(np.sum(np.arange(n) % 3) / (n - 1))
    assert summary["n_cutbacks"] == 4 and summary["cutback_causes"] == {"max_iterations": 1, "contact_band": 2}
    problems = [p for p in check_run_dir(str(tmp_path)) if not p.startswith(PNGS)]
    assert problems == []


def test_plot_failure_keeps_the_data_files(flat, tmp_path, monkeypatch):
    from jaxfric.io import figures

    def broken(*args, **kwargs):
        raise RuntimeError("no display")

    monkeypatch.setattr(figures, "mesh_figure", broken)
    scene, result = flat
    with pytest.raises(output.OutputError, match="mesh.png"):
        output.write_run(scene, result, str(tmp_path))
    with open(tmp_path / "summary.json") as f:
        assert "mesh.png not drawn" in json.load(f)["message"]
    problems = check_run_dir(str(tmp_path))
    assert problems == ["mesh.png: missing"]


# ---- the checker catches planted defects -----------------------------------------------------------------

def _planted(good_dir, tmp_path, edit):
    path = str(tmp_path / "run")
    shutil.copytree(good_dir[0], path)
    edit(path)
    return check_run_dir(path)


def _edit_csv(fn):
    def edit(path):
        p = os.path.join(path, "history.csv")
        with open(p) as f:
            lines = f.read().split("\n")
        with open(p, "w") as f:
            f.write("\n".join(fn(lines)))
    return edit


def _edit_summary(fn):
    def edit(path):
        p = os.path.join(path, "summary.json")
        with open(p) as f:
            s = json.load(f)
        fn(s)
        with open(p, "w") as f:
            json.dump(s, f)
    return edit


def _edit_npz(fn):
    def edit(path):
        p = os.path.join(path, "contact.npz")
        with np.load(p, allow_pickle=False) as f:
            data = {k: f[k] for k in f.files}
        fn(data)
        np.savez_compressed(p, **data)
    return edit


def _swap_columns(lines):
    out = []
    for line in lines:
        fields = line.split(",")
        if len(fields) > 3:
            fields[2], fields[3] = fields[3], fields[2]
        out.append(",".join(fields))
    return out


def _nan_in_row(lines):
    fields = lines[3].split(",")
    fields[4] = "nan"
    lines[3] = ",".join(fields)
    return lines


def _flip_status(data):
    status = data["final__status"].copy()
    status[0] = 1 if status[0] != 1 else 2
    data["final__status"] = status


PLANTED = {
    "column order": (_edit_csv(_swap_columns), "first 12 columns"),
    "NaN": (_edit_csv(_nan_in_row), "non-finite"),
    "empty field": (_edit_csv(lambda ls: [ls[0], ls[1].replace(",0,", ",,", 1)] + ls[2:]), "empty field"),
    "step": (_edit_csv(lambda ls: [ls[0], "7" + ls[1][1:]] + ls[2:]), "'step'"),
    "peak force": (_edit_summary(lambda s: s.update(peak_drawing_force=s["peak_drawing_force"] * 1.001)),
                   "peak_drawing_force"),
    "steady force": (_edit_summary(lambda s: s.update(steady_drawing_force=1.0)), "steady_drawing_force"),
    "converged": (_edit_summary(lambda s: s.update(converged=False, message="x")), "converged"),
    "variant": (_edit_summary(lambda s: s.update(variant="const_pressure")), "unknown variant"),
    "missing key": (_edit_summary(lambda s: s.pop("device")), "'device'"),
    "status": (_edit_npz(_flip_status), "status"),
    "status dtype": (_edit_npz(lambda d: d.update(final__status=d["final__status"].astype(np.int64))), "int8"),
    "instants": (_edit_npz(lambda d: d.update(instant_names=d["instant_names"][::-1].copy())), "instant"),
    "clamping": (_edit_npz(lambda d: d.update(final__rn=d["final__rn"] * 1.01)), "clamping force"),
    "small png": (lambda p: shutil.copy(os.path.join(os.path.dirname(jf.__file__), "..", "pyproject.toml"),
                                        os.path.join(p, "mesh.png")), "mesh.png"),
    "missing file": (lambda p: os.remove(os.path.join(p, "contact.png")), "contact.png: missing"),
    "error estimate": (_edit_summary(lambda s: s["error_estimate"].update(relative=-1.0)), "error_estimate"),
}


@pytest.mark.parametrize("defect", list(PLANTED))
def test_checker_catches_planted_defects(good_dir, tmp_path, defect):
    edit, words = PLANTED[defect]
    problems = _planted(good_dir, tmp_path, edit)
    assert any(words in p for p in problems), problems


def test_checker_rejects_nan_in_summary(good_dir, tmp_path):
    def edit(path):
        p = os.path.join(path, "summary.json")
        with open(p) as f:
            text = f.read()
        with open(p, "w") as f:
            f.write(text.replace('"max_penetration": ', '"max_penetration": NaN, "x": ', 1))
    problems = _planted(good_dir, tmp_path, edit)
    assert any("finite" in p for p in problems), problems


def test_checker_png_size_from_ihdr(good_dir, tmp_path):
    import matplotlib.pyplot as plt

    def edit(path):
        fig = plt.figure(figsize=(4, 3), dpi=100)
        fig.savefig(os.path.join(path, "forces.png"))
        plt.close(fig)
    problems = _planted(good_dir, tmp_path, edit)
    assert any("forces.png: 400 x 300 px" in p for p in problems), problems


# ---- command line ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv, words", [
    (["run", "cylinder"], "unknown scene"),
    (["run", "flat_die", "--variant", "const_pressure"], "unknown variant"),
    (["run", "nine", "--algorithm", "newton"], "unknown algorithm"),
    (["run", "flat_die", "--set", "thickness=1"], "thickness"),
    (["run", "flat_die", "--set", "U_draw=abc"], "U_draw"),
    (["run", "flat_die", "--set", "U_draw"], "NAME=VALUE"),
    (["run", "flat_die", "--mesh", "300by3"], "mesh"),
    (["run", "flat_die", "--mesh", "0x3"], "mesh"),
    (["run", "flat_die", "--tag", "bad tag"], "tag"),
    (["run", "flat_die", "--frobnicate"], "unrecognized"),
    (["run"], "scene"),
])
def test_cli_bad_input_is_one_line(capsys, argv, words):
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and words in err and "Traceback" not in err, err


def test_cli_parses_every_override_once_and_passes_typed_values(tmp_path, monkeypatch):
    """--set and --mesh are parsed once, on the command line; the scene gets the typed values (the
    mesh as (nx, ny), checked by parse_mesh), and the run the scene built from them."""
    import sys

    from jaxfric import scenes

    class Started(Exception):
        pass

    parsed, meshes, given = [], [], []
    parse_override, parse_mesh, make = scenes.parse_override, scenes.parse_mesh, scenes.make
    monkeypatch.setattr(scenes, "parse_override", lambda *a: parsed.append(a[1:]) or parse_override(*a))
    monkeypatch.setattr(scenes, "parse_mesh", lambda text: meshes.append(text) or parse_mesh(text))
    monkeypatch.setattr(scenes, "make", lambda *a: given.append(a[3]) or make(*a))

    def run(model, **kwargs):
        raise Started(model.mesh.nx, model.mesh.ny)

    monkeypatch.setattr(sys.modules["jaxfric.loadpath.run"], "run", run)
    with pytest.raises(Started) as info:
        cli.main(["run", "flat_die", *SHORT, "--set", "mu=0.1", "--out", str(tmp_path / "o"), "--quiet"])
    assert info.value.args == (24, 2)
    sets = [SHORT[i + 1] for i in range(0, len(SHORT), 2) if SHORT[i] == "--set"] + ["mu=0.1"]
    assert sorted(parsed) == sorted([("mesh", "24x2")] + [tuple(t.split("=", 1)) for t in sets])
    assert [m for m in meshes if isinstance(m, str)] == ["24x2"]
    assert given == [{"n_clamp": 2, "U_draw": 0.003, "U_fine": 0.001, "dU_fine": 0.0005, "dU": 0.001,
                      "steady_window": (0.002, 0.003), "mu": 0.1, "mesh": (24, 2)}]


def test_cli_scenes_lists_fields(capsys):
    assert cli.main(["scenes"]) == 0
    text = capsys.readouterr().out
    for word in ("flat_die", "bead", "nine", "blankholder", "shape9", "th135_mu017", "F_clamp", "N/mm",
                 "lcp_ssn"):
        assert word in text


def test_cli_run_end_to_end(flat, tmp_path, capsys):
    """Same structure as the `flat` fixture, so the compiled run is reused."""
    out = str(tmp_path / "cli")
    assert cli.main(["run", "flat_die", *SHORT, "--out", out, "--quiet", "--tag", "t1"]) == 0
    text = capsys.readouterr().out
    assert out in text and "steady drawing force" in text and "compile" in text
    assert "wall time" in text and "error estimate of the steady drawing force" in text
    assert check_run_dir(out) == []
    with open(os.path.join(out, "summary.json")) as f:
        summary = json.load(f)
    assert summary["scene"] == "flat_die" and summary["variant"] == "const_force" and summary["tag"] == "t1"
    assert summary["mesh"] == [24, 2]


def test_cli_failed_run_exits_non_zero(flat, tmp_path, capsys, monkeypatch):
    import sys

    run_module = sys.modules["jaxfric.loadpath.run"]  # the package attribute `jaxfric.run` is the function
    scene, result = flat
    partial = dataclasses.replace(
        result, history={k: v[:2] for k, v in result.history.items()},
        snapshots={k: v for k, v in result.snapshots.items() if k < 2}, converged=False,
        message="stopped after step 1: Newton did not converge")
    monkeypatch.setattr(run_module, "run", lambda *a, **k: partial)
    out = str(tmp_path / "cli")
    assert cli.main(["run", "flat_die", *SHORT, "--out", out, "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Newton did not converge" in err
    assert check_run_dir(out) == []


def test_damping_note_counts_the_stabilised_steps_against_the_drawing_work():
    """The summary's note on the step controller's damper: none without a damped step; otherwise how
    many steps, the energy the damper took and its share of the drawing force's work (trapezoids)."""
    values = {"drawing_force": np.array([0.0, 10.0, 10.0]), "drawing_displacement": np.array([0.0, 1.0, 2.0])}
    assert output.damping_note(np.zeros(3), values) == ""
    note = output.damping_note(np.array([0.0, 0.0, 0.3]), values)
    assert note.startswith("1 step stabilised") and "0.3 N mm/mm" in note
    assert "2 % of the drawing force's work (15 N mm/mm)" in note
    flat = {"drawing_force": np.zeros(3), "drawing_displacement": np.zeros(3)}
    assert "%" not in output.damping_note(np.array([0.0, 0.1, 0.2]), flat)


def test_band_note_says_where_the_proximity_band_grew_and_to_what():
    assert output.band_note(()) == ""
    note = output.band_note(((2.03125, 512), (2.5, None)))
    assert "to 512 nodes at t = 2.03125, to every candidate node at t = 2.5" in note and "BAND_FULL" in note


# ---- jaxfric.io.cache: the persistent compilation cache of the command lines ------------------------

def test_compilation_cache_folder_follows_jax_then_jaxfric_then_xdg():
    from jaxfric.io.cache import cache_dir

    assert cache_dir({"JAX_COMPILATION_CACHE_DIR": "/a", "JAXFRIC_CACHE_DIR": "/b"}) == "/a"
    assert cache_dir({"JAXFRIC_CACHE_DIR": "/b", "XDG_CACHE_HOME": "/c"}) == "/b"
    assert cache_dir({"JAXFRIC_CACHE_DIR": "off"}) is None and cache_dir({"JAXFRIC_CACHE_DIR": ""}) is None
    assert cache_dir({"XDG_CACHE_HOME": "/c"}) == os.path.join("/c", "jaxfric", "xla")


def test_compilation_cache_keeps_a_program_for_the_next_process(tmp_path):
    """A process that enables the cache writes its compiled program into the folder, however short its
    compilation (JAX by default keeps only those of a second or more), and a second process finds it
    there (JAX's cache hit, not a second compilation). JAX's own setting of that threshold, in the
    environment, still chooses."""
    import subprocess
    import sys

    folder = tmp_path / "xla"
    probe = ("import logging, jax, jax.numpy as jnp\n"
             "from jaxfric.io.cache import enable_compilation_cache\n"
             "print('folder', enable_compilation_cache())\n"
             "logging.basicConfig(level=logging.DEBUG)\n"
             "jax.jit(lambda x: jnp.sin(x) @ x)(jnp.ones((8, 8))).block_until_ready()\n")
    env = {k: v for k, v in os.environ.items()
           if k not in ("JAX_COMPILATION_CACHE_DIR", "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS")}

    def probe_in(path, **extra):
        return subprocess.run([sys.executable, "-c", probe], env={**env, "JAXFRIC_CACHE_DIR": str(path), **extra},
                              capture_output=True, text=True, timeout=120)

    runs = [probe_in(folder) for _ in range(2)]
    assert all(r.returncode == 0 for r in runs), runs[-1].stderr[-2000:]
    assert f"folder {folder}" in runs[0].stdout
    assert any(folder.iterdir())
    assert "cache hit" in runs[1].stderr.lower() and "cache hit" not in runs[0].stderr.lower()
    chosen = probe_in(tmp_path / "chosen", JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="100")
    assert chosen.returncode == 0 and not any((tmp_path / "chosen").iterdir()), chosen.stderr[-2000:]


def test_fast_compilation_flags_are_added_once_asked_once_and_never_override_the_user(tmp_path):
    from jaxfric.io.xla_flags import FAST_COMPILE_FLAGS, ONE_THREAD_PER_DEVICE, use_fast_compilation

    asked = []

    def accepts(answer):
        def probe(flags):
            asked.append(flags)
            return answer
        return probe

    folder = str(tmp_path / "cache")
    env = {"JAXFRIC_CACHE_DIR": folder, "XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert use_fast_compilation(env, accepts(True))
    # Two host devices: each computes on one thread as well.
    assert env["XLA_FLAGS"].split() == ["--xla_force_host_platform_device_count=2", *FAST_COMPILE_FLAGS,
                                        ONE_THREAD_PER_DEVICE]
    # Another process of the same jaxlib finds the answer in the cache folder and does not ask again.
    again = {"JAXFRIC_CACHE_DIR": folder, "XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert use_fast_compilation(again, accepts(False)) and again["XLA_FLAGS"] == env["XLA_FLAGS"]
    assert len(asked) == 1
    # One device: XLA's own threads. A thread setting of the user's: kept.
    one = {"XLA_FLAGS": "--xla_force_host_platform_device_count=1", "JAXFRIC_CACHE_DIR": "off"}
    assert use_fast_compilation(one, accepts(True))
    assert one["XLA_FLAGS"].split() == ["--xla_force_host_platform_device_count=1", *FAST_COMPILE_FLAGS]
    threads = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2 --xla_cpu_multi_thread_eigen=true",
               "JAXFRIC_CACHE_DIR": "off"}
    assert use_fast_compilation(threads, accepts(True))
    assert threads["XLA_FLAGS"].split()[:2] == ["--xla_force_host_platform_device_count=2",
                                                "--xla_cpu_multi_thread_eigen=true"]
    assert ONE_THREAD_PER_DEVICE not in threads["XLA_FLAGS"]
    # An XLA without the threads' switch still gets the fast compilation's flags.
    unknown = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2", "JAXFRIC_CACHE_DIR": "off"}
    assert use_fast_compilation(unknown, lambda flags: ONE_THREAD_PER_DEVICE not in flags)
    assert unknown["XLA_FLAGS"].split() == ["--xla_force_host_platform_device_count=2", *FAST_COMPILE_FLAGS]
    # Already in effect: nothing added twice; one given another value by the user: kept, the others added,
    # reported not all in effect.
    assert use_fast_compilation(env, accepts(True)) and env["XLA_FLAGS"].count("fusion_emitters") == 1
    own = {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=true", "JAXFRIC_CACHE_DIR": "off"}
    assert not use_fast_compilation(own, accepts(True))
    others = [flag for flag in FAST_COMPILE_FLAGS if not flag.startswith("--xla_cpu_use_fusion_emitters=")]
    assert own["XLA_FLAGS"].split() == ["--xla_cpu_use_fusion_emitters=true", *others]
    # An XLA that refuses them, or the user asking for XLA's defaults: XLA_FLAGS is left as it was. A refusal
    # is not kept (the child may have failed to start): the next process asks again.
    other = str(tmp_path / "other")
    for _ in range(2):
        refused = {"JAXFRIC_CACHE_DIR": other}
        assert not use_fast_compilation(refused, accepts(False)) and "XLA_FLAGS" not in refused
    defaults = {"JAXFRIC_XLA_DEFAULTS": "1", "JAXFRIC_CACHE_DIR": "off"}
    assert not use_fast_compilation(defaults, accepts(True)) and "XLA_FLAGS" not in defaults
    # the first, one device, the user's threads, the user's own value with the others added, the two refusals
    assert len(asked) == 6


def test_this_xla_accepts_the_fast_compilation_flags():
    """The flags the command lines ask for start this jaxlib's XLA (where they did not, the command lines
    would fall back to XLA's defaults, slower to compile)."""
    from jaxfric.io.xla_flags import FAST_COMPILE_FLAGS, ONE_THREAD_PER_DEVICE, xla_accepts

    assert xla_accepts(" ".join(FAST_COMPILE_FLAGS))
    assert xla_accepts(" ".join(["--xla_force_host_platform_device_count=2", *FAST_COMPILE_FLAGS,
                                 ONE_THREAD_PER_DEVICE]))
    assert not xla_accepts("--xla_no_such_flag_in_any_xla=1")
