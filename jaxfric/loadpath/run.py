"""Public entry point: compile, run in chunks with a progress bar, and turn result codes into exceptions.

:func:`run` advances the load path in chunks of accepted steps (:func:`jaxfric.loadpath.simulate.advance`),
returning to the host about once a second: the host keeps the new rows, draws the progress bar, hands a
partial result to the caller (who may write it to disk) and serves a stop request. The state between
chunks (:class:`Checkpoint`) is all a run needs to continue, bit for bit, in this process or another.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import os
import time
from collections.abc import Callable, Iterable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..numerics.devices import run_devices, traced_run_devices
from ..numerics.lru import LRU
from ..numerics.newton import NewtonOptions
from ..numerics.results import Result, SimulationError, band_widening, causes, describe
from .controller import StepControl, max_steps
from .model import SimState, StripModel, default_observe
from .progress import ProgressMonitor
from .simulate import Chunk, History, LoadPathState, Simulation, advance, begin, restart

__all__ = ["RunResult", "Record", "Checkpoint", "run", "extend_stroke", "MemoryBudgetError", "available_memory",
           "CHUNK_ROWS", "CHUNK_SECONDS"]

#: Rows of a chunk's buffers: the most accepted steps one chunk can take.
CHUNK_ROWS = 32
#: The wall time a chunk aims at (s): the host sees the run, and a stop request is served, about this often.
CHUNK_SECONDS = 2.0


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
            f"(XLA's account of the compiled program: the Jacobian's {mesh.num_blocks} blocks of "
            f"{mesh.block_size}x{mesh.block_size}, the work arrays and the history buffers), more than the "
            f"{available / 2**30:.3g} GiB available; use a coarser mesh (fewer elements through the thickness "
            f"first: the memory grows with their square)")
    return need


@dataclasses.dataclass
class Record:
    """The host's copy of a run's history rows, as the chunks bring them.

    Attributes:
        parts: per chunk, its rows: ``time``, ``phase``, ``newton_iters``, ``cutbacks``, ``cut_codes``,
            ``augmentations``, ``solver_stats`` (n, 3), ``predicted``, ``damping_energy``, ``wall_s``, and
            ``observed`` (a dict of the observations' rows), NumPy arrays.
        snapshots: history row -> ``snapshot(model, state)`` (NumPy), the rows kept.
        wall_s, cpu_s: solve time and process CPU time so far (s).
        band_widened: per widening of exact contact's proximity band (``Result.BAND_FULL``), the
            pseudo-time of the pending step and the new band (None: every candidate node).
    """

    parts: list = dataclasses.field(default_factory=list)
    snapshots: dict = dataclasses.field(default_factory=dict)
    wall_s: float = 0.0
    cpu_s: float = 0.0
    band_widened: list = dataclasses.field(default_factory=list)

    @property
    def n_rows(self) -> int:
        return sum(len(p["time"]) for p in self.parts)

    def columns(self) -> dict:
        """The rows of all parts, concatenated: the keys of a part."""
        if len(self.parts) > 1:  # keep one part: later calls are cheap
            first = self.parts[0]
            merged: dict[str, Any] = {k: np.concatenate([p[k] for p in self.parts]) for k in first
                                      if k != "observed"}
            merged["observed"] = {k: np.concatenate([p["observed"][k] for p in self.parts])
                                  for k in first["observed"]}
            self.parts = [merged]
        return self.parts[0]

    def add(self, chunk: Chunk, wall_s: float, cpu_s: float) -> int:
        """Append the rows of ``chunk`` (device or NumPy), sharing ``wall_s`` among them in proportion to
        their Newton iterations plus one (a step's attempts are not timed apart inside the compiled
        chunk). Returns the rows added."""
        h = jax.device_get(chunk.history)
        n = int(h.n_rows)
        first = int(chunk.first)
        if first != self.n_rows:
            raise ValueError(f"chunk starts at history row {first}, the record has {self.n_rows} rows")

        def rows(a):
            # A copy, not a view: a view would keep the chunk's whole buffer of CHUNK_ROWS rows alive (a run
            # of short chunks, one or two steps each, then holds 16 to 32 times its rows' memory).
            return np.array(a[:n])

        iters = rows(h.newton_iters)
        weight = iters + 1.0
        part = {"time": rows(h.time), "phase": rows(h.phase), "newton_iters": iters,
                "cutbacks": rows(h.cutbacks), "cut_codes": rows(h.cut_codes), "augmentations": rows(h.augmentations),
                "solver_stats": rows(h.solver_stats), "predicted": rows(h.predicted),
                "damping_energy": rows(h.damping_energy),
                "wall_s": wall_s * weight / weight.sum() if n else np.zeros(0),
                "observed": {k: rows(v) for k, v in h.observed.items()}}
        self.parts.append(part)
        if chunk.snapshots is not None:
            snaps = jax.device_get(chunk.snapshots)
            for i in range(n):
                self.snapshots[first + i] = jax.tree_util.tree_map(lambda a: np.array(a[i]), snaps)  # copies
        self.wall_s += wall_s
        self.cpu_s += cpu_s
        return n

    def keep_snapshots(self, rows: Iterable[int]) -> None:
        """Drop the snapshots of every row but ``rows`` and the last."""
        keep = set(int(r) for r in rows) | {self.n_rows - 1}
        self.snapshots = {k: v for k, v in self.snapshots.items() if k in keep}


@dataclasses.dataclass
class Checkpoint:
    """Everything a run needs to continue (:func:`run` with ``resume``): where its load path stands and
    the host's rows. ``path`` has NumPy leaves."""

    path: LoadPathState
    record: Record


@dataclasses.dataclass
class RunResult:
    """Host-side (NumPy) result of :func:`run`.

    Attributes:
        model: the model that was run.
        history: dict of per-row arrays (row 0 = initial state): ``time``, ``phase`` (index),
            ``phase_name``, ``newton_iters``, ``cutbacks`` (attempts before the accepted one),
            ``cut_codes`` (their result codes, a bit mask: :func:`jaxfric.numerics.results.causes`),
            ``augmentations`` (AL), ``predicted`` (1 where the accepted attempt started from the secant
            prediction), ``damping_energy`` (N mm per mm: what the stabilised attempt's damper took, 0
            in every other step), ``wall_s`` (a chunk's wall time shared among its steps in proportion
            to their Newton iterations plus one), plus every observation.
        final: the last converged :class:`~jaxfric.loadpath.model.SimState`.
        simulation: the :class:`~jaxfric.loadpath.simulate.Simulation` (NumPy: the history as one
            buffer, the final state, the result code, the failed attempt's time and residual).
        converged: True if the whole load path was completed.
        code: the :class:`~jaxfric.numerics.results.Result` (``STOPPED`` when a stop request ended it,
            ``CONTINUE`` for the partial result of a run still going).
        message: "" when converged, otherwise where and why the run stopped, and what to try.
        compile_s, wall_s: compilation time and solve time (s); a resumed run's solve time includes
            the solve before the stop.
        cpu_s: process CPU time of the solve (s); with one XLA thread it equals ``wall_s`` on an idle
            machine and, unlike it, does not grow when other jobs share the cores or the run is paused.
        snapshots: with ``run(..., snapshot=fn)``, ``fn(model, state)`` as NumPy pytrees per history
            row kept (row 0: the initial state); empty otherwise.
        checkpoint: what :func:`run` needs to continue this run (``resume``).
        devices: how many devices the run's work was split over (:func:`split_over`; 1: not split).
        band_widened: ``Record.band_widened``: where exact contact's proximity band grew, and to what
            (``model`` has the last band).
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
    checkpoint: Checkpoint | None = None
    devices: int = 1
    band_widened: tuple = ()


# Compiled programs by structure (shapes, static fields, options), the most recently used few.
_COMPILED: LRU = LRU(8)


def split_over(model: StripModel) -> tuple | None:
    """The devices a run of ``model`` traced now splits its work over: the
    :func:`~jaxfric.numerics.devices.run_devices` setting in effect, but none where the model's contact is
    Lemke's, whose pivoting calls the host (``jax.pure_callback``): in a program split over two host
    devices the callback ran on one of them, and the Nine with ``lcp_lemke`` stopped, each device waiting
    on the other (``tests/test_host_devices.py``, slow)."""
    if getattr(getattr(model, "contact", None), "solver", None) == "lemke":
        return None
    return traced_run_devices()


def _compiled(model, newton, control, observe, snapshot):
    """AOT-compile once per structure (shapes, static fields, options, the devices its work is split over:
    :func:`~jaxfric.numerics.devices.run_devices`); values never recompile, nor do
    the nominal increments or ``control.max_steps``, which the programs take as data."""
    leaves, treedef = jax.tree_util.tree_flatten(model)
    program_control = dataclasses.replace(control, max_steps=None)
    key = (treedef, tuple((np.shape(x), str(getattr(x, "dtype", type(x)))) for x in leaves),
           newton, program_control, observe, snapshot, split_over(model))

    def compile_split():
        with run_devices(split_over(model)):
            return _compile(model, newton, program_control, observe, snapshot)

    return _COMPILED.get(key, compile_split)


def _compile(model, newton, control, observe, snapshot):
    """The two compiled programs of ``model``'s structure: the start of its load path (with history row
    0) and one chunk (:func:`~jaxfric.loadpath.simulate.advance`), each taking the run's most accepted
    steps as its last argument. Neither calls the host.

    XLA compiles the start's program on a second thread (it releases the GIL) while this one traces the
    chunk's, which needs only the shapes of the start's output: the tracing is Python, on one core, and the
    start's compilation leaves the critical path (docs/results.md, compilation)."""
    start = eqx.filter_jit(lambda m, r: begin(m, control=control, observe=observe, snapshot=snapshot, max_steps=r))
    step = eqx.filter_jit(lambda m, p, k, r: advance(m, p, k, size=CHUNK_ROWS, newton=newton, control=control,
                                                     observe=observe, snapshot=snapshot, max_steps=r))
    rows = jnp.array(1, jnp.int32)
    lowered = start.lower(model, rows)
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        compiling = pool.submit(lowered.compile)
        shapes, _ = lowered.postprocess(lowered.lowered.out_info)   # the start's path, shapes only
        leaves, treedef = jax.tree_util.tree_flatten(shapes)
        examples = [_example(x) if isinstance(x, jax.ShapeDtypeStruct) else x for x in leaves]
        if any(e is None for e in examples):   # a type no host array gives: the start's own output
            path, _ = compiling.result()(model, rows)
        else:
            path = jax.tree_util.tree_unflatten(treedef, examples)
        chunk = step.lower(model, path, jnp.array(1, jnp.int32), rows)
        return compiling.result(), chunk.compile()


def _example(shape: jax.ShapeDtypeStruct):
    """An array of ``shape``'s type made on the host without compiling (a weak type from a Python number), or
    None where that does not give the type."""
    if not shape.weak_type:
        return np.zeros(shape.shape, shape.dtype)
    if shape.shape != ():
        return None
    x = jnp.asarray(np.zeros((), shape.dtype).item())
    return x if x.dtype == shape.dtype and x.weak_type else None


def _next_limit(rows: int, seconds: float, limit: int) -> int:
    """The next chunk's step limit: about :data:`CHUNK_SECONDS` at the last chunk's pace, at most
    doubling."""
    if rows == 0 or seconds <= 0.0:
        return min(2 * limit, CHUNK_ROWS)
    return int(np.clip(round(CHUNK_SECONDS * rows / seconds), 1, min(2 * limit, CHUNK_ROWS)))


def run(model: StripModel, *, newton: NewtonOptions = NewtonOptions(),
        control: StepControl = StepControl(), observe: Callable = default_observe,
        progress: bool = True, raise_on_failure: bool = True, label: str = "",
        snapshot: Callable | None = None, keep_snapshots: Callable | None = None,
        resume: Checkpoint | None = None, on_chunk: Callable | None = None,
        stop: Callable | None = None) -> RunResult:
    """Run ``model`` to the end of its load path, with adaptive steps, in chunks.

    Compilation is timed apart from the solve. A progress bar on stderr shows steps, pseudo-time and
    Newton iterations when ``progress``. If the run stops early it raises :class:`SimulationError`
    whose ``result`` holds everything converged up to the failure (or returns it, with
    ``raise_on_failure=False``). A run that would need more memory than is available raises
    :class:`MemoryBudgetError` after compiling, before it starts (:func:`check_memory`).

    Args:
        model, newton, control: the model and the solver's settings.
        observe: static ``observe(model, state) -> dict`` of arrays recorded at every accepted step.
        snapshot: static ``snapshot(model, state) -> dict`` of arrays (a module-level function or a
            hashable module), kept on the host in ``RunResult.snapshots``.
        keep_snapshots: ``keep_snapshots(history) -> rows``: after every chunk only the snapshots of
            these rows (and the last row) are kept, ``history`` being the rows so far as in
            ``RunResult.history``; None keeps every row's (host memory growing with the steps: 0.84 MB
            per row on the Nine's 1200 x 3 six-node mesh). The command line and the studies keep the
            instants' rows (:class:`jaxfric.io.instants.InstantRows`), all that ``contact.npz`` needs.
        resume: a :class:`Checkpoint` of a run of a model with this structure and values (a stopped
            or partial run's ``RunResult.checkpoint``, or one read back from disk): the run continues
            from it and returns the whole run's result, as the run that never stopped would (at the
            proximity band it had widened to).
        on_chunk: ``on_chunk(partial)`` after every chunk, ``partial()`` giving the
            :class:`RunResult` so far (code ``CONTINUE`` while the run goes on).
        stop: ``stop() -> bool``, asked before every chunk: True ends the run there, with code
            ``Result.STOPPED`` (a stop request: the result is resumable).

    Exact contact's proximity band (``Complementarity.band``) grows where a step needs more: a run that
    ends a chunk with ``Result.BAND_FULL`` (:func:`jaxfric.loadpath.controller.band_full`) goes on with the
    band doubled (:meth:`~jaxfric.contact.formulations.Complementarity.widened`), compiled anew, from the
    pending step; ``RunResult.band_widened`` says where.
    """
    for name, value, kind in (("model", model, StripModel), ("newton", newton, NewtonOptions),
                              ("control", control, StepControl)):
        if not isinstance(value, kind):
            raise ValueError(f"field '{name}' must be a {kind.__name__}, got {value!r}")
    for name, function in (("observe", observe), ("snapshot", snapshot), ("keep_snapshots", keep_snapshots),
                           ("on_chunk", on_chunk), ("stop", stop)):
        if not (callable(function) or (name != "observe" and function is None)):
            raise ValueError(f"field '{name}' must be a function{' or None' if name != 'observe' else ''}, "
                             f"got {function!r}")
    if resume is not None and not isinstance(resume, Checkpoint):
        raise ValueError(f"field 'resume' must be a Checkpoint (RunResult.checkpoint), got {resume!r}")
    if resume is not None and resume.record.band_widened:
        model = _with_band(model, resume.record.band_widened[-1][1])
    t0 = time.perf_counter()
    start, step = _compiled(model, newton, control, observe, snapshot)
    compile_s = time.perf_counter() - t0
    rows_max = jnp.array(max_steps(control, model.phases), jnp.int32)
    check_memory(step, model)
    if resume is None:
        path, chunk = start(model, rows_max)
        record = Record()
        record.add(chunk, 0.0, 0.0)
    else:
        path = jax.tree_util.tree_map(jnp.asarray, resume.path)
        record = dataclasses.replace(resume.record, parts=list(resume.record.parts),
                                     snapshots=dict(resume.record.snapshots),
                                     band_widened=list(resume.record.band_widened))
    code = Result(int(path.ctrl.code))
    limit = 4
    with ProgressMonitor(total_time=model.n_phases, show=progress, label=label) as monitor:
        while code == Result.CONTINUE:
            if stop is not None and stop():
                code = Result.STOPPED
                break
            t1, c1 = time.perf_counter(), time.process_time()
            path, chunk = step(model, path, jnp.array(limit, jnp.int32), rows_max)
            chunk = jax.device_get(chunk)
            wall, cpu = time.perf_counter() - t1, time.process_time() - c1
            rows = record.add(chunk, wall, cpu)
            if keep_snapshots is not None and snapshot is not None:
                record.keep_snapshots(keep_snapshots(_history(model, record)))
            code = Result(int(path.ctrl.code))
            last = record.parts[-1]
            if rows:
                monitor.update(record.n_rows - 1, float(last["time"][-1]), int(last["newton_iters"][-1]),
                               int(last["cutbacks"][-1]))
            limit = _next_limit(rows, wall, limit)
            if code == Result.BAND_FULL:
                t1 = time.perf_counter()
                law = None if model.contact is None else model.contact.widened(model.tools)
                if law is None:
                    raise RuntimeError("the run ended a chunk with BAND_FULL, but its contact has no band to widen")
                model = eqx.tree_at(lambda m: m.contact, model, law)
                start, step = _compiled(model, newton, control, observe, snapshot)
                compile_s += time.perf_counter() - t1
                check_memory(step, model)
                record.band_widened.append((float(path.ctrl.failed_t), law.proximity_band))
                monitor.note(f"exact contact's proximity band widened {band_widening(*record.band_widened[-1])} "
                             f"(Result.BAND_FULL)")
                path = eqx.tree_at(lambda p: p.ctrl.code, path, jnp.asarray(Result.CONTINUE, jnp.int32))
                code = Result.CONTINUE
            if on_chunk is not None:
                now = (path, record)
                on_chunk(lambda: _result(model, *now, Result(int(now[0].ctrl.code)), compile_s))
    result = _result(model, path, record, code, compile_s)
    if not result.converged and raise_on_failure:
        raise SimulationError(result.message, result.code, result)
    return result


def extend_stroke(checkpoint: Checkpoint, model: StripModel, scale: float, *,
                  control: StepControl = StepControl()) -> Checkpoint:
    """``checkpoint`` continued on ``model``, whose last phase is the checkpoint's stretched ``1 / scale``
    times (a longer stroke: S_new = S_old / scale, 0 < scale <= 1), the rest of the load path unchanged.

    The last phase's pseudo-times k + s (k its index, s in [0, 1]) become k + s scale, in the history
    rows and the state, so that every row keeps its displacement; the step controller restarts at the
    state with the nominal increment (:func:`jaxfric.loadpath.simulate.restart`). The continued run is the
    longer run from that state on, not bit for bit the longer run from the start: the increments it
    took before differ from the longer schedule's by round-off, and the controller restarts fresh.

    Raises:
        ValueError: ``scale`` not in (0, 1] (a shorter stroke cannot continue a run).
    """
    if not 0.0 < float(scale) <= 1.0:
        raise ValueError(f"field 'scale' must be in (0, 1] (the new stroke at least the old one), got {scale!r}")
    last = model.n_phases - 1
    record = checkpoint.record
    cols = dict(record.columns())
    time = np.asarray(cols["time"], np.float64)
    cols["time"] = np.where(time > last, last + (time - last) * float(scale), time)
    record = dataclasses.replace(record, parts=[cols], snapshots=dict(record.snapshots))
    path = jax.tree_util.tree_map(jnp.asarray, checkpoint.path)
    t = float(path.state.time)
    t_new = last + (t - last) * float(scale) if t > last else t
    control = dataclasses.replace(control, max_steps=max_steps(control, model.phases))  # needs the increments' values
    path = eqx.filter_jit(lambda m, p, s: restart(m, p, s, control=control))(model, path, t_new)
    return Checkpoint(path=jax.device_get(path), record=record)


def _with_band(model: StripModel, band: int | None) -> StripModel:
    """``model`` with its exact contact's proximity band ``band`` (a resumed run's widened band).

    Raises:
        ValueError: ``model`` has no contact with a proximity band, naming the field.
    """
    if model.contact is None:
        raise ValueError("field 'contact': the resumed run widened exact contact's proximity band, but this "
                         "model has no contact")
    return eqx.tree_at(lambda m: m.contact, model, model.contact.with_band(band))


def _history(model, record: Record) -> dict:
    """``RunResult.history`` of the rows in ``record``."""
    cols = record.columns()
    history = {k: cols[k] for k in ("time", "phase")}
    history["phase_name"] = np.array([p.name for p in model.phases])[cols["phase"]]
    history.update({k: cols[k] for k in ("newton_iters", "cutbacks", "cut_codes", "augmentations", "predicted",
                                         "damping_energy")})
    if model.tools and model.contact is not None and model.contact.solver_stats:
        history.update({name: cols["solver_stats"][:, k] for k, name in enumerate(model.contact.solver_stats)})
    history["wall_s"] = cols["wall_s"]
    history.update(cols["observed"])
    return history


def _result(model, path: LoadPathState, record: Record, code: Result, compile_s: float) -> RunResult:
    """The :class:`RunResult` of the rows in ``record`` with the load path standing at ``path``."""
    path = jax.device_get(path)
    history = _history(model, record)
    cols = record.columns()
    n = record.n_rows
    final = path.state
    converged = code == Result.SUCCESS
    ctrl = path.ctrl
    message = ""
    if not converged:
        t = float(final.time)
        phase = model.phases[int(final.phase)].name
        where = f"step {n - 1} at t = {t:.10g} (phase '{phase}')"
        if code == Result.CONTINUE:
            message = f"in progress: {where}"
        elif code == Result.STOPPED:
            message = f"stopped on request after {where}; results up to there are kept and the run can be resumed"
        else:
            r = float(ctrl.r_norm)
            residual = f"{r:.3g} N/mm" if np.isfinite(r) else "non-finite"
            cuts = int(ctrl.cuts)
            crawl = f", its last {int(ctrl.n_crawl)} steps each at the smallest increment"
            attempt = ("" if code == Result.MAX_STEPS else crawl if code == Result.STALLED else
                       f", while attempting t = {float(ctrl.failed_t):.10g} after {cuts} failed attempt"
                       f"{'s' if cuts != 1 else ''} of that step ({', '.join(causes(int(ctrl.cut_codes)))}), "
                       f"last residual {residual}")
            message = (f"stopped after {where}{attempt}: {describe(code)}. Results up to t = {t:.10g} "
                       f"are kept.")
    buffers = History(time=cols["time"], phase=cols["phase"], newton_iters=cols["newton_iters"],
                      cutbacks=cols["cutbacks"], cut_codes=cols["cut_codes"], augmentations=cols["augmentations"],
                      solver_stats=cols["solver_stats"], predicted=cols["predicted"],
                      damping_energy=cols["damping_energy"], observed=cols["observed"],
                      n_rows=jnp.asarray(n, jnp.int32))
    simulation = Simulation(history=buffers, final=final, code=jnp.asarray(code, jnp.int32), failed_time=ctrl.failed_t,
                            residual_norm=ctrl.r_norm, pending_cuts=ctrl.cuts)
    snapshots = {k: v for k, v in sorted(record.snapshots.items()) if k < n}
    checkpoint = Checkpoint(path=path, record=dataclasses.replace(record, parts=list(record.parts),
                                                                  snapshots=dict(record.snapshots),
                                                                  band_widened=list(record.band_widened)))
    return RunResult(model=model, history=history, final=final, simulation=simulation, converged=converged,
                     code=code, message=message, compile_s=compile_s, wall_s=record.wall_s, cpu_s=record.cpu_s,
                     snapshots=snapshots, checkpoint=checkpoint, devices=len(split_over(model) or (None,)),
                     band_widened=tuple(record.band_widened))
