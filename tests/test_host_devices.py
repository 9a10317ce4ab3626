"""A run's element loops split over two host devices (:func:`jaxfric.numerics.devices.run_devices`), as
``jaxfric run`` does on a machine with two cores or more (:func:`jaxfric.io.xla_flags.use_host_cores`): the
results are the one-device run's to round-off, in the same steps.

XLA fixes its host devices when it starts, so the split runs in a child process that asks for two; the
suite's own processes keep one (``tests/conftest.py``)."""

import json
import os
import subprocess
import sys
import time

import pytest

from jaxfric.io.xla_flags import HOST_DEVICES, cpu_load, use_host_cores

_TWO_DEVICES = r"""
import json
import numpy as np
import jax
jax.config.update("jax_enable_x64", True)
import jaxfric
from jaxfric import scenes
from jaxfric.fem import assembly
from jaxfric.fem.element import element_geometry
from jaxfric.loadpath.model import initial_state
from jaxfric.numerics.devices import run_devices

out = {"devices": len(jax.devices())}
two = tuple(jax.devices())

# Whether the program of fn at args is split over the devices (it exchanges values between them). A new
# function each time: jax.jit keeps a function's trace, made under the setting of its first call.
def collective(fn, *args):
    text = jax.jit(lambda *a: fn(*a)).lower(*args).compile().as_text()
    return any(op in text for op in ("all-gather", "all-reduce"))

# The assembly at a random displacement, on 25 elements: an odd count, padded to equal shares.
model = scenes.make("flat_die", "const_position", "penalty", {"mesh": "25x1"}).model
geo = element_geometry(model.mesh.nodes[model.mesh.elements], model.thickness_points)
states = initial_state(model).material
u = jax.numpy.asarray(np.random.default_rng(3).normal(scale=1e-3, size=model.mesh.nodes.shape))
def assembled(u, states):
    a = assembly.internal_force_and_tangent(model.mesh, model.material, model.formulation, geo, u, states)
    return a.f_int, a.tangent.diag, a.tangent.lower, a.tangent.upper
one = jax.jit(lambda *a: assembled(*a))(u, states)
with run_devices(two):
    split = jax.jit(lambda *a: assembled(*a))(u, states)
out["assembly"] = max(float(np.max(np.abs(a - b)) / np.max(np.abs(a))) for a, b in zip(one, split))
with run_devices(two):
    out["assembly_split"] = collective(assembled, u, states)

# The flat die (exact contact), with and without the split, in this process; every
# scene and algorithm: the slow test below.
sc = scenes.make("flat_die", None, "lcp_ssn", {"mesh": "24x1"})
runs = []
for devices in (None, two):
    with run_devices(devices):
        r = jaxfric.run(sc.model, newton=sc.newton, control=sc.control, observe=sc.observe, progress=False)
    runs.append({"converged": bool(r.converged), "time": [float(t) for t in r.history["time"]],
                 "iters": [int(i) for i in r.history["newton_iters"]],
                 "force": [float(f) for f in r.history["drawing_force"]],
                 "clamp": [float(f) for f in r.history["clamping_force"]]})
out["runs"] = runs
print(json.dumps(out))
"""


def _env_with_devices(count: int) -> dict:
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split()
             if not f.startswith("--xla_force_host_platform_device_count")]
    return dict(os.environ, XLA_FLAGS=" ".join([*flags, f"--xla_force_host_platform_device_count={count}"]))


def _same_steps(one, split):
    """The same step sequence, and Newton iterations within 3 % in all. The flat die 24 x 1's sliding steps
    converge at the round-off floor, where each one's stopping test is decided at round-off: at the suite's XLA
    backend level 0, whose code for a device's share of the elements rounds differently from the code for all
    of them, a third of its 386 steps take one or two iterations more or fewer on two devices, 1.1 % of the
    run's iterations in all, with the forces within 3e-12 of their largest (at XLA's default level, with the
    same XLA settings on one device and on two, the `make run` case is the same bit for bit)."""
    assert len(split["time"]) == len(one["time"])
    assert max(abs(a - b) for a, b in zip(one["time"], split["time"])) < 1e-12
    assert abs(sum(split["iters"]) - sum(one["iters"])) <= 0.03 * sum(one["iters"]), \
        (sum(one["iters"]), sum(split["iters"]))


def test_element_loops_on_two_host_devices_give_the_one_device_results():
    done = subprocess.run([sys.executable, "-c", _TWO_DEVICES], env=_env_with_devices(2), capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["devices"] == 2
    assert out["assembly_split"]
    assert out["assembly"] < 1e-12, out["assembly"]
    one, split = out["runs"]
    assert one["converged"] and split["converged"]
    _same_steps(one, split)
    scale = max(abs(f) for f in one["force"] + one["clamp"])
    assert scale > 10.0
    for name in ("force", "clamp"):
        assert max(abs(a - b) for a, b in zip(one[name], split[name])) < 1e-9 * scale, name


def test_the_command_line_asks_for_one_host_device_per_core_up_to_two():
    env: dict = {}
    assert use_host_cores(env, cores=16) == HOST_DEVICES == 2
    assert env["XLA_FLAGS"] == "--xla_force_host_platform_device_count=2"
    env = {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=false"}
    assert use_host_cores(env, cores=2, load={0: 0.1, 1: 0.2}) == 2
    assert env["XLA_FLAGS"].split() == ["--xla_cpu_use_fusion_emitters=false",
                                        "--xla_force_host_platform_device_count=2"]
    # One core: nothing to split over, nothing added.
    env = {}
    assert use_host_cores(env, cores=1) == 1 and "XLA_FLAGS" not in env
    # A count already given is kept, and XLA's defaults add nothing.
    env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=1"}
    assert use_host_cores(env, cores=8) == 1 and env["XLA_FLAGS"] == "--xla_force_host_platform_device_count=1"
    env = {"JAXFRIC_XLA_DEFAULTS": "1"}
    assert use_host_cores(env, cores=8) == 1 and "XLA_FLAGS" not in env


def test_the_command_line_keeps_to_one_cpu_where_other_processes_use_its_cores():
    """Half a core or more kept busy by other processes: one device, on the least busy CPU."""
    pinned: list = []
    env: dict = {}
    assert use_host_cores(env, cores=2, load={0: 0.3, 1: 0.9}, pin=pinned.append) == 1
    assert pinned == [0] and "XLA_FLAGS" not in env
    assert use_host_cores(env, cores=2, load={0: 0.2, 1: 0.2}, pin=pinned.append) == 2 and pinned == [0]
    # A count given is the user's: kept, nothing pinned.
    env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert use_host_cores(env, cores=2, load={0: 1.0, 1: 1.0}, pin=pinned.append) == 2 and pinned == [0]
    load = cpu_load({0})
    assert load is None or 0.0 <= load[0] <= 1.0


@pytest.mark.skipif(not os.path.exists("/proc/stat"), reason="no /proc/stat: the load is not measured")
def test_cpu_load_sees_a_busy_cpu(tmp_path):
    """A child process spinning on this process's first CPU: that CPU's load is near one."""
    cpu = min(os.sched_getaffinity(0))
    spin = subprocess.Popen([sys.executable, "-c", f"import os, time\nos.sched_setaffinity(0, {{{cpu}}})\n"
                             "end = time.time() + 3\nwhile time.time() < end: pass"])
    try:
        time.sleep(0.5)
        load = cpu_load({cpu}, interval=0.5)
    finally:
        spin.wait()
    assert load is not None and load[cpu] > 0.8, load


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2 if hasattr(os, "sched_getaffinity") else True,
                    reason="one core: jaxfric run does not split")
def test_jaxfric_run_splits_its_work_over_two_cores(tmp_path):
    """The command line with two host devices (given in XLA_FLAGS: left free, it measures the load of
    its CPUs, which the suite's other worker keeps busy): the run's work split over them, and the run
    directory says so."""
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split()
             if not f.startswith("--xla_force_host_platform_device_count")]
    env = dict(os.environ, XLA_FLAGS=" ".join([*flags, "--xla_force_host_platform_device_count=2"]))
    out = tmp_path / "run"
    done = subprocess.run([sys.executable, "-m", "jaxfric", "run", "flat_die", "--mesh", "24x1", "--quiet",
                           "--out", str(out)], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["converged"] and summary["run_devices"] == 2


_EVERY_SCENE = r"""
import json, sys
import numpy as np
import jax
jax.config.update("jax_enable_x64", True)
import jaxfric
from jaxfric import scenes
from jaxfric.numerics.devices import run_devices

out = []
for name, variant, algorithm, overrides in json.loads(sys.argv[1]):
    sc = scenes.make(name, variant, algorithm, overrides)
    runs = []
    for devices in (None, tuple(jax.devices())):
        with run_devices(devices):
            r = jaxfric.run(sc.model, newton=sc.newton, control=sc.control, observe=sc.observe, progress=False)
        runs.append({"converged": bool(r.converged), "iters": [int(i) for i in r.history["newton_iters"]],
                     "time": [float(t) for t in r.history["time"]], "devices": r.devices,
                     "force": [float(f) for f in r.history["drawing_force"]],
                     "clamp": [float(f) for f in r.history["clamping_force"]]})
    out.append([name, variant, algorithm, runs])
print(json.dumps(out))
"""

# Every scene, the force-driven tools (a bordered solve), the augmented Lagrangian's loop, and Lemke's (not split).
_CASES = [
    ["flat_die", "const_force", "penalty", {"mesh": "24x2"}],
    ["nine", "mu017", "auglag", {"mesh": "30x2", "U_draw": 1.0}],
    ["nine", "mu000", "lcp_lemke", {"mesh": "30x2", "U_draw": 1.0}],
    ["bead", "th090_mu017", "lcp_ssn", {"mesh": "100x2", "theta": 10.0, "dtheta": 2.5, "s_draw": 0.5, "ds": 0.25,
                                        "n_clamp": 2}],
    ["blankholder", "shape1", "lcp_ssn", {"nx": 40, "U_pull": 1.0}],
]


@pytest.mark.slow
def test_every_scene_and_algorithm_on_two_host_devices_gives_the_one_device_run():
    done = subprocess.run([sys.executable, "-c", _EVERY_SCENE, json.dumps(_CASES)], env=_env_with_devices(2),
                          capture_output=True, text=True, timeout=1800)
    assert done.returncode == 0, done.stderr[-3000:]
    for name, variant, algorithm, (one, split) in json.loads(done.stdout.strip().splitlines()[-1]):
        case = f"{name} {variant} {algorithm}"
        assert one["converged"] and split["converged"], case
        # Lemke's pivoting calls the host: its runs stay on one device (jaxfric.loadpath.run.split_over).
        assert (one["devices"], split["devices"]) == (1, 1 if algorithm == "lcp_lemke" else 2), case
        _same_steps(one, split)
        scale = max(abs(f) for f in one["force"] + one["clamp"])
        for key in ("force", "clamp"):
            assert max(abs(a - b) for a, b in zip(one[key], split[key])) <= 1e-9 * scale, (case, key)
