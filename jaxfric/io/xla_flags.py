"""XLA settings of jaxfric's command lines: a run's program compiled faster, run as fast.

Most of a run's compile time is XLA's CPU code generation. Its older fusion emitters
(``--xla_cpu_use_fusion_emitters=false``, :data:`FAST_COMPILE_FLAGS`) generate the code of the same fused
computations in less time, and the code runs as fast: the Nine ``mu017`` on 300 x 3 drawn 10 mm
(``JAXFRIC_CACHE_DIR=off jaxfric run nine --variant mu017 --set U_draw=10``, with and without the flag in
``XLA_FLAGS``) compiled in 16.7 s against 27.2 s and solved in 23.5 s against 24.8 s, in the same 210 steps
and 1379 Newton iterations (``docs/results.md``, run time of the Nine test). Results agree to round-off.

XLA's CPU pipeline also rewrites every reduction over more than 32 elements (a norm, a largest entry, an
``all`` over the dofs or the pairs) as a tree of windowed reductions, for the round-off of long sums; each
window is a kernel of its own (about 10 ms of code generation), and the Nine's chunk program holds 56 of
them. Leaving that pass out (``--xla_disable_hlo_passes=tree_reduction_rewriter``) reduces in one loop
instead: the Nine's chunk compiles in 4.5 to 4.9 s against 5.1 to 5.7 s, and the ``make run`` case takes
the same 810 steps and 5035 Newton iterations to the same steady force (``python
experiments/bench_compile.py --xla-flags=...``; ``docs/results.md``, compilation). The sums concerned run
over a mesh's dofs, pairs or points: one loop's round-off, about n eps of the sum of magnitudes (2e-11 for
n = 1e5), stays far below the Newton tolerance (1e-8 of the force scale).

``jaxfric run`` also shows XLA the process's cores as host devices, up to two (:func:`use_host_cores`), and
splits the run's element loops over them (:func:`host_devices`, :mod:`jaxfric.numerics.devices`): one run
then uses two cores, each device computing on one thread (:data:`ONE_THREAD_PER_DEVICE`, which
:func:`use_fast_compilation` adds where two host devices are asked for). Where other processes already keep
its cores busy (:func:`cpu_load`), it keeps to its least busy CPU with one device instead
(:data:`PIN_WHEN_BUSY`).

The command lines (:mod:`jaxfric.cli`) call :func:`use_fast_compilation` before their first computation;
the package's functions set nothing, and a script or notebook may call it first thing. XLA reads
``XLA_FLAGS`` once, when its backend starts, and an XLA that does not know a flag aborts the process
then; so a flag is first tried in a child process, and its acceptance kept per jaxlib version in the
compilation cache's folder (:func:`jaxfric.io.cache.cache_dir`; tried in every process where the cache is
off, and after a refusal). Flags already in ``XLA_FLAGS`` are kept as given; ``JAXFRIC_XLA_DEFAULTS=1``
leaves XLA's defaults.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import time
from collections.abc import Callable, MutableMapping
from importlib import metadata

from .cache import cache_dir

__all__ = ["FAST_COMPILE_FLAGS", "HOST_DEVICES", "ONE_THREAD_PER_DEVICE", "PIN_WHEN_BUSY", "cpu_load",
           "host_devices", "use_fast_compilation", "use_host_cores", "xla_accepts"]

FAST_COMPILE_FLAGS = ("--xla_cpu_use_fusion_emitters=false", "--xla_disable_hlo_passes=tree_reduction_rewriter")


def xla_accepts(flags: str) -> bool:
    """Whether a child process's XLA starts with ``XLA_FLAGS`` = ``flags`` and runs a computation."""
    probe = "import jax.numpy as jnp; (jnp.ones(3) + 1).block_until_ready()"
    env = {**os.environ, "XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu"}
    try:
        done = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


def _remembered(flags: str, folder: str | None, probe: Callable[[str], bool]) -> bool:
    """``probe(flags)``, an acceptance kept in ``folder`` per jaxlib version and flags (a refusal, which may
    be a child that could not start, is asked again in the next process)."""
    if folder is None:
        return probe(flags)
    try:
        version = metadata.version("jaxlib")
    except metadata.PackageNotFoundError:
        version = "unknown"
    key = hashlib.sha256(f"{version} {flags}".encode()).hexdigest()[:16]
    path = os.path.join(folder, f"xla-flags-{key}")
    if os.path.exists(path):
        return True
    accepted = probe(flags)
    if accepted:
        try:
            os.makedirs(folder, exist_ok=True)
            with open(path, "w") as f:
                f.write(flags + "\n")
        except OSError:
            pass
    return accepted


def use_fast_compilation(environ: MutableMapping[str, str] | None = None,
                         probe: Callable[[str], bool] = xla_accepts) -> bool:
    """Add :data:`FAST_COMPILE_FLAGS` to ``XLA_FLAGS`` in ``environ`` (default ``os.environ``) where XLA
    accepts them, and :data:`ONE_THREAD_PER_DEVICE` where ``XLA_FLAGS`` already asks for two host devices or
    more (:func:`use_host_cores`); call it before the process's first computation. Returns whether the fast
    compilation's flags are all in effect (False: ``JAXFRIC_XLA_DEFAULTS=1``, refused by this XLA, or a flag
    already given its own value, which is kept while the others are added)."""
    env = os.environ if environ is None else environ
    current = env.get("XLA_FLAGS", "")
    if env.get("JAXFRIC_XLA_DEFAULTS") == "1":
        return False
    given = {flag.split("=")[0] for flag in current.split()}
    # With the threads' flag first, then (refused) without it: an XLA without that switch still compiles fast.
    threads = ((ONE_THREAD_PER_DEVICE,), ()) if (_device_count(current) or 1) > 1 else ((),)
    for extra in threads:
        wanted = [flag for flag in (*FAST_COMPILE_FLAGS, *extra) if flag.split("=")[0] not in given]
        if not wanted:
            return all(flag in current.split() for flag in FAST_COMPILE_FLAGS)
        flags = " ".join([current, *wanted]).strip()
        if _remembered(flags, cache_dir(env), probe):
            env["XLA_FLAGS"] = flags
            return all(flag in flags.split() for flag in FAST_COMPILE_FLAGS)
    return False


# `jaxfric run` shows XLA this many of the process's cores as host devices (at most) and splits the run's
# work over them (:func:`jaxfric.numerics.devices.run_devices`). Two is the count measured (docs/results.md,
# run time of the Nine test: two cores).
HOST_DEVICES = 2
_DEVICE_COUNT = "--xla_force_host_platform_device_count"
# With one host device per core every device keeps its core busy, and XLA's Eigen operations (its dots, LU
# factorisations and triangular solves) would each still spread over a thread pool of all the cores: the
# devices' pools then contend for the same cores. One thread per device: the Nine mu017 drawn 10 mm (1379
# Newton iterations, two host devices) solved in 11.7 and 11.1 s against 14.2 and 15.5 s with the pools;
# on one device 14.6 to 15.1 s either way (docs/results.md, run time of the Nine test: two cores).
ONE_THREAD_PER_DEVICE = "--xla_cpu_multi_thread_eigen=false"
# Busy cores (summed shares) of the process's CPUs from which `jaxfric run` keeps to one device on one
# CPU. Two runs at once on the 2-core machine, each free to use both CPUs, contend for them: the
# six-node Nine on 150 x 12 (``--set element=anst --set thickness_points=4 --set element_order=2``) took
# 1280 ms per Newton iteration in each run with one device each, 73 and 75 ms with each run pinned to a
# CPU (``taskset``); a run pinned beside one that keeps two devices, 141 ms, and that one 210 ms
# (docs/results.md, two cores).
PIN_WHEN_BUSY = 0.5


def _device_count(flags: str) -> int | None:
    """The host devices that ``XLA_FLAGS`` = ``flags`` asks for (None where it names no count)."""
    for flag in flags.split():
        name, _, value = flag.partition("=")
        if name == _DEVICE_COUNT:
            return int(value) if value.isdigit() else 1
    return None


def cpu_load(cpus: set[int], interval: float = 0.2) -> dict[int, float] | None:
    """The share of each CPU of ``cpus`` that other processes keep busy now: its non-idle share of the
    time over ``interval`` seconds (``/proc/stat``, while this process sleeps). None where ``/proc/stat``
    cannot be read (not Linux)."""
    def sample() -> dict[int, tuple[int, int]]:
        times = {}
        with open("/proc/stat") as f:
            for line in f:
                name, *values = line.split()
                if name.startswith("cpu") and name[3:].isdigit() and int(name[3:]) in cpus:
                    ticks = [int(v) for v in values[:8]]   # user nice system idle iowait irq softirq steal
                    times[int(name[3:])] = (sum(ticks), ticks[3] + ticks[4])
        return times
    try:
        before = sample()
        time.sleep(interval)
        after = sample()
    except (OSError, ValueError):
        return None
    load = {}
    for cpu in before.keys() & after.keys():
        spent, idle = (a - b for a, b in zip(after[cpu], before[cpu], strict=True))
        load[cpu] = 1.0 - idle / spent if spent > 0 else 0.0
    return load


def _pin(cpu: int) -> None:
    os.sched_setaffinity(0, {cpu})


def use_host_cores(environ: MutableMapping[str, str] | None = None, cores: int | None = None,
                   load: dict[int, float] | None = None, pin: Callable[[int], None] = _pin) -> int:
    """Ask XLA for one host device per core, up to :data:`HOST_DEVICES`, in ``XLA_FLAGS`` of ``environ``
    (default ``os.environ``), where the process has those cores to itself; call it before the process's
    first computation. ``cores``: the cores this process may use (default: its CPU affinity). ``load``: the
    busy share of each of those CPUs (default: measured, :func:`cpu_load`, where ``cores`` is not given).
    Where other processes keep half a core or more of them busy, one device, and the process is pinned
    to its least busy CPU (``pin``): XLA's threads would otherwise contend with the other processes' on
    every CPU (:data:`PIN_WHEN_BUSY`). A count already in ``XLA_FLAGS`` is kept, and
    ``JAXFRIC_XLA_DEFAULTS=1`` adds nothing. Returns the host devices XLA will show (1 where nothing is
    added)."""
    env = os.environ if environ is None else environ
    current = env.get("XLA_FLAGS", "")
    given = _device_count(current)
    if given is not None:
        return given
    if env.get("JAXFRIC_XLA_DEFAULTS") == "1":
        return 1
    if cores is None:
        cpus = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
        cores = len(cpus) if cpus is not None else (os.cpu_count() or 1)
        if load is None and cpus is not None and cores > 1:
            load = cpu_load(cpus)
    count = max(1, min(HOST_DEVICES, cores))
    if count > 1 and load and sum(load.values()) >= PIN_WHEN_BUSY:
        pin(min(load, key=load.__getitem__))
        return 1
    if count > 1:
        env["XLA_FLAGS"] = " ".join([current, f"{_DEVICE_COUNT}={count}"]).strip()
    return count


def host_devices() -> tuple | None:
    """The devices to split a run's element loops over: JAX's CPU devices where the default backend is the
    CPU and shows two or more of them (:func:`use_host_cores`), else None (one device, or an accelerator,
    which runs a whole loop at once)."""
    import jax

    if jax.default_backend() != "cpu":
        return None
    devices = jax.local_devices(backend="cpu")
    return tuple(devices) if len(devices) > 1 else None
