"""Test configuration: float64 everywhere, strict dtype promotion, and faster-compiling XLA settings.

The fast suite is almost all XLA compilation: measured with `make test` on a 2-core machine,
compilation took 1426 s of the 1559 s that the tests ran (backend 1185 s, lowering 95 s, tracing
147 s, in 3176 compilations). The suite therefore asks XLA to compile faster, for results equal to
round-off: the command lines' flags (:mod:`jaxfric.io.xla_flags`: its older CPU fusion emitters, the same
two test files, each pinned to a core of its own, 451 s against 715 s; reductions in one loop), and,
where exactly the slow runs are deselected (``-m "not slow"``, as ``make test`` does), little
optimisation (JAX's ``jax_disable_most_optimizations``: XLA's backend optimisation level 0 and LLVM's
cheap passes; the fast suite 8 min 14 s and 8 min 49 s against 10 min 1 s). Its programs run up to
three times slower, so the tests that mostly run (marked ``xla_optimized``: their simulations take
longer than the optimisation's compilation, measured per test, docs/results.md, test suite run time)
and the slow runs keep XLA's default optimisation. The setting is JAX's, read at each compilation: a
test's own programs, and those of the command lines it starts (``JAX_DISABLE_MOST_OPTIMIZATIONS`` in
their environment), get its marker's. The flags are probed in a child
process first, because an XLA that no longer knows one aborts the process at start-up; they are then
left out. Flags already in ``XLA_FLAGS`` are kept, and ``JAXFRIC_TEST_XLA_DEFAULTS=1`` runs the suite
with XLA's defaults (the package's functions set no XLA flag; the command lines ask for
:data:`~jaxfric.io.xla_flags.FAST_COMPILE_FLAGS` only).

The suite's processes (pytest-xdist's two workers and the command lines that tests start) share one JAX
persistent compilation cache, so that a program compiled in one process is read from disk in the others,
and it is kept between test runs (``.pytest_cache/d/jaxfric-xla``; ``pytest --cache-clear`` or ``make clean``
empties it, and it is emptied when it passes :data:`CACHE_LIMIT_MB`): a later run reads the programs that
took 0.05 s or more to compile, unless a change touched them (the fast suite 301 s instead of 432 s in a
clean clone, docs/results.md, test suite run time). ``JAXFRIC_TEST_CACHE=fresh`` gives a test run a folder of its own,
removed at its end (what a clean clone sees, and how the suite's compilation is measured:
``experiments/suite_compile.py``); ``JAX_COMPILATION_CACHE_DIR`` already set: that folder is used, and kept.
"""

import os
import shutil
import tempfile

import pytest

# Importing jaxfric starts no XLA backend, so the flags set below still apply; FAST_COMPILE_FLAGS are the
# command lines' own.
from jaxfric.io.xla_flags import FAST_COMPILE_FLAGS, xla_accepts

# One host device: `jaxfric run` would otherwise ask for one per core (jaxfric.io.xla_flags.use_host_cores) in
# the command lines that tests start, whose cores the two workers already keep busy; the split over two
# host devices is tested in a child process of its own (tests/test_host_devices.py).
ONE_DEVICE_FLAGS = ("--xla_force_host_platform_device_count=1",)


def _ask_for_fast_compilation(wanted):
    """Runs before JAX starts its backend (which no test module does on import): XLA reads ``XLA_FLAGS``
    once, when it starts."""
    current = os.environ.get("XLA_FLAGS", "")
    if os.environ.get("JAXFRIC_TEST_XLA_DEFAULTS") == "1" or any(
            flag.split("=")[0] in current for flag in wanted):
        return
    flags = " ".join([current, *wanted]).strip()
    if xla_accepts(flags):
        # pytest-xdist's workers inherit the environment, and find the flags already set.
        os.environ["XLA_FLAGS"] = flags


# In the fast suite XLA also leaves its while loops' invariant code where it is: at little optimisation that pass
# took a quarter of the HLO passes' time, the runs' chunk programs compiled in 10 to 35 % less time without it
# and ran 3 to 7 % longer (docs/results.md, test suite run time).
FAST_SUITE_PASSES_OFF = ("while-loop-invariant-code-motion",)


def _passes_off(flags, passes):
    """``flags`` with ``passes`` added to its ``--xla_disable_hlo_passes`` list."""
    name = "--xla_disable_hlo_passes="
    return tuple(f + "," + ",".join(passes) if f.startswith(name) else f for f in flags)


def _fast_suite(config) -> bool:
    """Exactly the slow runs deselected (``-m "not slow"``, as ``make test`` runs the suite)."""
    return " ".join((config.option.markexpr or "").split()) == "not slow"


# JAX's switch for little optimisation, read at each compilation; its environment variable reaches the command
# lines that tests start. On in the fast suite, off in its tests marked xla_optimized (pytest_runtest_setup).
_LITTLE_OPTIMISATION = "JAX_DISABLE_MOST_OPTIMIZATIONS"


def pytest_configure(config):
    flags = _passes_off(FAST_COMPILE_FLAGS, FAST_SUITE_PASSES_OFF) if _fast_suite(config) else FAST_COMPILE_FLAGS
    _ask_for_fast_compilation(flags + ONE_DEVICE_FLAGS)


def _optimise(on: bool):
    jax.config.update("jax_disable_most_optimizations", not on)
    os.environ[_LITTLE_OPTIMISATION] = "0" if on else "1"


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    """Before the test's fixtures: its programs' optimisation (a module fixture is compiled with that of the
    first test that asks for it)."""
    if _fast_suite(item.config) and os.environ.get("JAXFRIC_TEST_XLA_DEFAULTS") != "1":
        _optimise(item.get_closest_marker("xla_optimized") is not None)


# The kept cache's folder, and the size past which it is emptied at the start of a test run: JAX trims a
# cache only with the filelock package, not a dependency of jaxfric. The fast suite writes 360 programs, 67 MB.
CACHE_FOLDER = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), ".pytest_cache", "d",
                            "jaxfric-xla")   # pytest's folder for plugins' data, which --cache-clear empties
CACHE_LIMIT_MB = 2000


def _folder_mb(folder) -> float:
    """The size of the files in ``folder`` (JAX's cache keeps its entries side by side), in MB."""
    return sum(entry.stat().st_size for entry in os.scandir(folder) if entry.is_file()) / 2**20


def _share_compiled_programs():
    """One compilation cache for the test run, set in the environment before JAX starts (the workers and the
    command lines that tests run inherit it). Returns the folder to remove at the end, if made here."""
    # The command lines keep every program (jaxfric.io.cache); the suite keeps those that took 0.05 s or more
    # (360 programs; 248 of them from 0.05 to 1 s took 71 s of XLA's time in a cold run), not the 2,900 shorter
    # one-primitive programs (36 s): writing them too made a first run 556 s, against 493 s. The next run
    # 323 s, against 355 s keeping JAX's default, a second or more (docs/results.md, test suite run time).
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.05")
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return None
    if os.environ.get("JAXFRIC_TEST_CACHE") == "fresh":
        folder = tempfile.mkdtemp(prefix="jaxfric-tests-xla-")
        os.environ["JAX_COMPILATION_CACHE_DIR"] = folder
        return folder
    if os.path.isdir(CACHE_FOLDER) and _folder_mb(CACHE_FOLDER) > CACHE_LIMIT_MB:
        shutil.rmtree(CACHE_FOLDER, ignore_errors=True)
    os.environ["JAX_COMPILATION_CACHE_DIR"] = CACHE_FOLDER
    return None


_SESSION_CACHE = _share_compiled_programs()


# The suite's longest files (summed test time: ``python experiments/suite_files.py REPORT.xml``), run first.
# pytest-xdist hands out whole files (``--dist loadfile``), by default the files with the most tests first,
# which puts the one-test files last (test_fit_nine.py, the longest file, among them), where one worker
# runs them alone; ``make test`` turns that order off (``--no-loadscope-reorder``) for this one.
LONGEST_FIRST = ("test_fit.py", "test_contact.py", "test_fit_nine.py", "test_solver.py", "test_resume.py",
                 "test_scenes.py", "test_exact.py", "test_element_ans.py", "test_accuracy.py",
                 "test_derivatives.py", "test_experiments.py", "test_original_study.py")


def pytest_collection_modifyitems(config, items):
    """The files of :data:`LONGEST_FIRST` first, in that order, then the others as collected."""
    def rank(item):
        name = os.path.basename(str(item.path))
        return LONGEST_FIRST.index(name) if name in LONGEST_FIRST else len(LONGEST_FIRST)
    items.sort(key=rank)   # stable: the order within a file, and of the other files, is kept


def pytest_unconfigure(config):
    """The controlling process (not a worker) removes the cache it made."""
    if _SESSION_CACHE and not hasattr(config, "workerinput"):
        shutil.rmtree(_SESSION_CACHE, ignore_errors=True)

import jax  # noqa: E402  (after XLA_FLAGS is final)

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
