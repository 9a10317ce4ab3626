"""Tools of one structure evaluated as one batch.

A scene's tools are a static tuple, and a loop over them would trace each tool's pair evaluation
(projection, pair law, their derivatives) once per tool, so that the compiled program grows with the
number of tools. Tools whose pair part (:class:`PairTool`) has one structure (the kinds and order of
their primitives, and, where the evaluation reads it, whether the tool has friction and which law; the
side the sheet lies on is data) are instead stacked leaf by leaf and evaluated by one ``vmap`` over the
tools of the batch (:func:`map_pairs`). The Nine's five rollers and its two guide faces are two batches
where only the geometry is read, three where the friction term is (A to C carry friction, D and E not):
its program is 28 % smaller (``python experiments/bench_compile.py``; ``docs/results.md``,
compilation). A batch evaluates as many pairs per tool as its largest tool; a smaller tool's rows are
padded with copies of its last row and the copies' results dropped. The arithmetic of every pair is the
same as in a loop over the tools (``tests/test_pair_batches.py``: bit for bit).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .friction import FrictionLaw
from .tools import project_chain

__all__ = ["PairTool", "pair_part", "tool_batches", "stack", "map_pairs"]


class PairTool(eqx.Module):
    """The part of a :class:`~jaxfric.contact.rigid.RigidTool` that one pair's evaluation reads: its chain
    of primitives, the side of the chain the sheet lies on (``side``, () +1 right or -1 left, data, so
    that tools facing either way share a batch), its capture depth (mm), closing direction e_q ((2,))
    and friction law. Tools whose parts have one structure stack leaf by leaf into one batched
    ``PairTool`` (:func:`map_pairs`)."""

    primitives: tuple
    side: jax.Array
    d_capture: jax.Array
    drive: jax.Array
    friction: FrictionLaw | None
    frictional: bool = eqx.field(static=True)

    def projection(self, X, u, u_ref, q, q_ref):
        """The projection (:class:`jaxfric.contact.tools.Projection`) of one candidate node on the tool at
        position ``q`` (mm along ``drive``): node at reference position ``X`` with displacement ``u``
        ((2,), mm). The slip ``zeta_increment`` is the change of zeta since the slip reference configuration
        (``u_ref``, ``q_ref``), computed from the relative motion since then, not as a difference of two
        zetas (round-off, see :func:`jaxfric.contact.tools.project`)."""
        increment = (u - u_ref) - (q - q_ref) * self.drive
        return self.project(X, q_ref * self.drive, displacement=u_ref, increment=increment)

    def jacobian(self, pr) -> jax.Array:
        """(4, 3) d(n_x, n_y, g_N, zeta_increment) / d(u, q) of a :meth:`projection` ``pr``, in closed form.

        The projection depends on (u, q) through the point's motion relative to the tool, u - q e_q, so
        d/dq = -(d/du) e_q; and on the chosen primitive (piecewise constant, as the projection's own
        derivatives): d g_N = n . du, d n = curvature (t . du) t, d zeta = slip_rate (t . du). Zero for
        an open pair (its n and t are zero). Equal to ``jax.jacfwd`` of the projection to round-off
        (``tests/test_tools.py``), and differentiable itself (a derivative along the path differentiates
        it)."""
        n, t = pr.normal, pr.tangent
        bend = pr.curvature * t
        d_u = jnp.stack([bend * t[0], bend * t[1], n, pr.slip_rate * t])   # (4, 2)
        return jnp.concatenate([d_u, -(d_u @ self.drive)[:, None]], axis=1)

    def project(self, x, offset, displacement=None, increment=None):
        """:func:`jaxfric.contact.tools.project` on this tool's chain."""
        return project_chain(self.primitives, self.side, self.d_capture, x, offset, displacement, increment)


def pair_part(tool, friction: bool = True) -> PairTool:
    """The :class:`PairTool` of a :class:`~jaxfric.contact.rigid.RigidTool`; with ``friction`` False its
    geometry only (no friction law, frictionless), for evaluations that only project: tools that differ
    in their friction alone then share a batch."""
    g = tool.geometry
    frictional = tool.frictional and friction
    return PairTool(g.primitives, jnp.asarray(g.side, jnp.float64), g.d_capture, tool.drive,
                    tool.friction if frictional else None, frictional)


def _structure(part: PairTool):
    """Static, hashable: the tree structure and leaf shapes of a pair part."""
    leaves, treedef = jax.tree_util.tree_flatten(part)
    return treedef, tuple((jnp.shape(a), jnp.result_type(a)) for a in leaves)


def tool_batches(tools, only=None, key=None, friction: bool = True) -> list[tuple[int, ...]]:
    """Static: the tools (indices into ``tools``; only those in ``only`` where given) grouped by the
    structure of their pair part (:func:`pair_part` with ``friction``) and, where given, the hashable
    ``key(tool)``, in order of each group's first tool."""
    batches: dict = {}
    for k, tool in enumerate(tools):
        if only is None or k in only:
            group = (_structure(pair_part(tool, friction)), None if key is None else key(tool))
            batches.setdefault(group, []).append(k)
    return [tuple(b) for b in batches.values()]


def stack(trees):
    """One pytree whose leaves stack those of ``trees`` (of one structure) along a new leading axis."""
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *trees)


def _padded(tree, n: int):
    """Rows of every leaf (n_k, ...) repeated from the last up to ``n``."""
    def pad(a):
        extra = n - a.shape[0]
        return a if extra == 0 else jnp.concatenate([a, jnp.broadcast_to(a[-1:], (extra,) + a.shape[1:])])
    return jax.tree_util.tree_map(pad, tree)


def map_pairs(tools, pair_fn, tool_args, pair_args, only=None, friction: bool = True) -> list:
    """Evaluate ``pair_fn`` at every pair of every tool, one vectorised evaluation per batch of tools
    (:func:`tool_batches`).

    Args:
        tools: the scene's :class:`~jaxfric.contact.rigid.RigidTool` s (static structure).
        pair_fn: ``pair_fn(part, tool_values, pair_values) -> pytree`` for one pair, with ``part`` its
            tool's :class:`PairTool`.
        tool_args: ``k -> tool_values``: a pytree of tool k's own values (no pair axis).
        pair_args: ``k -> pair_values``: a pytree of (n_k, ...) arrays, one row per pair of tool k
            (n_k may differ between tools).
        only: the tools to evaluate (None: all).
        friction: ``pair_fn`` reads the tools' friction (False: their geometry only, so that tools that
            differ in their friction alone share a batch; :func:`pair_part`).

    Returns:
        per tool, ``pair_fn``'s outputs with a leading axis over its n_k pairs (None for a tool left out
        by ``only``).
    """
    out: list = [None] * len(tools)
    for batch in tool_batches(tools, only, friction=friction):
        if len(batch) == 1:   # one tool: no tool axis
            k = batch[0]
            part, values = pair_part(tools[k], friction), tool_args(k)
            out[k] = jax.vmap(lambda one: pair_fn(part, values, one))(pair_args(k))
            continue
        rows = [pair_args(k) for k in batch]
        sizes = [jax.tree_util.tree_leaves(r)[0].shape[0] for r in rows]
        part = stack([pair_part(tools[k], friction) for k in batch])
        values = stack([tool_args(k) for k in batch])
        pairs = stack([_padded(r, max(sizes)) for r in rows])
        result = jax.vmap(lambda p, t, a: jax.vmap(lambda one: pair_fn(p, t, one))(a))(part, values, pairs)
        for i, (k, n_k) in enumerate(zip(batch, sizes)):
            out[k] = jax.tree_util.tree_map(lambda a, i=i, n_k=n_k: a[i, :n_k], result)
    return out
