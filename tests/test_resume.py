"""Runs in chunks: a run stopped between two chunks and resumed (in this process, from its checkpoint on
disk, or by the command line after SIGINT and SIGTERM) is the run that never stopped, bit for bit."""

import json
import os
import signal
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

import jaxfric as jf
from jaxfric import cli, scenes
from jaxfric.io import batch, checkpoint, output
from jaxfric.io.contract import check_run_dir
from jaxfric.io.instants import InstantRows
from jaxfric.loadpath import run as run_module
from jaxfric.numerics.lru import LRU

# A flat die of a few seconds' solve (24 x 2 elements, 120 draw steps): long enough to be stopped in the
# middle, from a command line or a stop request.
OVERRIDES = {"mesh": "24x2", "n_clamp": "4", "U_draw": "0.012", "U_fine": "0.001", "dU_fine": "0.0005",
             "dU": "0.00003", "steady_window": "0.008,0.012"}


def _args(**changes) -> list:
    """The command line's scene arguments of OVERRIDES with ``changes``."""
    values = {**OVERRIDES, **changes}
    return ["flat_die", "--mesh", values.pop("mesh")] + [a for k, v in values.items() for a in ("--set", f"{k}={v}")]


ARGS = _args()


def _scene():
    return scenes.make("flat_die", None, "lcp_ssn", dict(OVERRIDES))


def _run(scene, **kwargs):
    return jf.run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                  snapshot=scene.snapshot, progress=False, raise_on_failure=False, **kwargs)


def _same_rows(a: dict, b: dict) -> None:
    """Every history column but the wall time equal bit for bit."""
    assert set(a) == set(b)
    for key in a:
        if key != "wall_s":
            assert np.array_equal(np.asarray(a[key]), np.asarray(b[key])), key


def _same_state(a, b) -> None:
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        assert np.array_equal(np.asarray(x), np.asarray(y))


class _StopAfter:
    """A stop request after ``n`` chunks."""

    def __init__(self, n):
        self.n, self.asked = n, 0

    def __call__(self):
        self.asked += 1
        return self.asked > self.n


@pytest.fixture(scope="module")
def whole():
    scene = _scene()
    result = _run(scene)
    assert result.converged, result.message
    return scene, result


def test_chunked_run_is_the_single_loop(whole):
    """The chunks take the steps of `simulate`, which runs the whole load path in one loop.

    The two are different XLA programs, equal to round-off, not bit for bit: compiled at XLA's backend
    optimisation level 0 (as the fast suite is, ``tests/conftest.py``), round-off tips the convergence
    test of 8 of these 374 steps by one or two Newton iterations. So the steps' times are compared
    exactly, and the observed values to 1e-9 of their largest (they differ by 2e-12 there)."""
    scene, result = whole
    sim = jax.jit(lambda m: jf.simulate(m, newton=scene.newton, control=scene.control,
                                        observe=scene.observe))(scene.model)
    n = int(sim.history.n_rows)
    assert n == len(result.history["time"]) > 100
    np.testing.assert_array_equal(np.asarray(sim.history.time[:n]), result.history["time"])
    iterations = np.asarray(sim.history.newton_iters[:n])
    assert np.mean(iterations != result.history["newton_iters"]) < 0.05
    np.testing.assert_allclose(iterations.sum(), result.history["newton_iters"].sum(), rtol=0.02)
    for key, value in sim.history.observed.items():
        scale = np.max(np.abs(result.history[key]))
        np.testing.assert_allclose(np.asarray(value[:n]), result.history[key], rtol=0, atol=1e-9 * scale, err_msg=key)


def test_the_rows_kept_hold_their_own_memory_not_their_chunks_buffers(whole):
    """The record copies each row out of its chunk's buffers (``CHUNK_ROWS`` rows each). A row kept as a
    view would hold its chunk's whole buffer: a run of short chunks, one or two steps each as on fine
    meshes, then held up to ``CHUNK_ROWS`` times its snapshots' memory (every row's snapshot kept, as
    ``jaxfric.run`` keeps them without ``keep_snapshots``)."""
    _, result = whole
    leaves = [a for snap in result.snapshots.values() for a in jax.tree_util.tree_leaves(snap)]
    assert len(result.snapshots) == len(result.history["time"]) > 100
    buffers = {id(a if a.base is None else a.base): (a if a.base is None else a.base).nbytes for a in leaves}
    assert sum(buffers.values()) == sum(a.nbytes for a in leaves)


def test_the_chunk_traced_from_the_start_programs_own_output_runs_the_same(whole, monkeypatch):
    """The chunk's program is traced from host arrays of the types of the start's output, while XLA compiles
    the start's program (``jaxfric.loadpath.run._compile``); where a type has no such array (a weakly typed
    array, not a scalar) it is traced from the start's output itself. Either way the same run, bit for bit."""
    weak = jax.ShapeDtypeStruct((), np.float64, weak_type=True)
    assert run_module._example(weak).weak_type and run_module._example(weak).dtype == np.float64
    assert run_module._example(jax.ShapeDtypeStruct((3,), np.float64, weak_type=True)) is None
    assert run_module._example(jax.ShapeDtypeStruct((2, 3), np.int32)).dtype == np.int32
    scene, result = whole
    monkeypatch.setattr(run_module, "_example", lambda shape: None)
    monkeypatch.setattr(run_module, "_COMPILED", LRU(1))   # compiled anew, the fallback's way
    _same_rows(_run(scene).history, result.history)


def test_a_stopped_run_resumes_bit_for_bit_from_its_checkpoint_on_disk(whole, tmp_path):
    """Stopped after two chunks, saved, read back and resumed: the whole run's history, final state and
    instants' snapshots, exactly."""
    scene, result = whole
    stopped = _run(scene, stop=_StopAfter(2))
    assert stopped.code == jf.Result.STOPPED and not stopped.converged
    n = len(stopped.history["time"])
    assert 1 < n < len(result.history["time"]) // 2 and "resumed" in stopped.message
    checkpoint.save(str(tmp_path), stopped.checkpoint, checkpoint.configuration(scene))
    saved, config = checkpoint.load(str(tmp_path), scene)
    assert config == checkpoint.configuration(scene)
    resumed = _run(scene, resume=saved)
    assert resumed.converged
    _same_rows(resumed.history, result.history)
    _same_state(resumed.final, result.final)
    for row, snap in resumed.snapshots.items():
        _same_state(snap, result.snapshots[row])
    # Raised by default (the snapshots asked for only so that the run's compiled programs serve it too).
    with pytest.raises(jf.SimulationError, match="stopped on request"):
        jf.run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
               snapshot=scene.snapshot, progress=False, stop=lambda: True)


def test_a_study_case_killed_while_it_runs_continues_from_its_checkpoint(whole, tmp_path, monkeypatch):
    """``jaxfric.io.batch.run_case`` (the studies' cases) keeps a running case's checkpoint in its directory.
    Killed after its first checkpoint (here after the first chunk), the case has no summary.json; the
    next call continues it from the checkpoint, the uninterrupted run's history and contact states bit
    for bit, and removes the checkpoint. A checkpoint of another case (other settings, other steps) is
    not resumed."""
    scene, result = whole
    out = str(tmp_path / "case")
    save, saved = checkpoint.save, []

    class Killed(BaseException):  # not a failed case: run_case lets it through, as SIGTERM ends the process
        pass

    def save_then_kill(*args):
        saved.append(save(*args))
        raise Killed

    monkeypatch.setattr(checkpoint, "save", save_then_kill)
    with pytest.raises(Killed):
        batch.run_case(out, "flat_die", None, "lcp_ssn", OVERRIDES, checkpoint_s=0.0, log=lambda m: None)
    assert not os.path.exists(os.path.join(out, "summary.json")) and os.path.exists(saved[-1])
    logs: list = []
    other = scenes.make("flat_die", None, "lcp_ssn", {**OVERRIDES, "mu": "0.2"})
    assert batch._saved_checkpoint(out, other, batch.case_configuration(other), logs.append) is None
    assert "another case" in logs[-1] and "mu" in logs[-1]
    replay = batch.case_configuration(scene, result.history["time"][1:])
    assert batch._saved_checkpoint(out, scene, replay, logs.append) is None and "steps" in logs[-1]
    monkeypatch.setattr(checkpoint, "save", save)
    done = batch.run_case(out, "flat_die", None, "lcp_ssn", OVERRIDES, checkpoint_s=0.0, log=logs.append)
    resumed = [m for m in logs if "resumed from its checkpoint at step" in m]
    assert len(resumed) == 1 and int(resumed[0].split("at step ")[1].split(",")[0]) > 0, logs
    assert done["summary"]["converged"] and not os.path.exists(saved[-1])
    output.write_run(scene, result, str(tmp_path / "whole"), figures=False)
    expected = batch.read_history(str(tmp_path / "whole" / "history.csv"))
    assert set(done["history"]) == set(expected)
    for key, column in expected.items():
        if key != "wall_s":
            assert np.array_equal(done["history"][key], column), key
    with np.load(tmp_path / "whole" / "contact.npz") as whole_contact:
        assert sorted(done["contact"]) == sorted(whole_contact.files)
        assert all(np.array_equal(done["contact"][k], whole_contact[k]) for k in whole_contact.files)


def test_partial_writes_come_when_due_and_take_at_most_a_hundredth_of_the_run(monkeypatch):
    """``checkpoint.Every``: nothing before ``first_s``, then a write at the first chunk after each due time,
    the next one ``every_s`` later, or 100 times the write's own duration where that is longer."""
    clock, cost, written = [0.0], [0.0], []
    monkeypatch.setattr(checkpoint.time, "perf_counter", lambda: clock[0])

    def write(result):
        written.append(result)
        clock[0] += cost[0]

    every = checkpoint.Every(write, 10.0, first_s=5.0)
    for now, duration in ((0.0, 0), (4.9, 0), (5.0, 0), (14.9, 0), (15.0, 0.5), (65.4, 0), (65.5, 0), (75.4, 0)):
        clock[0], cost[0] = now, duration
        every(lambda: now)
    assert written == [5.0, 15.0, 65.5]


def test_kept_snapshots_write_the_contact_file_of_all_snapshots(whole, tmp_path):
    """The rows `InstantRows` keeps as the run goes are the rows contact.npz needs at the end."""
    scene, result = whole
    kept = _run(scene, keep_snapshots=InstantRows(scene.name))
    assert len(kept.snapshots) < len(result.snapshots) // 10
    output.write_run(scene, kept, str(tmp_path / "kept"), figures=False)
    output.write_run(scene, result, str(tmp_path / "all"), figures=False)
    with np.load(tmp_path / "kept" / "contact.npz") as a, np.load(tmp_path / "all" / "contact.npz") as b:
        assert a.files == b.files and all(np.array_equal(a[k], b[k]) for k in a.files)


def test_resume_with_another_configuration_is_refused_in_one_line(whole, tmp_path, capsys):
    out = str(tmp_path / "run")
    assert cli.main(["run", *ARGS, "--quiet", "--out", out]) == cli.EXIT_OK
    capsys.readouterr()
    assert cli.main(["run", *_args(mu="0.2"), "--quiet", "--resume", out]) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "mu" in err and "0.15" in err and "0.2" in err, err
    assert cli.main(["run", *ARGS, "--quiet", "--resume", str(tmp_path / "none")]) == cli.EXIT_USAGE
    assert "checkpoint.npz" in capsys.readouterr().err


def _table(path):
    return np.genfromtxt(os.path.join(path, "history.csv"), delimiter=",", names=True, dtype=None, encoding="utf-8")


def test_resume_with_a_longer_stroke_extends_the_run(whole, tmp_path, capsys):
    """--resume with --set U_draw larger continues the finished run from its last state to the longer
    stroke: the rows before keep their displacements and forces exactly, and the extended run follows the
    longer run made from the start (whose increments differ: the schedule divides each stroke into equal
    steps) to 1e-3 of the force, ending on the same forces to round-off (the sliding die under constant
    force). A shorter stroke is refused."""
    out, ref = str(tmp_path / "run"), str(tmp_path / "ref")
    longer = _args(U_draw="0.02")
    assert cli.main(["run", *ARGS, "--quiet", "--out", out]) == cli.EXIT_OK
    before = _table(out)
    assert cli.main(["run", *longer, "--quiet", "--resume", out]) == cli.EXIT_OK
    assert cli.main(["run", *longer, "--quiet", "--out", ref]) == cli.EXIT_OK
    assert check_run_dir(out) == []
    capsys.readouterr()
    a, b = _table(out), _table(ref)
    for name in ("drawing_displacement", "drawing_force", "clamping_force", "tool_position"):
        assert np.array_equal(a[name][:len(before)], before[name]), name
        np.testing.assert_allclose(a[name][-1], b[name][-1], rtol=1e-9)
    assert a["drawing_displacement"][-1] == 0.02 and len(a) > len(before) + 200
    draw = b["drawing_displacement"] > 0.0012
    curve = np.interp(b["drawing_displacement"][draw], a["drawing_displacement"], a["drawing_force"])
    assert np.max(np.abs(curve - b["drawing_force"][draw])) < 1e-3 * np.max(b["drawing_force"])
    assert cli.main(["run", *_args(U_draw="0.015"), "--quiet", "--resume", out]) == cli.EXIT_USAGE
    assert "can only be extended" in capsys.readouterr().err


def _summary(out):
    try:
        with open(os.path.join(out, "summary.json")) as f:
            return json.load(f)
    except (OSError, ValueError):  # not written yet, or being replaced
        return None


def _signalled(argv, out, signum, after_steps, env):
    """Run the command line, send ``signum`` once summary.json reports more than ``after_steps`` steps;
    returns (exit status, stderr)."""
    proc = subprocess.Popen([sys.executable, "-m", "jaxfric", *argv], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        summary = _summary(out)
        if summary is not None and summary["n_steps"] > after_steps:
            proc.send_signal(signum)
            break
        time.sleep(0.02)
    _, err = proc.communicate(timeout=300)
    return proc.returncode, err


def test_sigterm_and_sigint_stop_the_command_line_and_resume_to_the_uninterrupted_run(tmp_path):
    """SIGTERM, then SIGINT in the resumed run: each ends the run within a chunk with exit status 3,
    one line saying how to resume, and a run directory that passes the contract checker with
    converged false; the run resumed to the end writes what the uninterrupted run writes (all but the
    times), here in this process: the command lines read its programs from the suite's persistent
    compilation cache (tests/conftest.py)."""
    assert os.environ.get("JAX_COMPILATION_CACHE_DIR")   # set by tests/conftest.py, inherited below
    env = dict(os.environ, JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0", JAX_PLATFORMS="cpu")
    ref, out = str(tmp_path / "ref"), str(tmp_path / "run")
    assert cli.main(["run", *ARGS, "--quiet", "--out", ref]) == cli.EXIT_OK
    argv = ["run", *ARGS, "--quiet", "--out", out]
    steps = 0
    for signum, extra in ((signal.SIGTERM, []), (signal.SIGINT, ["--resume", out])):
        code, err = _signalled(argv + extra, out, signum, steps, env)
        assert code == cli.EXIT_STOPPED, err
        assert err.strip().splitlines()[-1].startswith("jaxfric: stopped at step") and "--resume" in err, err
        assert check_run_dir(out) == []
        summary = _summary(out)
        assert not summary["converged"] and "stopped on request" in summary["message"]
        assert steps < summary["n_steps"] < 200
        steps = summary["n_steps"]
    done = subprocess.run([sys.executable, "-m", "jaxfric", *argv, "--resume", out], capture_output=True,
                          text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr
    assert check_run_dir(out) == []

    def table(path):
        with open(os.path.join(path, "history.csv")) as f:
            rows = [line.split(",") for line in f.read().splitlines()]
        wall = rows[0].index("wall_s")
        return [r[:wall] + r[wall + 1:] for r in rows]

    assert table(out) == table(ref)
    with np.load(os.path.join(out, "contact.npz")) as a, np.load(os.path.join(ref, "contact.npz")) as b:
        assert a.files == b.files and all(np.array_equal(a[k], b[k]) for k in a.files)
