"""Public entry point: compile, run with a progress bar, and turn result codes into exceptions."""

from __future__ import annotations

import dataclasses
import time
from typing import Callable

import equinox as eqx
import jax
import numpy as np

from .newton import NewtonOptions
from .progress import ProgressMonitor
from .results import Result, SimulationError, describe
from .simulate import (Simulation, StepControl, StripModel, default_observe, simulate,
                       simulate_fixed)

__all__ = ["RunResult", "run"]


@dataclasses.dataclass
class RunResult:
    """Host-side (NumPy) result of :func:`run`.

    Attributes:
        model: the model that was run.
        history: dict of per-row arrays (row 0 = initial state): ``time``, ``phase`` (index),
            ``phase_name``, ``newton_iters``, ``cutbacks``, ``wall_s``, plus every observation.
        final: the last converged :class:`~jaxfric.simulate.SimState`.
        simulation: the raw :class:`~jaxfric.simulate.Simulation` (device arrays, full buffers).
        converged: True if the whole load path was completed.
        code: the :class:`~jaxfric.results.Result`.
        message: "" when converged, otherwise where and why the run stopped, and what to try.
        compile_s, wall_s: compilation time and solve time (s).
    """

    model: StripModel
    history: dict
    final: object
    simulation: Simulation
    converged: bool
    code: Result
    message: str
    compile_s: float
    wall_s: float


_COMPILED: dict = {}


def _compiled(model, newton, control, observe, progress, adaptive):
    """AOT-compile once per structure (shapes, static fields, options); values never recompile."""
    leaves, treedef = jax.tree_util.tree_flatten(model)
    key = (treedef, tuple((np.shape(x), str(getattr(x, "dtype", type(x)))) for x in leaves),
           newton, control, observe, progress, adaptive)
    if key not in _COMPILED:
        if adaptive:
            fn = eqx.filter_jit(lambda m: simulate(m, newton=newton, control=control, observe=observe,
                                                   progress=progress))
        else:
            fn = eqx.filter_jit(lambda m: simulate_fixed(m, newton=newton, observe=observe,
                                                         progress=progress))
        _COMPILED[key] = fn.lower(model).compile()
    return _COMPILED[key]


def run(model: StripModel, *, newton: NewtonOptions = NewtonOptions(),
        control: StepControl = StepControl(), observe: Callable = default_observe,
        progress: bool = True, adaptive: bool = True, raise_on_failure: bool = True,
        label: str = "") -> RunResult:
    """Run ``model`` to the end of its load path.

    Compilation is timed apart from the solve. A progress bar on stderr shows steps, pseudo-time and
    Newton iterations when ``progress``. If the run stops early it raises :class:`SimulationError`
    whose ``result`` holds everything converged up to the failure (or returns it, with
    ``raise_on_failure=False``).
    """
    t0 = time.perf_counter()
    compiled = _compiled(model, newton, control, observe, progress, adaptive)
    compile_s = time.perf_counter() - t0
    with ProgressMonitor(total_time=model.n_phases, show=progress, label=label) as monitor:
        t1 = time.perf_counter()
        sim = jax.block_until_ready(compiled(model))
        wall_s = time.perf_counter() - t1
    result = _to_host(model, sim, monitor if progress else None, compile_s, wall_s)
    if not result.converged and raise_on_failure:
        raise SimulationError(result.message, result.code, result)
    return result


def _to_host(model, sim: Simulation, monitor, compile_s, wall_s) -> RunResult:
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
    if monitor is not None:
        history["wall_s"] = monitor.step_wall_times(n)
    else:  # no per-step stamps: spread the measured solve time evenly
        history["wall_s"] = np.r_[0.0, np.full(n - 1, wall_s / max(n - 1, 1))]
    for name, value in h.observed.items():
        history[name] = np.asarray(value[:n])
    code = Result(int(sim.code))
    final = jax.tree_util.tree_map(np.asarray, sim.final)
    converged = code == Result.SUCCESS
    message = ""
    if not converged:
        t = float(final.time)
        phase = model.phases[int(final.phase)].name
        attempt = ("" if code == Result.MAX_STEPS else
                   f", while attempting t = {float(sim.failed_time):.6g}, last residual "
                   f"{float(sim.residual_norm):.3g} N/mm")
        message = (f"stopped after step {n - 1} at t = {t:.6g} (phase '{phase}'){attempt}: "
                   f"{describe(code)}. Results up to t = {t:.6g} are kept.")
    return RunResult(model=model, history=history, final=final, simulation=sim, converged=converged,
                     code=code, message=message, compile_s=compile_s, wall_s=wall_s)
