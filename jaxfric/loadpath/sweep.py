"""Batched parameter sweeps: many models of one structure as a single vmapped, compiled simulation.

    >>> models = [scenes.make("nine", "mu017", "penalty", {"mu": m}).model for m in mus]
    >>> out = sweep(models)                  # one compiled run, the members side by side
    >>> out.history(3)["drawing_force"]      # member 3, as the rows of RunResult.history

The members must share their structure (mesh size, phases, tools, which tools have friction, static
options): only array values may differ. Leaves that differ are batched; the others stay shared, so a
sweep over mu does not batch the mesh. Every member runs the adaptive load loop of
:func:`jaxfric.loadpath.simulate.simulate` with its own step sizes and cutbacks; under ``vmap`` the loop runs
until the last member has finished, and a finished member's state no longer changes.

Cost: every loop pass computes all members, and both branches of every ``lax.cond`` run. With the
nested loops of :func:`~jaxfric.loadpath.simulate.simulate` (a loop of attempts, each a Newton loop) a batched
attempt lasts as long as its slowest member's, and with 16 friction coefficients on the flat die
nearly every attempt paid some member's iteration limit: 31x one run. The penalty law therefore
sweeps with :func:`~jaxfric.loadpath.simulate.simulate_flat` (one Newton iteration per pass, each member's
step controller advancing on its own), whose number of passes is the largest member's total of
Newton iterations and attempts. That halved the flat-die sweep, but on the 2-core CPU a batched pass
still costs nearly one single pass per member (16 members: 18x one run; ``docs/results.md``, batched sweeps):
each member has its own state, so the element arithmetic, which a single run already evaluates as
one vectorised batch, is done 16 times over. The members are traced with element chunks n times
smaller (:func:`jaxfric.fem.assembly.element_chunk`) so that one chunk's working set stays in cache
(20 % off the 16-member sweep).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from ..fem.assembly import ELEMENT_CHUNK, element_chunk
from ..numerics.devices import run_devices
from ..numerics.linalg import on_gpu
from ..numerics.newton import NewtonOptions
from .controller import StepControl, max_steps
from .model import StripModel, default_observe
from .simulate import Simulation, simulate, simulate_flat

__all__ = ["SweepResult", "sweep", "stack_models", "default_chunk"]


def stack_models(models: Sequence[StripModel]):
    """The batched leaves of ``models``, their ``vmap`` axes and the shared structure: leaves that
    differ between members are stacked (axis 0), equal leaves are kept once (axis None). Raises
    ValueError naming the first member whose structure differs from the first one."""
    if len(models) == 0:
        raise ValueError("field 'models' must hold at least one model")
    dyn0, static0 = eqx.partition(models[0], eqx.is_array)
    treedef: Any = jax.tree_util.tree_structure(dyn0)
    dyns = [dyn0]
    for i, model in enumerate(models[1:], start=1):
        dyn, static = eqx.partition(model, eqx.is_array)
        if jax.tree_util.tree_structure(dyn) != treedef or not eqx.tree_equal(static, static0):
            raise ValueError(f"field 'models': member {i} differs in structure from member 0 (mesh size, "
                             f"phases, tools, friction on/off or static options); only values may differ")
        shapes = [(np.shape(a), np.asarray(a).dtype) for a in jax.tree_util.tree_leaves(dyn)]
        if shapes != [(np.shape(a), np.asarray(a).dtype) for a in jax.tree_util.tree_leaves(dyn0)]:
            raise ValueError(f"field 'models': member {i} has arrays of other shapes than member 0")
        dyns.append(dyn)

    # Flat lists of leaves: vmap's in_axes then need no knowledge of the model's classes.
    leaves = [jax.tree_util.tree_leaves(d) for d in dyns]
    values: list = []
    axes: list[int | None] = []
    for column in zip(*leaves):
        first = np.asarray(column[0])
        if all(np.array_equal(first, np.asarray(x), equal_nan=True) for x in column[1:]):
            values.append(column[0])
            axes.append(None)
        else:
            values.append(jnp.stack(column))
            axes.append(0)
    return values, axes, (treedef, static0)


@dataclasses.dataclass
class SweepResult:
    """Outcome of :func:`sweep`.

    Attributes:
        simulation: the batched :class:`~jaxfric.loadpath.simulate.Simulation` (leading axis: member).
        n_members: number of members.
        compile_s, wall_s: compilation and solve time of the whole sweep (s).
        n_devices: the devices the members were spread over.
    """

    simulation: Simulation
    n_members: int
    compile_s: float
    wall_s: float
    n_devices: int = 1

    def converged(self, i: int) -> bool:
        return int(self.simulation.code[i]) == 0

    def history(self, i: int) -> dict:
        """Member ``i``'s filled history rows: ``time``, ``phase``, ``newton_iters``, ``cutbacks``,
        ``cut_codes`` and every observation, as NumPy arrays (the columns of
        :attr:`jaxfric.loadpath.run.RunResult.history`)."""
        h = self.simulation.history
        n = int(h.n_rows[i])
        out = {"time": np.asarray(h.time[i, :n]), "phase": np.asarray(h.phase[i, :n]),
               "newton_iters": np.asarray(h.newton_iters[i, :n]), "cutbacks": np.asarray(h.cutbacks[i, :n]),
               "cut_codes": np.asarray(h.cut_codes[i, :n])}
        for name, value in h.observed.items():
            out[name] = np.asarray(value[i, :n])
        return out


def default_chunk(n_members: int) -> int:
    """The element chunk per member a sweep of ``n_members`` traces with by default: on a CPU
    ``ELEMENT_CHUNK // n`` (at least 16), the same working set per batched chunk as a single run's; on
    a GPU ``ELEMENT_CHUNK``, more work per launch (docs/results.md, batched sweeps)."""
    return ELEMENT_CHUNK if on_gpu() else max(ELEMENT_CHUNK // n_members, 16)


def sweep(models: Sequence[StripModel], *, newton: NewtonOptions = NewtonOptions(),
          control: StepControl = StepControl(), observe: Callable = default_observe,
          flat: bool | None = None, chunk: int | None = None,
          devices: Sequence[jax.Device] | None = None) -> SweepResult:
    """Run ``models`` (one structure, different values) as one vmapped adaptive simulation.

    ``observe`` must be a static (hashable) function, as for :func:`jaxfric.loadpath.run.run`. No progress bar
    (the members advance at different paces). ``flat``: one Newton iteration per loop pass
    (:func:`jaxfric.loadpath.simulate.simulate_flat`), so that no member waits for another's attempt; the
    default where the law allows it (penalty, or no tools). The results are the same either way.
    ``chunk``: elements per chunk of the element loop, per member (default :func:`default_chunk` of the
    members on one device).

    ``devices``: the devices the members are spread over (default ``jax.devices()``: every device of
    every process, with ``jax.distributed`` initialised beforehand on several hosts). With more than one,
    the members are split into equal blocks along a one-axis device mesh (``jax.sharding.Mesh``, axis
    ``members``) and each device runs the vmapped loop of its own block under ``jax.shard_map``: its own
    while loop, which ends when its slowest member does, with no communication between devices until the
    histories are gathered. A member count that the devices do not divide is padded with copies of the
    last member, whose results are dropped. One device: the plain vmapped program. Tested on several
    CPU devices of one process (``tests/test_sweep.py``), not across hosts.
    """
    if chunk is not None and (isinstance(chunk, bool) or not isinstance(chunk, int) or chunk < 1):
        raise ValueError(f"chunk must be a positive integer, got {chunk!r}")
    devices = list(jax.devices() if devices is None else devices)
    if not devices:
        raise ValueError("field 'devices' must name at least one device")
    values, axes, (treedef, static) = stack_models(models)
    # One history buffer for every member (their increments are data and may differ): the largest.
    control = dataclasses.replace(control, max_steps=max(max_steps(control, m.phases) for m in models))
    first = models[0]
    if flat is None:
        flat = first.contact is None or not first.tools or first.contact.one_newton_solve
    loop = simulate_flat if flat else simulate
    n_dev = min(len(devices), len(models))
    per_device = -(-len(models) // n_dev)

    def one(v):
        model = eqx.combine(jax.tree_util.tree_unflatten(treedef, v), static)
        return loop(model, newton=newton, control=control, observe=observe)

    batched = jax.vmap(one, in_axes=(axes,))
    if n_dev > 1:
        values, program = _sharded(batched, values, axes, devices[:n_dev], per_device * n_dev)
    else:
        program = batched
    t0 = time.perf_counter()
    # On a CPU, chunks n times smaller under vmap over n members (16 flat-die members: one batched
    # iteration 2x cheaper, docs/results.md).
    # The members, not a member's work, are split over the devices: each member runs on its own device
    # (run_devices(None), whatever the caller's setting).
    with element_chunk(default_chunk(per_device) if chunk is None else chunk), run_devices(None):
        compiled = jax.jit(program).lower(values).compile()
    compile_s = time.perf_counter() - t0
    t1 = time.perf_counter()
    sim = jax.block_until_ready(compiled(values))
    if n_dev > 1:
        sim = jax.tree_util.tree_map(lambda x: _gathered(x)[:len(models)], sim)
    return SweepResult(simulation=sim, n_members=len(models), compile_s=compile_s,
                       wall_s=time.perf_counter() - t1, n_devices=n_dev)


def _sharded(batched: Callable, values: list, axes: list, devices: list, n_padded: int):
    """``batched`` (vmapped over the members) as a program over a one-axis mesh of ``devices``: the
    batched leaves padded to ``n_padded`` members (copies of the last) and placed in blocks along the
    mesh, the shared leaves replicated."""
    mesh = Mesh(np.asarray(devices), ("members",))
    split, whole = NamedSharding(mesh, P("members")), NamedSharding(mesh, P())

    def pad(v, ax):
        if ax is None:
            return jax.device_put(v, whole)
        extra = n_padded - v.shape[0]
        if extra:
            v = jnp.concatenate([v, jnp.repeat(v[-1:], extra, axis=0)])
        return jax.device_put(v, split)

    placed = [pad(v, ax) for v, ax in zip(values, axes, strict=True)]
    specs = [P() if ax is None else P("members") for ax in axes]
    # Each device runs its block's loop alone: the replication checks of shard_map do not apply to a
    # while loop whose trip count differs between devices.
    program = jax.shard_map(batched, mesh=mesh, in_specs=(specs,), out_specs=P("members"), check_vma=False)
    return placed, program


def _gathered(x: jax.Array) -> np.ndarray:
    """A member-sharded result as one host array; with several processes, every process's blocks."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils
        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    return np.asarray(x)
