"""Public entry point: compile, run with a progress bar, and turn result codes into exceptions."""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable

import equinox as eqx
import jax
import numpy as np

from ..numerics.lru import LRU
from ..numerics.newton import NewtonOptions
from ..numerics.results import Result, SimulationError, describe
from .controller import StepControl
from .model import SimState, StripModel, default_observe, initial_state
from .progress import ProgressMonitor
from .simulate import Simulation, simulate, simulate_fixed

__all__ = ["RunResult", "run", "MemoryBudgetError", "available_memory"]


class MemoryBudgetError(ValueError):
    """The compiled run needs more memory than the machine has available (raised before it starts)."""


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation now (Linux ``MemAvailable``; else the free
    physical pages), or None where neither can be read."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return None


def check_memory(compiled, model: StripModel, available: int | None = None) -> int | None:
    """Refuse a run whose compiled program needs more memory than is available, before it allocates.

    The need is XLA's own account of the compiled program (``memory_analysis()``: its arguments,
    outputs, with the history buffers, and temporary buffers, with the Jacobian's blocks, which grow
    as nx (ny + 1)^2). Checked on the CPU only (an accelerator's runtime reports its own out-of-memory
    error); ``available`` defaults to :func:`available_memory`. Returns the bytes needed (None if XLA
    gives no account).

    Raises:
        MemoryBudgetError: naming the mesh, when the need exceeds what is available.
    """
    try:
        # equinox's filter_jit wraps JAX's compiled object as ``.compiled``
        analysis = getattr(compiled, "compiled", compiled).memory_analysis()
    except Exception:  # noqa: BLE001 - an account some backends do not give
        return None
    if analysis is None:
        return None
    need = int(analysis.temp_size_in_bytes + analysis.argument_size_in_bytes + analysis.output_size_in_bytes)
    if jax.default_backend() != "cpu":
        return need
    available = available_memory() if available is None else available
    if available is not None and need > available:
        mesh = model.mesh
        raise MemoryBudgetError(
            f"field 'mesh': the run at {mesh.nx}x{mesh.ny} needs about {need / 2**30:.3g} GiB of memory "
            f"(XLA's account of the compiled program: the Jacobian's {mesh.nx + 1} blocks of "
            f"{2 * (mesh.ny + 1)}x{2 * (mesh.ny + 1)}, the work arrays and the history buffers), more than the "
            f"{available / 2**30:.3g} GiB available; use a coarser mesh (fewer elements through the thickness "
            f"first: the memory grows with their square)")
    return need


@dataclasses.dataclass
class RunResult:
    """Host-side (NumPy) result of :func:`run`.

    Attributes:
        model: the model that was run.
        history: dict of per-row arrays (row 0 = initial state): ``time``, ``phase`` (index),
            ``phase_name``, ``newton_iters``, ``cutbacks`` (attempts before the accepted one),
            ``augmentations`` (AL), ``wall_s``, plus every observation.
        final: the last converged :class:`~jaxfric.loadpath.model.SimState`.
        simulation: the raw :class:`~jaxfric.loadpath.simulate.Simulation` (device arrays, full buffers).
        converged: True if the whole load path was completed.
        code: the :class:`~jaxfric.numerics.results.Result`.
        message: "" when converged, otherwise where and why the run stopped, and what to try.
        compile_s, wall_s: compilation time and solve time (s).
        cpu_s: process CPU time of the solve (s); with one XLA thread it equals ``wall_s`` on an idle
            machine and, unlike it, does not grow when other jobs share the cores or the run is paused.
        snapshots: with ``run(..., snapshot=fn)``, ``fn(model, state)`` as NumPy pytrees per history
            row (row 0: the initial state); empty otherwise.
    """

    model: StripModel
    history: dict
    final: SimState
    simulation: Simulation
    converged: bool
    code: Result
    message: str
    compile_s: float
    wall_s: float
    cpu_s: float
    snapshots: dict = dataclasses.field(default_factory=dict)


# Compiled programs by structure (shapes, static fields, options), the most recently used few.
_COMPILED: LRU = LRU(8)


def _compiled(model, newton, control, observe, snapshot, adaptive):
    """AOT-compile once per structure (shapes, static fields, options); values never recompile."""
    leaves, treedef = jax.tree_util.tree_flatten(model)
    key = (treedef, tuple((np.shape(x), str(getattr(x, "dtype", type(x)))) for x in leaves),
           newton, control, observe, snapshot, adaptive)
    return _COMPILED.get(key, lambda: _compile(model, newton, control, observe, snapshot, adaptive))


def _compile(model, newton, control, observe, snapshot, adaptive):
    """The compiled run program of ``model``'s structure. Every accepted step reports to the host (time
    stamps for the per-step wall time; the bar is drawn only when asked for)."""
    if adaptive:
        fn = eqx.filter_jit(lambda m: simulate(m, newton=newton, control=control, observe=observe,
                                               progress=True, snapshot=snapshot))
    else:
        fn = eqx.filter_jit(lambda m: simulate_fixed(m, newton=newton, observe=observe,
                                                     progress=True, snapshot=snapshot))
    return fn.lower(model).compile()


def run(model: StripModel, *, newton: NewtonOptions = NewtonOptions(),
        control: StepControl = StepControl(), observe: Callable = default_observe,
        progress: bool = True, adaptive: bool = True, raise_on_failure: bool = True,
        label: str = "", snapshot: Callable | None = None) -> RunResult:
    """Run ``model`` to the end of its load path.

    Compilation is timed apart from the solve. A progress bar on stderr shows steps, pseudo-time and
    Newton iterations when ``progress``. If the run stops early it raises :class:`SimulationError`
    whose ``result`` holds everything converged up to the failure (or returns it, with
    ``raise_on_failure=False``). ``snapshot(model, state) -> pytree`` (a module-level function) is
    evaluated at every accepted step and kept on the host in ``RunResult.snapshots``. ``adaptive``
    False runs the nominal steps without cutting (:func:`~jaxfric.loadpath.simulate.simulate_fixed`) instead
    of the adaptive controller (:func:`~jaxfric.loadpath.simulate.simulate`). A run that would need more memory
    than is available raises :class:`MemoryBudgetError` after compiling, before it starts
    (:func:`check_memory`).
    """
    for name, value, kind in (("model", model, StripModel), ("newton", newton, NewtonOptions),
                              ("control", control, StepControl)):
        if not isinstance(value, kind):
            raise ValueError(f"field '{name}' must be a {kind.__name__}, got {value!r}")
    for name, function in (("observe", observe), ("snapshot", snapshot)):
        if not (callable(function) or (name == "snapshot" and function is None)):
            raise ValueError(f"field '{name}' must be a function{' or None' if name == 'snapshot' else ''}, "
                             f"got {function!r}")
    t0 = time.perf_counter()
    compiled = _compiled(model, newton, control, observe, snapshot, adaptive)
    compile_s = time.perf_counter() - t0
    check_memory(compiled, model)
    with ProgressMonitor(total_time=model.n_phases, show=progress, label=label) as monitor:
        t1, c1 = time.perf_counter(), time.process_time()
        sim = jax.block_until_ready(compiled(model))
        wall_s, cpu_s = time.perf_counter() - t1, time.process_time() - c1
    result = _to_host(model, sim, monitor, compile_s, wall_s, cpu_s)
    if snapshot is not None:
        first = eqx.filter_jit(lambda m: snapshot(m, initial_state(m)))(model)
        snaps = {0: first, **monitor.snapshots}
        result.snapshots = {k: jax.tree_util.tree_map(np.asarray, v) for k, v in sorted(snaps.items())
                            if k < len(result.history["time"])}
    if not result.converged and raise_on_failure:
        raise SimulationError(result.message, result.code, result)
    return result


def _to_host(model, sim: Simulation, monitor, compile_s, wall_s, cpu_s) -> RunResult:
    h = sim.history
    n = int(h.n_rows)
    history = {
        "time": np.asarray(h.time[:n]),
        "phase": np.asarray(h.phase[:n]),
        "phase_name": np.array([model.phases[int(p)].name for p in np.asarray(h.phase[:n])]),
        "newton_iters": np.asarray(h.newton_iters[:n]),
        "cutbacks": np.asarray(h.cutbacks[:n]),
        "augmentations": np.asarray(h.augmentations[:n]),
    }
    if model.tools and model.contact is not None and model.contact.solver_stats:
        stats = np.asarray(h.solver_stats[:n])
        history.update({name: stats[:, k] for k, name in enumerate(model.contact.solver_stats)})
    history["wall_s"] = monitor.step_wall_times(n)
    for name, value in h.observed.items():
        history[name] = np.asarray(value[:n])
    code = Result(int(sim.code))
    final = jax.tree_util.tree_map(np.asarray, sim.final)
    converged = code == Result.SUCCESS
    message = ""
    if not converged:
        t = float(final.time)
        phase = model.phases[int(final.phase)].name
        r = float(sim.residual_norm)
        residual = f"{r:.3g} N/mm" if np.isfinite(r) else "non-finite"
        cuts = int(sim.pending_cuts)
        attempt = ("" if code == Result.MAX_STEPS else
                   f", while attempting t = {float(sim.failed_time):.10g} after {cuts} failed attempt"
                   f"{'s' if cuts != 1 else ''} of that step, last residual {residual}")
        message = (f"stopped after step {n - 1} at t = {t:.10g} (phase '{phase}'){attempt}: "
                   f"{describe(code)}. Results up to t = {t:.10g} are kept.")
    return RunResult(model=model, history=history, final=final, simulation=sim, converged=converged,
                     code=code, message=message, compile_s=compile_s, wall_s=wall_s, cpu_s=cpu_s)
