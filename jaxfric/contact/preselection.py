"""Pair pre-selection: per load step, only the candidate nodes that can reach a tool are evaluated.

A tool's candidate list is static and covers every node that may ever touch it (the Nine's rollers: the
whole face of the strip), while at any moment only the nodes near the tool can. At the start of each
step the ``capacity`` candidates of the tool nearest to it (:attr:`jaxfric.contact.rigid.RigidTool.capacity`,
static) are selected by a lower bound of their distance to the tool (:func:`distance_bound`), and the
step's Newton iterations evaluate their pairs only; the others enter every array as open pairs (no force,
no stiffness), as they would if evaluated.

That is exact while no left-out node can reach the tool within the step. With d_0 the smallest distance
bound of the left-out nodes at the step's start (the tool's ``clearance``) and delta the largest motion
of any candidate relative to the tool since then, the distance of every left-out node to the tool is
still above d_0 - delta (the distance is 1-Lipschitz in the point), so where

    d_0 - delta > 0

no left-out node has touched or crossed the tool's surface (:func:`holds`). A left-out node that lies
inside its tool at the step's start (a closed pair beyond the capacity) makes the clearance -inf, so
the guard fails. Each left-out node is then outside its tool, or deeper inside it than the capture depth
(open: the sheet has passed through the tool), where it was at the start, and open as its evaluation
would find it; the one case that evaluation would treat otherwise is such a deep node coming back within
the capture depth, which no scene's candidates do. Where the guard fails the attempt fails with
:attr:`~jaxfric.numerics.results.Result.PRESELECTION` and the step controller cuts the step; a capacity
too small for the contact zone shows the same way, and the advice names the field to raise.

The selection, the clearance and the guard are integers and comparisons of the converged state: they
carry no derivative, and the pairs' forces and their derivatives are those of the full evaluation.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ..numerics._checks import is_concrete
from ..numerics.tensor import safe_norm
from .pair_batches import PairTool, map_pairs, pair_part, stack, tool_batches
from .tools import Arc, Segment, Tool

__all__ = ["distance_bound", "tool_capacity", "select", "select_pairs", "gather", "expand", "holds",
           "complete_geometry", "PAIR_REACH", "PAYS_FROM"]

PAIR_REACH = 1.5   # mm: how far from a tool its capacity covers candidates [chosen: 15 of the Nine's 0.1 mm
                   # increments, and one and a half of the thickness of the Nine's and the bead's sheets]

# Pairs left out (candidates less capacities, over a model's tools) from which the scenes pre-select by default
# [chosen]. The selection adds about 2 s to a program's compilation (the Nine mu017 on 300 x 3: 10.6 s with it,
# 8.4 s without, the same runs), and saves about 0.1 to 0.2 us per left-out pair and Newton iteration (the pairs'
# geometry, experiments/bench_preselection.py: 0.44 ms for 5070 pairs left out on 1200 x 3, 1.78 ms for 10,168
# on 2400 x 3, 0.04 ms for 1244 on 300 x 3): over the 5,000 or so Newton iterations of a Nine run it repays its
# compilation from about 4000 left-out pairs on (docs/results.md, pair pre-selection).
PAYS_FROM = 4000


def _segment_distance(seg: Segment, y: jax.Array) -> jax.Array:
    d = seg.end - seg.start
    s = jnp.clip((y - seg.start) @ d / (d @ d), 0.0, 1.0)
    return safe_norm(y - seg.start - s * d)


def _arc_distance(arc: Arc, y: jax.Array) -> jax.Array:
    # The distance to the whole circle is at most the distance to any arc of it.
    return jnp.abs(safe_norm(y - arc.centre) - arc.radius)


def distance_bound(tool: Tool | PairTool, y: jax.Array) -> jax.Array:
    """() a lower bound of the Euclidean distance (mm) from the point ``y`` (2,), in the tool's frame
    (the point less the tool's translation), to the tool's chain: exact on segments, the distance to
    the supporting circle on arcs."""
    parts = [_segment_distance(p, y) if isinstance(p, Segment) else _arc_distance(p, y) for p in tool.primitives]
    return jnp.min(jnp.stack(parts))


def tool_capacity(tool: Tool, candidate_nodes, reach: float | None = None) -> int | None:
    """Static: how many candidates a tool's steps evaluate, or None for all of them.

    An estimate of the length of strip within ``reach`` (default :data:`PAIR_REACH`) of the chain: the
    chain's length, a convex arc counted for half a turn at most (a strip wraps a roller by less), plus
    the approach of a strip tangent to the largest arc at each end, 2 sqrt(2 R r + r^2), and 2 r; divided
    by the smallest spacing of consecutive candidates at rest, a tenth more for a strip shortened along
    its length, and 4 nodes. A contact zone longer than that shows as a failed guard
    (:data:`~jaxfric.numerics.results.Result.PRESELECTION`), never as a missed contact. None where that is
    not less than the number of candidates, or where the tool or the nodes are not concrete (traced).

    Args:
        tool: the tool at rest.
        candidate_nodes: (n_k, 2) the candidates' reference positions (mm), in order along the strip.
    """
    r = PAIR_REACH if reach is None else reach
    if not is_concrete((tool, candidate_nodes)):
        return None
    nodes = np.asarray(candidate_nodes, np.float64)
    n = nodes.shape[0]
    spacing = np.linalg.norm(np.diff(nodes, axis=0), axis=1)
    if not np.any(spacing > 0):
        return None
    h = float(np.min(spacing[spacing > 0]))
    length, radius = 0.0, 0.0
    for p in tool.primitives:
        if isinstance(p, Segment):
            length += float(p.length())
        else:
            arc = float(p.length())
            length += arc if p.concave else min(arc, math.pi * float(p.radius))
            radius = max(radius, float(p.radius))
    length += 2.0 * math.sqrt(2.0 * radius * r + r * r) + 2.0 * r
    capacity = int(math.ceil(1.1 * length / h)) + 4
    return capacity if capacity < n else None


def select(tool: Tool | PairTool, capacity: int, nodes_ref: jax.Array, u: jax.Array, offset: jax.Array, gap: jax.Array):
    """The ``capacity`` candidates nearest to the tool, by :func:`distance_bound`, and the clearance.

    Args:
        nodes_ref, u: (n_k, 2) the candidates' reference positions and displacements (mm).
        offset: (2,) the tool's translation from rest (mm).
        gap: (n_k,) the candidates' gaps in that state (mm; GAP_OPEN where a pair projects on no primitive).

    Returns:
        near: (capacity,) int32, indices into the candidates (nearest first);
        clearance: () the smallest distance bound among the others (mm); -inf where one of them lies
        inside the tool.
    """
    # (X - offset) + u: the small relative parts kept apart from the large coordinates, as `project` does.
    d = jax.lax.stop_gradient(jax.vmap(lambda X, v: distance_bound(tool, X + (v - offset)))(nodes_ref, u))
    value, order = jax.lax.top_k(-d, capacity + 1)
    near = order[:capacity].astype(jnp.int32)
    left_out = jnp.ones(d.shape, bool).at[near].set(False)
    inside = jnp.any(left_out & (jax.lax.stop_gradient(gap) <= 0.0))
    return near, jnp.where(inside, -jnp.inf, -value[capacity])


def select_pairs(tools, nodes_ref: jax.Array, u: jax.Array, q: jax.Array, gap: jax.Array,
                 every_pair: bool) -> tuple[tuple, tuple]:
    """Per tool, its selected candidates (or None: all) and its clearance (mm; inf where all), in the
    state of a step's start: displacements ``u`` (n_nodes, 2), tool positions ``q`` (n_t,), the pairs'
    gaps ``gap`` (m,). ``every_pair`` (static): the law gives every pair a force however far (a smoothed
    law), and every candidate is kept."""
    starts = np.cumsum([0] + [len(t.candidates) for t in tools])
    near: list = [None] * len(tools)
    clearance: list = [jnp.array(jnp.inf)] * len(tools)
    chosen = [] if every_pair else [k for k, t in enumerate(tools) if t.capacity is not None]

    def tool_args(k):
        idx = np.asarray(tools[k].candidates)
        return (pair_part(tools[k], friction=False), nodes_ref[idx], u[idx], q[k] * tools[k].drive,
                gap[starts[k]:starts[k + 1]])

    # Tools of one chain structure, capacity and candidate count select as one batch
    # (jaxfric.contact.pair_batches).
    batches = tool_batches(tools, chosen, key=lambda t: (t.capacity, len(t.candidates)), friction=False)
    for batch in batches:
        capacity = tools[batch[0]].capacity
        args = [tool_args(k) for k in batch]
        if len(batch) == 1:
            picked = [select(args[0][0], capacity, *args[0][1:])]
        else:
            sel, c = jax.vmap(lambda tool, *a: select(tool, capacity, *a))(*stack(args))
            picked = [(sel[i], c[i]) for i in range(len(batch))]
        for k, (sel_k, c_k) in zip(batch, picked):
            near[k], clearance[k] = sel_k, c_k
    return tuple(near), tuple(clearance)


def gather(near, values: jax.Array) -> jax.Array:
    """The rows ``near`` of a per-candidate array (all of them where ``near`` is None)."""
    return values if near is None else values[near]


def expand(near, tree, n: int, fill=0.0):
    """Per-candidate arrays (n, ...) from those of the selected candidates (capacity, ...): the rows
    ``near`` set, the others ``fill`` (an open pair's value); ``tree`` as it is where ``near`` is None."""
    if near is None:
        return tree
    return jax.tree_util.tree_map(
        lambda a: jnp.full((n,) + a.shape[1:], fill, a.dtype).at[near].set(a), tree)


def holds(step, u: jax.Array, q: jax.Array) -> jax.Array | None:
    """() bool: no candidate left out of the step's evaluation can have reached its tool (module doc):
    for every tool with a selection, clearance - delta > 0, with delta = max_a |u_a - u_a,n| + |q - q_n|
    over all candidates a (the triangle inequality's bound of their motion relative to the tool since
    the step's start: one reduction for all tools). None (static) where the step evaluates every pair.

    Args:
        step: the step's :class:`~jaxfric.contact.rigid.ContactStep`.
        u: (n_nodes, 2) displacements at the iterate (mm); q: (n_t,) tool positions (mm).
    """
    selected = [k for k in range(len(step.tools)) if step.selected(k) is not None]
    if not selected:
        return None
    moved = jnp.max(safe_norm(step.pair_displacements(u) - jnp.concatenate(step.u_ref), axis=-1))
    clearance = jnp.stack([step.clearance[k] for k in selected])
    delta = moved + jnp.abs(q[np.asarray(selected)] - step.q_ref[np.asarray(selected)])
    return jax.lax.stop_gradient(jnp.all(clearance - delta > 0.0))


def complete_geometry(step, nodes_ref: jax.Array, u: jax.Array, q: jax.Array, out: dict) -> dict:
    """The contact outputs ``out`` of a converged step (per pair: ``gap``, ``zeta``, ``normal``, ``slip``)
    with the geometry of the pairs the step left out projected at (``u`` (n_nodes, 2), ``q`` (n_t,)),
    as their evaluation would have given it: the state and the written results do not depend on the
    pre-selection. One projection per left-out pair and step, without derivatives."""
    selected = [k for k in range(len(step.tools)) if step.selected(k) is not None]
    if not selected:
        return out

    def pair_fn(tool, tool_values, pair_values):   # pair_values (X, u, u_ref), tool_values (q, q_ref)
        pr = tool.projection(*pair_values, *tool_values)
        return {"gap": pr.gap, "zeta": pr.zeta, "normal": pr.normal, "slip": pr.zeta_increment}

    def pair_args(k):
        idx = np.asarray(step.tools[k].candidates)
        return nodes_ref[idx], u[idx], step.u_ref[k]

    full = map_pairs(step.tools, pair_fn, lambda k: (q[k], step.q_ref[k]), pair_args, only=selected, friction=False)
    parts: dict[str, list] = {name: [] for name in ("gap", "zeta", "normal", "slip")}
    start = 0
    for k, tool in enumerate(step.tools):   # static
        n_k = len(tool.candidates)
        mine = {name: out[name][start:start + n_k] for name in parts}
        start += n_k
        if full[k] is not None:
            kept = jnp.zeros(n_k, bool).at[step.selected(k)].set(True)
            mine = {name: jnp.where(kept.reshape((n_k,) + (1,) * (v.ndim - 1)), v, full[k][name])
                    for name, v in mine.items()}
        for name in parts:
            parts[name].append(mine[name])
    return {**out, **{name: jnp.concatenate(v) for name, v in parts.items()}}
