"""Tools evaluated in batches (jaxfric.contact.pair_batches): which tools share a batch, that a batch is
traced once however many tools it holds, and that it gives every pair what the tool's own evaluation
gives, values and derivatives, for tools facing either way and of different candidate counts (padded)."""

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxfric.contact.pair_batches import map_pairs, tool_batches
from jaxfric.contact.rigid import Move, RigidTool
from jaxfric.contact.tools import Tool, project
from jaxfric.scenes import _common as cm
from jaxfric.scenes import make


def test_the_nine_s_tools_batch_by_shape_and_friction():
    tools = make("nine", "mu017", "lcp_ssn", {"mesh": "60x2"}).model.tools
    names = [t.name for t in tools]
    assert names == ["A", "B", "C", "D", "E", "guide_top", "guide_bottom"]
    # Forces: A to C carry friction, D and E not; the guides face opposite ways and still share a batch.
    assert tool_batches(tools) == [(0, 1, 2), (3, 4), (5, 6)]
    # Geometry alone: the five rollers are one batch.
    assert tool_batches(tools, friction=False) == [(0, 1, 2, 3, 4), (5, 6)]
    assert tool_batches(tools, only=(1, 5), friction=False) == [(1,), (5,)]


def _faces():
    """The Nine's entry-guide faces (a straight face between two convex lips, sheet below the upper face
    and above the lower) and a roller, with different numbers of candidates."""
    upper, lower = cm.flat_faces(-6.0, -1.0, 1.05, -0.05, 0.5, 2.0)
    still = (Move(0.0, 0.0),)
    return (RigidTool("upper", upper, (0.0, -1.0), np.arange(7), still, 0.0),
            RigidTool("lower", lower, (0.0, 1.0), np.arange(3, 12), still, 0.0),
            RigidTool("roller", Tool.circle((0.0, -2.0), 2.0, seam=-0.5 * math.pi), (0.0, 1.0), np.arange(5), still,
                      0.0))


def test_a_batch_gives_each_tool_its_own_projection_and_derivatives():
    tools = _faces()
    assert tool_batches(tools) == [(0, 1), (2,)]
    rng = np.random.default_rng(3)
    points = jnp.asarray(np.stack([rng.uniform(-7.0, 0.5, 12), rng.uniform(-0.3, 1.3, 12)], axis=1))
    offsets = jnp.asarray(rng.normal(0.0, 0.05, (3, 2)))

    def pair_fn(part, offset, X):
        def local(x):
            pr = part.project(x, offset)
            return jnp.concatenate([pr.gap[None], pr.normal, pr.zeta[None]])
        return local(X), jax.jacfwd(local)(X)

    # One compiled program each (evaluated eagerly, every primitive would compile on its own).
    batched = jax.jit(lambda p, o: map_pairs(tools, pair_fn, lambda k: o[k],
                                             lambda k: p[np.asarray(tools[k].candidates)]))(points, offsets)

    @jax.jit
    def own(p, o):   # each tool projected on its own, its side a Python number
        def one(tool, x, offset):
            pr = project(tool.geometry, x, offset)
            return jnp.concatenate([pr.gap[None], pr.normal, pr.zeta[None]])
        return [(jax.vmap(lambda x, t=t, k=k: one(t, x, o[k]))(p[np.asarray(t.candidates)]),
                 jax.vmap(jax.jacfwd(lambda x, t=t, k=k: one(t, x, o[k])))(p[np.asarray(t.candidates)]))
                for k, t in enumerate(tools)]

    for k, ((value, jac), (value_own, jac_own)) in enumerate(zip(batched, own(points, offsets))):
        assert value.shape == (len(tools[k].candidates), 4)
        np.testing.assert_array_equal(value, value_own)
        np.testing.assert_array_equal(jac, jac_own)
    # The points near the faces do touch both sides' chains (the check would pass on open pairs alone).
    gaps = np.concatenate([np.asarray(batched[k][0][:, 0]) for k in range(2)])
    assert np.sum(np.abs(gaps) < 1.0) >= 6


def test_a_batch_traces_its_evaluation_once(monkeypatch):
    import jaxfric.contact.pair_batches as pb

    traced = []
    original = pb.project_chain

    def counted(*args, **kwargs):
        traced.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(pb, "project_chain", counted)
    still = (Move(0.0, 0.0),)
    rollers = tuple(RigidTool(f"r{k}", Tool.circle((3.0 * k, -2.0), 2.0 + k), (0.0, 1.0), np.arange(4 + k), still, 0.0)
                    for k in range(4))
    points = jnp.zeros((8, 2))

    def evaluate(tools):
        traced.clear()
        jax.make_jaxpr(lambda p: map_pairs(tools, lambda part, _, X: part.project(X, jnp.zeros(2)).gap,
                                           lambda k: (), lambda k: p[np.asarray(tools[k].candidates)]))(points)
        return len(traced)

    assert evaluate(rollers) == 1
    assert evaluate(rollers + _faces()) == 2   # the two faces, and the rollers with the faces' roller
