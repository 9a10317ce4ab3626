"""Malformed input through the command line and the Python API.

Requirement: every malformed input (unknown scene, variant, algorithm or field; wrong types; negative,
zero, NaN and infinite values; meshes of size 0; contradictory options; an unwritable output
directory; a ``--set`` value that does not parse) gives a non-zero exit status or an exception with a
one-line message naming the field, no traceback on the command line, and no partial state written as
if the run had succeeded.

Command-line cases run ``jaxfric.cli.main`` in-process with the simulation replaced by a stub that
raises :class:`SimulationStarted`: bad input must be refused before any simulation starts, and a case
that gets through fails fast instead of running one. Each case also runs in an empty working directory
that must stay empty (no ``runs/...`` written by default).

Related cases elsewhere (not repeated here): ``test_output.test_cli_bad_input_is_one_line``,
``test_scenes.test_parse_helpers`` / ``test_bad_field_values_name_the_field`` /
``test_unknown_identifiers``, ``test_mesh.test_bad_mesh_input_names_the_field``,
``test_material.test_bad_values_raise``, ``test_contact.test_bad_contact_input_names_the_field`` and
``test_tools.test_bad_input_raises_value_error_naming_the_field``.
"""

import importlib
import math

import pytest

import jaxfric as jf
from jaxfric import cli, scenes
from jaxfric.contact.formulations import AugmentedLagrangian, Complementarity, Penalty
from jaxfric.io import output
from jaxfric.numerics.lru import LRU

NAN, INF = math.nan, math.inf
PREFIX = "jaxfric: error: "
TINY = ["--mesh", "4x1"]  # keeps a case that wrongly gets through cheap even without the stub
# The module `jaxfric.loadpath.run` (the package attribute `jaxfric.run` is the function).
RUN_MODULE = importlib.import_module("jaxfric.loadpath.run")


class SimulationStarted(Exception):
    """Raised by the stubbed simulation: the input got past validation."""


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    """An empty working directory, and a simulation that refuses to start."""
    def refuse(*args, **kwargs):
        raise SimulationStarted("the input reached the simulation")

    monkeypatch.setattr(RUN_MODULE, "run", refuse)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    return work


def cli_error(capsys, argv, codes=(2,)):
    """Run the command line; check a non-zero status in ``codes`` and one error line; return it."""
    status = cli.main(argv)
    captured = capsys.readouterr()
    assert status in codes, (status, captured.err)
    assert "Traceback" not in captured.err + captured.out
    assert captured.err.endswith("\n") and captured.err.count("\n") == 1, repr(captured.err)
    line = captured.err.rstrip("\n")
    assert line.startswith(PREFIX) and line[len(PREFIX):].strip(), line
    return line


# ---- command line: bad input is refused before any simulation -------------------------------------------

CLI_CASES = [
    # unknown scene, variant, algorithm, field, subcommand, option
    (["run", "Nine"], "unknown scene 'Nine'"),
    (["run", ""], "unknown scene ''"),
    (["run", "flat_die", "--variant", "mu017"], "unknown variant 'mu017'"),  # a variant of nine
    (["run", "bead", "--variant", ""], "unknown variant ''"),
    (["run", "flat_die", "--variant", "const_force", "--variant", "const"], "--variant: given twice"),
    (["run", "nine", "--algorithm", "Penalty"], "unknown algorithm 'Penalty'"),
    (["run", "nine", "--algorithm", ""], "unknown algorithm ''"),
    (["run", "nine", "--set", "MU=0.1"], "'MU'"),
    (["run", "blankholder", "--set", "mesh_x=3"], "'mesh_x'"),
    (["frob"], "'frob'"),
    (["scenes", "nine"], "nine"),
    (["run", "flat_die", "--quiet=yes"], "--quiet"),
    # --set syntax
    (["run", "nine", "--set", "=0.1"], "NAME=VALUE"),
    (["run", "nine", "--set", "mu:0.1"], "NAME=VALUE"),
    # --set values that do not parse
    (["run", "nine", "--set", "mu=0x10"], "'mu'"),
    (["run", "nine", "--set", "mu=none"], "'mu'"),  # None only for optional fields
    (["run", "nine", "--set", "U_draw=1\n2"], "'U_draw'"),  # the message stays on one line
    (["run", "nine", "--set", "nx=2.5"], "'nx'"),
    (["run", "nine", "--set", "nx=nan"], "'nx'"),
    (["run", "nine", "--set", "ny=abc"], "'ny'"),
    (["run", "nine", "--set", "steady_window=20;35"], "'steady_window'"),
    # negative, zero, NaN, infinite (and overflowing: 1e400 parses as inf) values
    (["run", "nine", "--set", "mu=-0.17"], "'mu'"),
    (["run", "flat_die", "--set", "mu=nan"], "'mu'"),
    (["run", "bead", "--set", "mu_roller=inf"], "'mu_roller'"),
    (["run", "nine", "--set", "eps_n=0"], "'eps_n'"),
    (["run", "flat_die", "--set", "eps_n=1e400"], "'eps_n'"),
    (["run", "bead", "--set", "eps_n=-inf"], "'eps_n'"),
    (["run", "nine", "--set", "smoothing=-1"], "'smoothing'"),
    (["run", "flat_die", "--algorithm", "lcp_ssn", "--set", "smoothing=0.1"], "'smoothing'"),  # contradictory
    (["run", "nine", "--set", "eps_t=nan"], "'eps_t'"),
    (["run", "flat_die", "--set", "eps_t=-1.5e8"], "'eps_t'"),
    (["run", "nine", "--algorithm", "auglag", "--set", "target_gap=0"], "'target_gap'"),
    (["run", "flat_die", "--set", "target_gap=-1e-5"], "'target_gap'"),
    (["run", "nine", "--algorithm", "auglag", "--set", "max_augmentations=0"], "'max_augmentations'"),
    (["run", "bead", "--set", "max_augmentations=2.5"], "'max_augmentations'"),
    (["run", "nine", "--set", "max_steps=0"], "'max_steps'"),
    (["run", "bead", "--set", "E=-200000"], "'E'"),
    (["run", "flat_die", "--set", "E=inf"], "'E'"),
    (["run", "nine", "--set", "t=0"], "'t'"),
    (["run", "blankholder", "--set", "t=-1"], "'t'"),
    (["run", "bead", "--set", "nu=0.5"], "'nu'"),
    (["run", "nine", "--set", "nu=-1"], "'nu'"),
    (["run", "flat_die", "--set", "nu=nan"], "'nu'"),
    (["run", "bead", "--set", "F_clamp=-600"], "'F_clamp'"),
    (["run", "blankholder", "--set", "F_clamp=nan"], "'F_clamp'"),
    (["run", "flat_die", "--set", "F_clamp=1e400"], "'F_clamp'"),
    (["run", "bead", "--set", "sigma_y=0"], "'sigma_y'"),
    (["run", "blankholder", "--set", "n=-0.28"], "'n'"),
    (["run", "flat_die", "--set", "nx=0"], "'nx'"),
    (["run", "bead", "--set", "n_clamp=-3"], "'n_clamp'"),
    (["run", "flat_die", "--set", "dU=0"], "'dU'"),
    (["run", "flat_die", "--set", "steady_window=0.03,0.02"], "'steady_window'"),
    (["run", "blankholder", "--set", "lock_control=torque"], "'lock_control'"),
    # meshes of size 0 and malformed meshes
    (["run", "flat_die", "--mesh", "3x0"], "'mesh'"),
    (["run", "flat_die", "--mesh", "ax3"], "'mesh'"),
    (["run", "flat_die", "--mesh", "300"], "'mesh'"),
    (["run", "flat_die", "--mesh=-1x3"], "'mesh'"),
    (["run", "flat_die", "--mesh", "-1x3"], "--mesh"),  # argparse takes "-1x3" for an option
    (["run", "flat_die", "--mesh", "4.5x1"], "'mesh'"),
    (["run", "flat_die", "--mesh", "4x1x1"], "'mesh'"),
    (["run", "flat_die", "--mesh", ""], "'mesh'"),
    (["run", "flat_die", "--mesh"], "--mesh"),
    (["run", "nine", "--set", "mesh=0x3"], "'mesh'"),
    (["run", "nine", "--set", "mesh=3"], "'mesh'"),
    # contradictory options
    (["run", "flat_die", "--mesh", "4x1", "--set", "mesh=8x1"], "--mesh"),
    (["run", "flat_die", "--set", "mesh=4x1", "--set", "mesh=8x1"], "'mesh' twice"),
    (["run", "nine", "--set", "mu=0.1", "--set", "mu=0.2"], "'mu' twice"),
    # bad tags
    (["run", "flat_die", "--tag", ""], "--tag"),
    (["run", "flat_die", "--tag", "a/b"], "--tag"),
    (["run", "flat_die", "--tag", "-x"], "--tag"),
    (["run", "flat_die", "--tag", "ok\nno"], "--tag"),
    # ---- library gaps ----
    pytest.param(["run", "flat_die", "--set", "nx=1e400"], "'nx'", id="nx=1e400"),
    pytest.param(["run", "bead", "--set", "ny=-inf"], "'ny'", id="ny=-inf"),
    pytest.param(["run", "nine", *TINY, "--set", "entry_guide=maybe"], "'entry_guide'", id="entry_guide=maybe"),
    pytest.param(["run", "nine", *TINY, "--set", "entry_guide_kind=tube"], "'entry_guide_kind'",
                 id="entry_guide_kind=tube"),
    pytest.param(["run", "nine", *TINY, "--set", "guide_clearance=0"], "'guide_clearance'", id="guide_clearance=0"),
    pytest.param(["run", "flat_die", "--mesh", "99999999999999999999x1"], "'mesh'", id="mesh=99999999999999999999x1"),
    pytest.param(["run", "flat_die", "--mesh", "4x1", "--set", "nx=8"], "nx", id="--mesh+--set-nx"),
    pytest.param(["run", "flat_die", "--set", "mesh=4x1", "--set", "nx=8"], "nx", id="--set-mesh+--set-nx"),
    pytest.param(["run", "flat_die", *TINY, "--set", "dU_fine=1e-300"], "'dU_fine'", id="dU_fine=1e-300"),
    pytest.param(["run", "flat_die", *TINY, "--out", ""], "--out", id="out=''"),
    pytest.param(["run", "flat_die", *TINY, "--out", "a\0b"], "--out", id="out-nul"),
    # a mesh whose directions pass but whose element count does not
    pytest.param(["run", "flat_die", "--mesh", "100000x100000"], "'mesh'", id="mesh-product"),
    pytest.param(["run", "flat_die", "--set", "nx=1000000", "--set", "ny=1000000"], "'nx'", id="nx*ny"),
    # lengths that overflow the derived geometry or no longer close a tool chain
    pytest.param(["run", "blankholder", *TINY, "--set", "r=1e300"], "'r'", id="blankholder-r=1e300"),
    pytest.param(["run", "blankholder", *TINY, "--set", "Rp=1e300"], "'Rp'", id="blankholder-Rp=1e300"),
    pytest.param(["run", "blankholder", *TINY, "--set", "r_e=1e300"], "'r_e'", id="blankholder-r_e=1e300"),
    pytest.param(["run", "bead", *TINY, "--set", "r_e=1e300"], "'r_e'", id="bead-r_e=1e300"),
    pytest.param(["run", "nine", *TINY, "--set", "R2=1e300"], "'R2'", id="nine-R2=1e300"),
    pytest.param(["run", "flat_die", *TINY, "--set", "L=1e308"], "'L'", id="flat_die-L=1e308"),
    # a steady window outside the drawing stroke, a stroke of zero
    pytest.param(["run", "flat_die", *TINY, "--set", "steady_window=1,2"], "'steady_window'", id="flat_die-window"),
    pytest.param(["run", "nine", *TINY, "--set", "steady_window=20,80"], "'steady_window'", id="nine-window"),
    pytest.param(["run", "bead", *TINY, "--set", "steady_window=-1,4"], "'steady_window'", id="bead-window"),
    pytest.param(["run", "blankholder", *TINY, "--set", "U_pull=30", "--set", "steady_window=35,55"],
                 "'steady_window'", id="blankholder-window"),
    pytest.param(["run", "flat_die", *TINY, "--set", "U_draw=0"], "'U_draw'", id="U_draw=0"),
    pytest.param(["run", "bead", *TINY, "--set", "s_draw=0"], "'s_draw'", id="s_draw=0"),
    pytest.param(["run", "blankholder", *TINY, "--set", "U_pull=0"], "'U_pull'", id="U_pull=0"),
    # options given twice
    pytest.param(["run", "flat_die", *TINY, "--algorithm", "penalty", "--algorithm", "auglag"],
                 "--algorithm: given twice", id="algorithm-twice"),
    pytest.param(["run", "flat_die", "--mesh", "4x1", "--mesh", "8x1"], "--mesh: given twice", id="mesh-twice"),
    # the report validates before it makes its directory
    pytest.param(["report", "accuracy-cost", "--test", "nope"], "--test 'nope'", id="report-test=nope"),
    # bead cards: bad penetrations, fields the card sets itself, bad config, unknown derivatives
    pytest.param(["bead-card", "--penetrations", "0.5,1.5"], "'penetrations'", id="card-penetration>1"),
    pytest.param(["bead-card", "--penetrations", "half"], "--penetrations", id="card-penetration-text"),
    pytest.param(["bead-card", "--set", "closure=2"], "'closure'", id="card-closure"),
    pytest.param(["bead-card", "--set", "mu=-0.1"], "'mu'", id="card-mu<0"),
    pytest.param(["bead-card", "--variant", "shape10"], "'shape10'", id="card-variant"),
    pytest.param(["bead-card", "--derivatives", "Q"], "'Q'", id="card-derivative"),
    # kinematic hardening: one rate per modulus, a radius that stays positive
    pytest.param(["run", "nine", "--set", "C_kin=2000,100", "--set", "gamma_kin=20"], "'gamma_kin'",
                 id="kin-counts"),
    pytest.param(["run", "nine", "--set", "C_kin=20000", "--set", "gamma_kin=20"], "'C_kin'", id="kin-radius"),
    pytest.param(["run", "nine", "--set", "Q_voce=100"], "'b_voce'", id="voce-counts"),
]


@pytest.mark.parametrize("argv, words", CLI_CASES)
def test_cli_bad_input_is_refused_in_one_line(workdir, capsys, argv, words):
    line = cli_error(capsys, argv)
    assert words in line, line
    assert list(workdir.iterdir()) == []  # nothing written (no default run directory)


def test_repeated_option_is_refused_not_replaced(workdir, capsys):
    line = cli_error(capsys, ["run", "flat_die", "--variant", "const_force", "--variant", "const_position"])
    assert "--variant: given twice" in line and "'const_position'" in line, line


def test_default_steady_window_beyond_a_short_stroke_is_kept():
    """Only a window the user gives is checked against the stroke: a shortened stroke with the default
    window is a run without a steady force (reported as such), not bad input."""
    scene = scenes.make("flat_die", overrides={**FAST, "U_draw": 0.01})
    assert scene.steady_window == (0.02, 0.03)


def test_module_runs_as_a_script():
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "jaxfric.cli", "report", "--help"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert "10 %, 1 % and 0.1 %" in " ".join(done.stdout.split())


def test_cli_bad_input_creates_no_run_directory(workdir, tmp_path, capsys):
    out = tmp_path / "out" / "run1"
    line = cli_error(capsys, ["run", "flat_die", "--set", "mu=-0.15", "--out", str(out)])
    assert "'mu'" in line
    assert not (tmp_path / "out").exists()


# ---- command line: an unwritable output directory -------------------------------------------------------

@pytest.fixture
def blocker(tmp_path):
    """A regular file, so that no directory can be created at or under it (also as root)."""
    path = tmp_path / "file"
    path.write_text("not a directory\n")
    return path


UNWRITABLE = [pytest.param(("sub",), id="under-a-file"), pytest.param((), id="a-file")]


@pytest.mark.parametrize("parts", UNWRITABLE)
def test_cli_unwritable_out_is_refused_before_the_run(workdir, blocker, capsys, parts):
    out = blocker.joinpath(*parts)
    line = cli_error(capsys, ["run", "flat_die", *TINY, "--quiet", "--out", str(out)])
    assert "--out" in line or str(out) in line, line
    assert blocker.read_text() == "not a directory\n"


@pytest.mark.parametrize("parts", UNWRITABLE)
def test_cli_unwritable_out_after_a_run_is_one_line(workdir, blocker, capsys, monkeypatch, parts):
    """Whatever the run gave, a directory that cannot be made is one error line, exit 1 or 2."""
    monkeypatch.setattr(RUN_MODULE, "run", lambda *a, **k: object())  # never read: makedirs fails first
    out = blocker.joinpath(*parts)
    line = cli_error(capsys, ["run", "flat_die", *TINY, "--quiet", "--out", str(out)], codes=(1, 2))
    assert str(out) in line or "--out" in line, line
    assert blocker.read_text() == "not a directory\n"
    assert list(workdir.iterdir()) == []


def test_write_run_bad_tag_writes_nothing(tmp_path):
    out = tmp_path / "run"
    scene = scenes.make("flat_die", overrides={"mesh": "4x1"})
    with pytest.raises(ValueError, match="'tag'") as info:
        output.write_run(scene, None, str(out), tag="two words")
    assert "\n" not in str(info.value)
    assert not out.exists()


# ---- Python API ------------------------------------------------------------------------------------------

MESH = dict(x_left=0.0, x_right=1.0, y_bottom=0.0, thickness=1.0, nx=2, ny=2)
BEAD = dict(E=200000.0, nu=0.3, sigma_y=169.0, A=127.42425, n=0.225)
FAST = {"mesh": "4x1"}


def _mesh(**kw):
    return lambda: jf.strip_mesh(**{**MESH, **kw})


def _material(**kw):
    return lambda: jf.J2Material(**{**BEAD, **kw})


def _make(name, **overrides):
    return lambda: scenes.make(name, overrides=overrides)


API_CASES = [
    # strip_mesh: meshes of size 0, wrong types, non-finite sizes
    pytest.param(_mesh(nx=-3), "'nx'", id="mesh-nx=-3"),
    pytest.param(_mesh(ny=True), "'ny'", id="mesh-ny=True"),
    pytest.param(_mesh(nx="4"), "'nx'", id="mesh-nx='4'"),
    pytest.param(_mesh(thickness="abc"), "'thickness'", id="mesh-thickness='abc'"),
    pytest.param(_mesh(thickness=INF), "'thickness'", id="mesh-thickness=inf"),
    pytest.param(_mesh(x_right=0.0), "length", id="mesh-length=0"),
    pytest.param(_mesh(grading_x=0.0), "'grading_x'", id="mesh-grading_x=0"),
    pytest.param(_mesh(grading_y=-1.0), "'grading_y'", id="mesh-grading_y=-1"),
    # J2Material (values beyond test_material.BAD_VALUES)
    pytest.param(lambda: jf.J2Material.elastic(0.0, 0.3), "J2Material: E = ", id="elastic-E=0"),
    pytest.param(lambda: jf.J2Material.elastic(1.0, NAN), "J2Material: nu = ", id="elastic-nu=nan"),
    pytest.param(_material(nu=[0.3, 0.6]), "J2Material: nu = ", id="mat-nu=[0.3,0.6]"),
    pytest.param(_material(E=-200000.0), "J2Material: E = ", id="mat-E<0"),
    pytest.param(_material(nu=0.5), "J2Material: nu = ", id="mat-nu=0.5"),
    pytest.param(_material(sigma_y=-169.0), "J2Material: sigma_y = ", id="mat-sigma_y<0"),
    pytest.param(_material(A=0.0, n=-0.5), "J2Material: n = ", id="mat-softening-n"),
    pytest.param(_material(A=-0.5), "J2Material: A = ", id="mat-softening-A"),
    # contact laws
    pytest.param(lambda: Penalty(-1e5, 1e4), "'eps_n'", id="penalty-eps_n<0"),
    pytest.param(lambda: Penalty(NAN, 1e4), "'eps_n'", id="penalty-eps_n=nan"),
    pytest.param(lambda: Penalty(1e5, INF), "'eps_t'", id="penalty-eps_t=inf"),
    pytest.param(lambda: Penalty(1e5, -1.0), "'eps_t'", id="penalty-eps_t<0"),
    pytest.param(lambda: Penalty(1e5, 1e4, smoothing=-1.0), "'smoothing'", id="penalty-smoothing<0"),
    pytest.param(lambda: Penalty("stiff", 1e4), "'eps_n'", id="penalty-eps_n='stiff'"),
    pytest.param(lambda: Penalty([1e5, 2e5], 1e4), "'eps_n'", id="penalty-eps_n=array"),
    pytest.param(lambda: AugmentedLagrangian(1e5, 1e4, target_gap=-1e-5), "'target_gap'",
                 id="al-target_gap<0"),
    pytest.param(lambda: AugmentedLagrangian(1e5, 1e4, target_gap=NAN), "'target_gap'",
                 id="al-target_gap=nan"),
    pytest.param(lambda: AugmentedLagrangian(1e5, 1e4, max_augmentations=0), "'max_augmentations'",
                 id="al-max_augmentations=0"),
    pytest.param(lambda: Complementarity(solver="newton"), "'solver'", id="lcp-solver"),
    pytest.param(lambda: Complementarity(band=0), "'band'", id="lcp-band=0"),
    pytest.param(lambda: Complementarity(ssn_max_iter=0), "'ssn_max_iter'", id="lcp-ssn_max_iter=0"),
    # Newton options
    pytest.param(lambda: jf.NewtonOptions(max_iterations=0), "'max_iterations'",
                 id="newton-max_iterations=0"),
    pytest.param(lambda: jf.NewtonOptions(max_iterations=-1), "'max_iterations'",
                 id="newton-max_iterations<0"),
    pytest.param(lambda: jf.NewtonOptions(rtol=-1e-8), "'rtol'", id="newton-rtol<0"),
    pytest.param(lambda: jf.NewtonOptions(du_rtol=NAN), "'du_rtol'", id="newton-du_rtol=nan"),
    # scenes.make: unknown names, wrong types, bad values
    pytest.param(_make("flat_die", friction=0.1), "'friction'", id="make-unknown-field"),
    pytest.param(_make("flat_die", nx=2.5), "'nx'", id="make-nx=2.5"),
    pytest.param(_make("flat_die", nx="a"), "'nx'", id="make-nx='a'"),
    pytest.param(_make("flat_die", nx=True), "'nx'", id="make-nx=True"),
    pytest.param(_make("flat_die", mu="abc"), "'mu'", id="make-mu='abc'"),
    pytest.param(_make("flat_die", mu=[0.1]), "'mu'", id="make-mu=[0.1]"),
    pytest.param(_make("flat_die", mu=None), "'mu'", id="make-mu=None"),
    pytest.param(_make("flat_die", mu=1j), "'mu'", id="make-mu=1j"),
    pytest.param(_make("bead", E=NAN), "'E'", id="make-E=nan"),
    pytest.param(_make("nine", eps_n=-INF), "'eps_n'", id="make-eps_n=-inf"),
    pytest.param(_make("flat_die", mesh=(0, 3)), "'mesh'", id="make-mesh=(0,3)"),
    pytest.param(_make("flat_die", mesh=(2.5, 3)), "'mesh'", id="make-mesh=(2.5,3)"),
    pytest.param(_make("flat_die", mesh=None), "'mesh'", id="make-mesh=None"),
    pytest.param(_make("flat_die", steady_window=(1.0,)), "'steady_window'", id="make-steady_window=(1,)"),
    pytest.param(_make("flat_die", draw_control=3), "'draw_control'", id="make-draw_control=3"),
    pytest.param(_make("nine", x_left=50.0, x_right=-50.0, **FAST), "'x_right'", id="make-x_right<x_left"),
    pytest.param(_make("bead", x_jaw=INF, **FAST), "'x_jaw'", id="make-x_jaw=inf"),
    pytest.param(lambda: scenes.make("flat_die", 3), "variant 3", id="make-variant=3"),
    pytest.param(lambda: scenes.make("flat_die", algorithm=None), "algorithm None", id="make-algorithm=None"),
    pytest.param(lambda: scenes.make(None), "scene None", id="make-scene=None"),
    pytest.param(lambda: scenes.variants("drawbead"), "'drawbead'", id="variants-unknown"),
    pytest.param(lambda: scenes.parse_override("bead", "eps_n", ""), "'eps_n'", id="parse_override-empty"),
    # ---- library gaps ----
    pytest.param(_mesh(y_bottom=NAN), "'y_bottom'", id="mesh-y_bottom=nan"),
    pytest.param(_material(E="steel"), "J2Material: E = ", id="mat-E='steel'"),
    pytest.param(_material(E=None), "J2Material: E = ", id="mat-E=None"),
    pytest.param(lambda: AugmentedLagrangian(1e5, 1e4, max_augmentations=2.5), "'max_augmentations'",
                 id="al-max_augmentations=2.5"),
    pytest.param(lambda: AugmentedLagrangian(1e5, 1e4, max_augmentations="x"), "'max_augmentations'",
                 id="al-max_augmentations='x'"),
    pytest.param(lambda: AugmentedLagrangian(1e5, 1e4, max_augmentations=INF), "'max_augmentations'",
                 id="al-max_augmentations=inf"),
    pytest.param(lambda: Complementarity(band=2.5), "'band'", id="lcp-band=2.5"),
    pytest.param(lambda: Complementarity(band="a"), "'band'", id="lcp-band='a'"),
    pytest.param(lambda: Complementarity(ssn_max_iter=NAN), "'ssn_max_iter'", id="lcp-ssn_max_iter=nan"),
    pytest.param(lambda: jf.NewtonOptions(max_iterations=NAN), "'max_iterations'",
                 id="newton-max_iterations=nan"),
    pytest.param(lambda: jf.NewtonOptions(max_iterations=2.5), "'max_iterations'",
                 id="newton-max_iterations=2.5"),
    pytest.param(lambda: jf.NewtonOptions(max_iterations="5"), "'max_iterations'",
                 id="newton-max_iterations='5'"),
    pytest.param(lambda: jf.NewtonOptions(atol=INF), "'atol'", id="newton-atol=inf"),
    pytest.param(lambda: jf.NewtonOptions(rtol="tight"), "'rtol'", id="newton-rtol='tight'"),
    pytest.param(lambda: jf.StepControl(max_steps=0), "'max_steps'", id="stepcontrol-max_steps=0"),
    pytest.param(lambda: jf.StepControl(max_cuts=-1, growth=NAN), "'max_cuts'", id="stepcontrol-max_cuts<0"),
    pytest.param(_make("nine", entry_guide="maybe", **FAST), "'entry_guide'", id="make-entry_guide='maybe'"),
    pytest.param(_make("nine", entry_guide=3, **FAST), "'entry_guide'", id="make-entry_guide=3"),
    pytest.param(_make("flat_die", mesh="4x1", nx=8), "mesh", id="make-mesh+nx"),
    pytest.param(_make("nine", plastic_integration="trapezoid", **FAST), "'plastic_integration'",
                 id="make-plastic_integration='trapezoid'"),
    pytest.param(_make("nine", plastic_integration="midpoint", C_kin=(1000.0,), gamma_kin=(10.0,), **FAST),
                 "'plastic_integration'", id="make-plastic_integration=midpoint+C_kin"),
    pytest.param(lambda: scenes.make("flat_die", overrides=[("mu", 0.1)]), "overrides",
                 id="make-overrides=list"),
    pytest.param(lambda: scenes.parse_override("nine", "nx", "inf"), "'nx'", id="parse_override-nx=inf"),
    pytest.param(lambda: scenes.parse_mesh((INF, 3)), "'mesh'", id="parse_mesh-(inf,3)"),
    pytest.param(lambda: scenes.parse_mesh(("a", 3)), "'mesh'", id="parse_mesh-('a',3)"),
    pytest.param(lambda: scenes.parse_mesh("100000x100000"), "'mesh'", id="parse_mesh-product"),
    pytest.param(_mesh(nx=10**6, ny=10**6), "'nx'", id="mesh-nx*ny"),
    pytest.param(_mesh(x_left="0"), "'x_left'", id="mesh-x_left='0'"),
    pytest.param(_mesh(x_left=None), "'x_left'", id="mesh-x_left=None"),
    pytest.param(_mesh(grading_x=1e300), "'grading_x'", id="mesh-grading_x=1e300"),
    pytest.param(_mesh(grading_y=1e-300), "'grading_y'", id="mesh-grading_y=1e-300"),
    pytest.param(_material(E=1 + 0j), "J2Material: E = ", id="mat-E=1+0j"),
    pytest.param(lambda: jf.Phase("x", None, n_steps=2), "'bcs'", id="phase-bcs=None"),
    pytest.param(lambda: jf.Phase("x", "abc", n_steps=2), "'bcs'", id="phase-bcs='abc'"),
    pytest.param(lambda: jf.DirichletBC([0.5]), "'nodes'", id="bc-nodes=[0.5]"),
    pytest.param(lambda: jf.Ramp((0, 0), (NAN, 0)), "'end'", id="ramp-end=nan"),
    pytest.param(lambda: jf.Ramp(("a", 0), (1, 0)), "'start'", id="ramp-start=str"),
    pytest.param(lambda: scenes.make(["nine"]), "scene ['nine']", id="make-scene=list"),
    pytest.param(lambda: scenes.make("nine", ["mu017"]), "variant ['mu017']", id="make-variant=list"),
    pytest.param(lambda: scenes.make("nine", {}), "variant {}", id="make-variant=dict"),
    pytest.param(lambda: scenes.make("flat_die", algorithm=["penalty"]), "algorithm ['penalty']",
                 id="make-algorithm=list"),
    pytest.param(lambda: jf.run(None), "'model'", id="run-model=None"),
    pytest.param(lambda: jf.run(_tiny_model(), newton="x"), "'newton'", id="run-newton='x'"),
    pytest.param(lambda: jf.run(_tiny_model(), control=3), "'control'", id="run-control=3"),
    pytest.param(lambda: jf.StripModel(jf.strip_mesh(**MESH), "steel", (jf.Phase("p", [], n_steps=1),)),
                 "'material'", id="model-material=str"),
    pytest.param(lambda: jf.StripModel(None, jf.J2Material(**BEAD), (jf.Phase("p", [], n_steps=1),)),
                 "'mesh'", id="model-mesh=None"),
]


def _tiny_model():
    mesh = jf.strip_mesh(**MESH)
    return jf.StripModel(mesh, jf.J2Material(**BEAD), (jf.Phase("load", [jf.DirichletBC(mesh.left)], n_steps=2),))


@pytest.mark.parametrize("build, field", API_CASES)
def test_api_bad_input_raises_one_line_naming_the_field(build, field):
    with pytest.raises((ValueError, TypeError)) as info:
        build()
    message = str(info.value)
    assert field in message and "\n" not in message, message


def test_string_false_does_not_silently_mean_true():
    try:
        scene = scenes.make("nine", overrides={**FAST, "entry_guide": "false"})
    except ValueError as err:
        assert "'entry_guide'" in str(err) and "\n" not in str(err)
    else:
        assert scene.config.entry_guide is False, repr(scene.config.entry_guide)


# ---- a mesh within the limits but too large for this machine's memory --------------------------------

class _Accounted:
    """A stand-in for a compiled run: XLA's memory account only (40 GiB of temporaries)."""

    def memory_analysis(self):
        import types

        return types.SimpleNamespace(temp_size_in_bytes=40 * 2**30, argument_size_in_bytes=0,
                                     output_size_in_bytes=2**20)


def test_cli_run_that_needs_more_memory_than_available_is_refused_in_one_line(tmp_path, capsys, monkeypatch):
    """The command line gives one line naming the mesh, exit 2, and removes the directories it made."""
    monkeypatch.setattr(RUN_MODULE, "_compiled", lambda *a, **k: (None, _Accounted()))   # nothing compiles or runs
    monkeypatch.setattr(RUN_MODULE, "available_memory", lambda: 8 * 2**30)
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "out" / "run1"
    line = cli_error(capsys, ["run", "flat_die", *TINY, "--quiet", "--out", str(out)])
    assert "field 'mesh'" in line and "4x1" in line and "40 GiB" in line and "8 GiB available" in line, line
    assert list(tmp_path.iterdir()) == []


def test_a_run_that_needs_more_memory_than_available_is_refused_before_it_starts(monkeypatch):
    """XLA's account of a real compiled run against the available memory: refused (MemoryBudgetError, one
    line naming the mesh) when it exceeds it, accepted up to it."""
    from models import clamped_pull

    model = clamped_pull(nx=2, ny=1, unload=False, n_steps=1)
    monkeypatch.setattr(RUN_MODULE, "available_memory", lambda: 1)   # one byte: any run is too large
    with pytest.raises(jf.MemoryBudgetError, match="field 'mesh'") as info:
        jf.run(model, progress=False)
    assert "\n" not in str(info.value) and "2x1" in str(info.value)
    _, compiled = RUN_MODULE._compiled(model, jf.NewtonOptions(), jf.StepControl(), jf.default_observe, None)
    need = RUN_MODULE.check_memory(compiled, model, available=2**50)   # plenty: the need, no error
    assert need is not None and 0 < need < 2**30
    with pytest.raises(jf.MemoryBudgetError):
        RUN_MODULE.check_memory(compiled, model, available=need - 1)
    RUN_MODULE.check_memory(compiled, model, available=need)


def test_a_resume_that_is_no_checkpoint_is_refused_before_anything_compiles(monkeypatch):
    from models import clamped_pull

    def refuse(*args, **kwargs):
        raise AssertionError("compiled before the input was checked")

    monkeypatch.setattr(RUN_MODULE, "_compiled", refuse)
    with pytest.raises(ValueError, match="field 'resume' must be a Checkpoint") as info:
        jf.run(clamped_pull(), progress=False, resume={"t": 1.0})
    assert "\n" not in str(info.value)


def test_compiled_programs_are_bounded_least_recently_used_first(monkeypatch):
    """The public entry point keeps a few compiled programs, not one per structure ever run: a process
    running many scene variants must not run out of memory. A stand-in compiler (one compilation per
    call; a structure has two programs, the start and the chunk) and models of several shapes (the key
    is the structure)."""
    import numpy as np

    compiled = []

    class _Program:
        def __call__(self, *args):
            return None, None

    class _Jitted:
        def __init__(self, fn):
            pass

        def lower(self, *args):
            return self

        class lowered:   # noqa: N801  (equinox's Lowered: the start's output shapes, path and history row)
            out_info = (None, None)

        @staticmethod
        def postprocess(out):
            return out

        def compile(self):
            compiled.append(_Program())
            return compiled[-1]

    monkeypatch.setattr(RUN_MODULE, "_COMPILED", LRU(2))
    monkeypatch.setattr(RUN_MODULE.eqx, "filter_jit", _Jitted)
    options = (jf.NewtonOptions(), jf.StepControl(), jf.default_observe, None)
    first, second = (RUN_MODULE._compiled(np.zeros(n), *options) for n in (1, 2))
    assert RUN_MODULE._compiled(np.zeros(1), *options) is first  # a hit: compiled once
    RUN_MODULE._compiled(np.zeros(3), *options)  # drops the least recently used: shape (2,)
    assert len(RUN_MODULE._COMPILED) == 2 and len(compiled) == 2 * 3
    assert RUN_MODULE._compiled(np.zeros(1), *options) is first
    assert RUN_MODULE._compiled(np.zeros(2), *options) is not second and len(compiled) == 2 * 4
