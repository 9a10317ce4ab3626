"""Global assembly of internal forces and of the block-tridiagonal tangent of a strip.

The element loops are ``vmap``s; gathering and scattering use static index arrays computed once per
mesh size with NumPy. The tangent is scattered directly into the blocks of a
:class:`~jaxfric.numerics.linalg.BlockTridiag` (one block per column of nodes), so no global sparse or dense
matrix is ever formed.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..numerics.devices import run_devices, traced_run_devices
from ..numerics.linalg import BlockTridiag
from .element import ElementGeometry, element_force, element_force_and_tangent, element_geometry
from .mesh import StripMesh, block_rows, connectivity

__all__ = ["Assembled", "mesh_geometry", "internal_force", "internal_force_and_tangent",
           "tangent_scatter_index", "element_chunk", "ELEMENT_CHUNK", "shared_trace"]


class Assembled(NamedTuple):
    """Result of one assembly at a displacement field.

    Attributes:
        f_int: (n_nodes, 2) internal nodal forces (N/mm).
        tangent: d f_int / d u as a BlockTridiag over the flattened dofs (node-major), or None.
        states: trial material states at every Gauss point (leading axes (n_el, gp), gp = 4 with the
            default 2 x 2 rule).
        tau: (n_el, gp, 3, 3) Kirchhoff stress (MPa).
        det_min: () smallest det F over all Gauss points and centroids (<= 0: inverted element).
        predictor: (n_el, n_alpha, 9) the enhanced parameters' predictor of the next Newton iterate, where
            the assembly was given one (:func:`internal_force_and_tangent`); else None.
        enhanced_gap: () largest nodal force the elements' own equations still move (``K_ua K_aa^-1 R_a``
            assembled; zero once alpha is condensed, N/mm), with a predictor; else None.
    """

    f_int: jax.Array
    tangent: BlockTridiag | None
    states: object
    tau: jax.Array
    det_min: jax.Array
    predictor: jax.Array | None = None
    enhanced_gap: jax.Array | None = None


@eqx.filter_jit
def mesh_geometry(mesh: StripMesh, thickness_points: int = 2) -> ElementGeometry:
    """Reference shape-function gradients and weights of every element of ``mesh``, with
    ``thickness_points`` Gauss points through each element's thickness (:func:`~jaxfric.fem.element.gauss_rule`).
    One compiled program where it is called outside one (some 50 one-primitive programs op by op)."""
    return element_geometry(mesh.nodes[mesh.elements], thickness_points)


@functools.cache
def tangent_scatter_index(nx: int, ny: int, order: int = 1) -> np.ndarray:
    """(n_el*(2n)^2,) positions of the entries of every (2n, 2n) element tangent (n nodes per element) in the
    flat storage ``concat(diag.ravel(), lower.ravel(), upper.ravel())`` of a BlockTridiag with nx+1 blocks
    (:attr:`~jaxfric.fem.mesh.StripMesh.block_size`, ``order`` node columns per block)."""
    m, nb = 2 * order * (ny + 1), nx + 1
    # Block and in-block row of each element dof (node-major, x then y).
    blocks, rows = block_rows(connectivity(nx, ny, order).ravel(), ny, order)
    n_el = nx * ny
    col = np.repeat(blocks.reshape(n_el, -1), 2, axis=1)
    row = rows.reshape(n_el, -1)
    bi, bj = col[:, :, None], col[:, None, :]
    ri, rj = row[:, :, None], row[:, None, :]
    in_block = ri * m + rj
    off_lower = nb * m * m
    off_upper = off_lower + (nb - 1) * m * m
    index = np.where(
        bi == bj, bi * m * m + in_block,
        np.where(bi > bj, off_lower + bj * m * m + in_block, off_upper + bi * m * m + in_block))
    return index.reshape(-1).astype(np.int64)


def _scatter_tangent(K_el: jax.Array, mesh: StripMesh) -> BlockTridiag:
    m, nb = mesh.block_size, mesh.num_blocks
    size = (3 * nb - 2) * m * m
    flat = jnp.zeros(size, K_el.dtype).at[tangent_scatter_index(mesh.nx, mesh.ny, mesh.order)].add(K_el.reshape(-1))
    diag = flat[: nb * m * m].reshape(nb, m, m)
    lower = flat[nb * m * m: (2 * nb - 1) * m * m].reshape(nb - 1, m, m)
    upper = flat[(2 * nb - 1) * m * m:].reshape(nb - 1, m, m)
    if mesh.padding.size:   # the padding column's unit springs (:func:`_padding_force`)
        _, pad_rows = mesh.block_rows(mesh.padding)
        diag = diag.at[-1, pad_rows.ravel(), pad_rows.ravel()].add(1.0)
    return BlockTridiag(lower=lower, diag=diag, upper=upper)


def _padding_force(mesh: StripMesh, u: jax.Array) -> jax.Array:
    """The force of unit springs (N/mm per mm) that hold the padding column of an ``order=2`` mesh at rest
    (:mod:`jaxfric.fem.mesh`): (n_nodes, 2), zero elsewhere. Its nodes are in no element, so its rows of
    the tangent are otherwise empty; with the springs they are identity rows and the Newton steps leave
    them at zero."""
    pad = mesh.padding
    return jnp.zeros_like(u).at[pad].set(u[pad]) if pad.size else jnp.zeros_like(u)


# Elements are processed in chunks of this many (up to twice as many: `_element_map`), vmapped inside a
# chunk: the per-element working set of the material derivatives then stays in cache. Measured on the
# 2-core CPU: one vmap over all 7200 elements of a 1200 x 6 strip costs 10.7 us per element, chunks of
# 128-600 cost 6.0-6.4, the same as a 300 x 3 strip, so the assembly cost grows linearly with the number
# of elements.
ELEMENT_CHUNK = 512
_CHUNK = contextvars.ContextVar("element_chunk", default=ELEMENT_CHUNK)


@contextlib.contextmanager
def element_chunk(size: int):
    """Trace the element loops with chunks of ``size`` elements (default :data:`ELEMENT_CHUNK`).

    A setting read when a program is traced, not when it runs. Under ``vmap`` over n members a chunk
    holds chunk x n element evaluations, so a batched sweep traces with chunks n times smaller to
    keep the working set of one chunk (:func:`jaxfric.loadpath.sweep.sweep`)."""
    token = _CHUNK.set(max(int(size), 1))
    try:
        yield
    finally:
        _CHUNK.reset(token)


def shared_trace(fn):
    """``fn`` jitted, so that its calls with the same argument structure within one traced program share
    a single trace: a loop's ``filter_eval_shape`` (the shapes of its carry) and the loop body that
    calls ``fn`` again (the element tangent was traced twice per run program, four times with the
    augmented Lagrangian; ``experiments/bench_compile.py``). XLA inlines the call: the runs compared
    before and after were bit-identical. The :func:`element_chunk` setting is part of the key, so a
    trace made under one setting is never reused under another.
    """
    @eqx.filter_jit
    def jitted(chunk, devices, *args):
        with element_chunk(chunk), run_devices(devices):
            return fn(*args)

    @functools.wraps(fn)
    def wrapper(*args):
        return jitted(_CHUNK.get(), traced_run_devices(), *args)

    return wrapper


def _element_map(fn, material, formulation, geo, u_el, states, *extra):
    """``fn`` over the elements in n // c equal chunks (c = :data:`ELEMENT_CHUNK` or the traced setting;
    at least one chunk), so a chunk holds fewer than 2c elements (all of them when there are fewer than c).

    The elements are padded (repeats of the last one, results dropped) to a whole number of equal chunks:
    ``lax.map`` evaluates a remainder that is not a whole chunk with a second copy of ``fn``, which
    doubled the element code in the compiled program (the Nine's 900 elements in chunks of 512: one
    chunk and a remainder of 388; now one chunk of 900). Rounding the number of chunks down, not up,
    matters too: two chunks of 450 made the Nine's run 13 % slower (a two-trip loop in the Newton loop,
    76 s against 67 s of solve on the 2-core CPU), one chunk of 900 runs as fast as before.
    ``extra``: further per-element arguments of ``fn`` (leading axis n_el).

    Under :func:`~jaxfric.numerics.devices.run_devices` each device maps ``fn`` over an equal share of the
    elements (the chunks counted per share) and the shares are gathered onto every device in one
    exchange, so that everything after the loop (the scatter into the global force and tangent, in the
    one-device order) runs replicated: the results equal the one-device loop's to round-off (the Nine's
    ``make run`` case to the last bit at the same XLA settings; ``jaxfric run`` gives each of its devices
    one thread, which moves the forces by round-off; ``tests/test_host_devices.py``). Gathering the elements' results
    costs one exchange per loop; scattering each share on its own device and summing the two global
    arrays costs two (the force and tangent, and the smallest determinant), and was no faster
    (docs/results.md, run time of the Nine test).
    """
    def one(args):
        return fn(material, formulation, *args)

    devices = traced_run_devices()
    parts = 1 if devices is None else len(devices)
    n = u_el.shape[0]
    share = -(-n // parts)                   # elements per device
    n_chunks = max(1, share // _CHUNK.get())
    size = -(-share // n_chunks)
    pad = parts * n_chunks * size - n
    xs = (geo.gradients(formulation), geo.dN_dX_center, geo.weight, u_el, states, *extra)
    if pad:
        xs = jax.tree_util.tree_map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]), xs)
    if devices is None:
        ys = jax.lax.map(one, xs, batch_size=size)
    else:
        def on_device(xs):
            first = jax.lax.axis_index("elements") * (n_chunks * size)
            mine = jax.tree_util.tree_map(lambda a: jax.lax.dynamic_slice_in_dim(a, first, n_chunks * size), xs)
            ys = jax.lax.map(one, mine, batch_size=size)
            return jax.tree_util.tree_map(lambda a: jax.lax.all_gather(a, "elements", tiled=True), ys)

        # Every device takes its share of the whole (replicated) arrays and returns the whole gathered result:
        # nothing outside the loop is split, so XLA partitions nothing else of the program, and every device
        # runs the rest on the same values (a share given by in_specs let XLA split the work around the loop
        # too: Lemke's pivoting then took different paths on the two devices and waited on each other). The
        # gathered results are the same on every device (check_vma off: shard_map cannot see it).
        replicated = jax.sharding.PartitionSpec()
        ys = jax.shard_map(on_device, mesh=jax.sharding.Mesh(np.asarray(devices), ("elements",)),
                           in_specs=(replicated,), out_specs=replicated, check_vma=False)(xs)
    return jax.tree_util.tree_map(lambda a: a[:n], ys) if pad else ys


def internal_force(mesh: StripMesh, material, formulation: str, geo: ElementGeometry,
                   u: jax.Array, states) -> Assembled:
    """Internal forces at displacement ``u`` (n_nodes, 2) from the converged ``states`` of the last step."""
    elements = mesh.elements
    f_el, (new_states, tau, det_min) = _element_map(
        element_force, material, formulation, geo, u[elements], states)
    f_int = _padding_force(mesh, u).at[elements].add(f_el)
    return Assembled(f_int, None, new_states, tau, jnp.min(det_min))


def internal_force_and_tangent(mesh: StripMesh, material, formulation: str, geo: ElementGeometry,
                               u: jax.Array, states, predictor: jax.Array | None = None) -> Assembled:
    """As :func:`internal_force`, plus the consistent tangent d f_int / d u (block-tridiagonal).

    ``predictor`` (n_el, n_alpha, 9), enhanced formulations only: the enhanced parameters follow the
    Newton iterate instead of the local solve (:func:`~jaxfric.fem.element.element_force_and_tangent`);
    ``f_int`` is then the condensed residual, and the result carries the next predictor and the
    elements' remaining share of the force (``enhanced_gap``)."""
    elements = mesh.elements
    extra = () if predictor is None else (predictor,)
    f_el, K_el, aux = _element_map(element_force_and_tangent, material, formulation, geo, u[elements], states,
                                   *extra)
    f_int = _padding_force(mesh, u).at[elements].add(f_el.reshape(elements.shape + (2,)))
    K = _scatter_tangent(K_el, mesh)
    new_states, tau, det_min = aux[:3]
    if predictor is None:
        return Assembled(f_int, K, new_states, tau, jnp.min(det_min))
    gap = jnp.max(jnp.abs(jnp.zeros_like(u).at[elements].add(aux[4])))
    return Assembled(f_int, K, new_states, tau, jnp.min(det_min), aux[3], gap)
