"""Rigid tools: closest-point projection on circles, grooves, segments and the benchmark chains, against
closed forms and brute force; the choice of primitive at junctions and corners; objectivity under tool
translation; derivatives against finite differences (forward, reverse, dot-product test); NaN-freedom at
the kinks (arc centre, open pairs); vmap, jit without retracing; construction checks."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfric.contact.tools import GAP_OPEN, Arc, Circle, Segment, Tool, chain_length, project, tool_outline

RNG_SEED = 20240613
ZERO2 = np.zeros(2)

# ---------------------------------------------------------------------------------------------------
# Benchmark tools, built from the spec's data (section 3: bead lower clamp die; section 5: blankholder).


def bead_lower_die():
    """Line (-90, 0) -> (-40, 0), end arcs r_e = 2, sheet above: walked left to right, sheet on the left."""
    return Tool((Arc((-90.0, -2.0), 2.0, math.pi, 0.5 * math.pi),
                 Segment((-90.0, 0.0), (-40.0, 0.0)),
                 Arc((-40.0, -2.0), 2.0, 0.5 * math.pi, 0.0)), normal_side="left")


def blankholder_upper_die(t=1.0, r=3.0, r_groove=7.25, land=25.0, r_edge=2.0):
    """Spec section 5, shape 1: edge arc, land, fillet, concave groove, fillet, land, edge arc; sheet below."""
    x_g = math.sqrt((r_groove + r) ** 2 - r**2)
    c_fillet = np.array([x_g, t + r])
    t_right = np.array([0.0, t]) + r_groove * (c_fillet - np.array([0.0, t])) / (r_groove + r)
    t_left = t_right * np.array([-1.0, 1.0])
    a_groove_left = math.atan2(t_left[1] - t, t_left[0])  # in (pi/2, pi)
    a_groove_right = math.atan2(t_right[1] - t, t_right[0])  # in (0, pi/2)
    a_fillet_left = math.atan2(t_left[1] - t - r, t_left[0] + x_g) + 2 * math.pi  # in (3pi/2, 2pi)
    a_fillet_right = math.atan2(t_right[1] - t - r, t_right[0] - x_g)  # in (pi, 3pi/2), mod 2 pi
    a_fillet_right = a_fillet_right % (2 * math.pi)
    xe = x_g + land
    return Tool((Arc((-xe, t + r_edge), r_edge, math.pi, 1.5 * math.pi),
                 Segment((-xe, t), (-x_g, t)),
                 Arc((-x_g, t + r), r, 1.5 * math.pi, a_fillet_left),
                 Arc((0.0, t), r_groove, a_groove_left, a_groove_right, concave=True),
                 Arc((x_g, t + r), r, a_fillet_right, 1.5 * math.pi),
                 Segment((x_g, t), (xe, t)),
                 Arc((xe, t + r_edge), r_edge, 1.5 * math.pi, 2.0 * math.pi)), normal_side="right")


def blankholder_lower_tool(H=9.0, R=6.0, x_far=140.0):
    """Land, flank, nose (convex, 180 -> 0 deg), flank, land; sheet above: walked left to right, left."""
    return Tool((Segment((-x_far, -H), (-R, -H)),
                 Segment((-R, -H), (-R, -R)),
                 Arc((0.0, -R), R, math.pi, 0.0),
                 Segment((R, -R), (R, -H)),
                 Segment((R, -H), (x_far, -H))), normal_side="left")


def walk(tool, s):
    """Point and sheet-side normal at arc length s from the chain's start, written independently of
    `project` from the spec's definitions: convex arcs have outward normals, concave ones inward."""
    side = 1.0 if tool.normal_side == "right" else -1.0
    last = len(tool.primitives) - 1
    for k, prim in enumerate(tool.primitives):
        if isinstance(prim, Segment):
            a, b = np.asarray(prim.start), np.asarray(prim.end)
            length = np.linalg.norm(b - a)
            if s <= length or k == last:
                d = (b - a) / length
                return a + s * d, side * np.array([d[1], -d[0]])
        else:
            c, radius = np.asarray(prim.centre), float(prim.radius)
            a0, a1 = float(prim.angle_start), float(prim.angle_end)
            length = radius * abs(a1 - a0)
            if s <= length or k == last:
                angle = a0 + np.sign(a1 - a0) * s / radius
                radial = np.array([np.cos(angle), np.sin(angle)])
                return c + radius * radial, (-radial if prim.concave else radial)
        s -= length


# ---------------------------------------------------------------------------------------------------
# Compiled helpers: the tool is an argument, so new dimensions reuse the compiled code.

# Every point set is padded to one batch size, so each tool structure compiles once.
BATCH = 2048
project_batch = jax.jit(jax.vmap(project, in_axes=(None, 0, None)))


def project_many(tool, xs, offset=ZERO2):
    """`project` on the points xs (k, 2), k <= BATCH, as numpy arrays."""
    xs = np.atleast_2d(np.asarray(xs, dtype=np.float64))
    padded = np.zeros((BATCH, 2))
    padded[: len(xs)] = xs
    out = project_batch(tool, jnp.asarray(padded), jnp.asarray(offset, dtype=jnp.float64))
    return jax.tree.map(lambda a: np.asarray(a[: len(xs)]), out)


def project_one(tool, x, offset=ZERO2):
    return jax.tree.map(lambda a: a[0], project_many(tool, [x], offset))



def flat(tool, x, offset):
    """(gap, normal, tangent, zeta, closest) as one vector of 8 floats."""
    p = project(tool, x, offset)
    return jnp.concatenate([p.gap[None], p.normal, p.tangent, p.zeta[None], p.closest])


def flat_args(args):
    """Same, from one pytree (tool, x, offset): a single differentiable argument."""
    return flat(*args)


jvp_flat = jax.jit(lambda args, v: jax.jvp(flat_args, (args,), (v,))[1])
vjp_flat = jax.jit(lambda args, w: jax.vjp(flat_args, args)[1](w)[0])
jacfwd_flat = jax.jit(jax.jacfwd(flat_args))
jacrev_flat = jax.jit(jax.jacrev(flat_args))
value_flat = jax.jit(flat_args)


def tree_axpy(alpha, v, x):
    return jax.tree.map(lambda vi, xi: xi + alpha * vi, v, x)


def tree_dot(a, b):
    return sum(float(jnp.vdot(ai, bi)) for ai, bi in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def random_direction(rng, tree):
    return jax.tree.map(lambda leaf: jnp.asarray(rng.standard_normal(np.shape(leaf))), tree)


def central_difference(args, v, h=1e-5):
    return (value_flat(tree_axpy(h, v, args)) - value_flat(tree_axpy(-h, v, args))) / (2 * h)


# ---------------------------------------------------------------------------------------------------
# Circle (convex)


def test_circle_gap_normal_zeta_closed_form():
    centre, radius = np.array([1.0, -5.0]), 5.0
    tool = Tool.circle(centre, radius)
    rng = np.random.default_rng(RNG_SEED)
    angles = rng.uniform(-math.pi, math.pi, 50)
    distances = rng.uniform(radius - 1.9, radius + 3.0, 50)  # penetrating and open, within capture
    radial = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    xs = centre + distances[:, None] * radial
    p = project_many(tool, jnp.asarray(xs))
    assert np.all(p.valid)
    np.testing.assert_allclose(p.gap, distances - radius, atol=1e-13)
    np.testing.assert_allclose(p.normal, radial, atol=1e-14)  # radially outward
    np.testing.assert_allclose(p.tangent, np.stack([-radial[:, 1], radial[:, 0]], axis=1), atol=1e-14)
    np.testing.assert_allclose(p.closest, centre + radius * radial, atol=1e-13)
    # zeta: counter-clockwise arc length from the seam at the bottom (-pi/2)
    np.testing.assert_allclose(p.zeta, radius * np.mod(angles + 0.5 * math.pi, 2 * math.pi), atol=1e-12)
    assert np.all(p.gap[distances < radius] < 0)
    np.testing.assert_allclose(chain_length(tool), 2 * math.pi * radius, rtol=1e-15)


def test_circle_seam_and_capture_depth():
    tool = Tool.circle((0.0, -5.0), 5.0, seam=0.5 * math.pi)
    p = project_one(tool, jnp.array([0.0, -10.5]))  # bottom: half way from the top seam
    np.testing.assert_allclose(p.zeta, 5.0 * math.pi, rtol=1e-15)
    # Penetration 1.9 mm is captured, 2.1 mm is not (d_capture = 2 mm), 2.1 mm is with d_capture = 3.
    assert bool(project_one(tool, jnp.array([0.0, -1.9])).valid)
    deep = project_one(tool, jnp.array([0.0, -2.1]))
    assert not bool(deep.valid)
    assert float(deep.gap) == GAP_OPEN and np.all(np.asarray(deep.normal) == 0) and float(deep.zeta) == 0
    wide = Tool.circle((0.0, -5.0), 5.0, d_capture=3.0, seam=0.5 * math.pi)
    np.testing.assert_allclose(project_one(wide, jnp.array([0.0, -2.1])).gap, -2.1, rtol=1e-14)


@pytest.mark.parametrize("concave", [False, True])
def test_point_at_arc_centre_is_open_without_nan(concave):
    centre = np.array([0.3, -0.2])
    arc = Circle(centre, 1.5) if not concave else Arc(centre, 1.5, math.pi, 0.0, concave=True)
    tool = Tool((arc,), "right", d_capture=5.0)  # deep enough that only the centre rule can open it
    args = (tool, jnp.asarray(centre), jnp.zeros(2))
    p = project_one(*args)
    assert not bool(p.valid) and float(p.gap) == GAP_OPEN
    for jac in (jacfwd_flat(args), jacrev_flat(args)):
        for leaf in jax.tree.leaves(jac):
            assert np.all(np.isfinite(leaf)) and np.all(np.asarray(leaf) == 0.0)


# ---------------------------------------------------------------------------------------------------
# Concave arc (groove) and segments


def test_concave_groove_normal_points_to_centre():
    centre, radius = np.array([0.0, 1.0]), 7.25
    tool = Tool((Arc(centre, radius, 0.9 * math.pi, 0.1 * math.pi, concave=True),), "right")
    for x, gap in [((0.0, 4.0), 4.25), ((0.0, 9.0), -0.75), ((1.0, 1.0 + radius + 0.5), None)]:
        x = np.asarray(x)
        p = project_one(tool, jnp.asarray(x))
        rho = np.linalg.norm(x - centre)
        assert bool(p.valid)
        np.testing.assert_allclose(p.gap, radius - rho, atol=1e-14)  # inside the circle: sheet side
        if gap is not None:
            np.testing.assert_allclose(p.gap, gap, atol=1e-14)
        np.testing.assert_allclose(p.normal, (centre - x) / rho, atol=1e-15)
    # The groove is walked clockwise (sheet on the right): zeta grows from the left end to the right.
    z = [float(project_one(tool, jnp.array([xx, 5.0])).zeta) for xx in (-2.0, 0.0, 2.0)]
    assert z[0] < z[1] < z[2]
    np.testing.assert_allclose(z[1], radius * 0.4 * math.pi, rtol=1e-14)
    # Below the centre the radial foot is off the arc: open.
    assert not bool(project_one(tool, jnp.array([0.0, 0.0])).valid)


@pytest.mark.parametrize("side", ["right", "left"])
def test_segment_gap_side_zeta_extent(side):
    start, end = np.array([1.0, 2.0]), np.array([7.0, 10.0])  # length 10, direction (0.6, 0.8)
    d = np.array([0.6, 0.8])
    right = np.array([d[1], -d[0]])
    n = right if side == "right" else -right
    tool = Tool.line(start, end, normal_side=side)
    for s, g in [(0.0, 0.5), (3.0, 1.5), (10.0, -1.0), (6.0, -1.9)]:
        p = project_one(tool, jnp.asarray(start + s * d + g * n))
        assert bool(p.valid)
        np.testing.assert_allclose(p.gap, g, atol=1e-14)
        np.testing.assert_allclose(p.normal, n, atol=1e-15)
        np.testing.assert_allclose(p.tangent, [-n[1], n[0]], atol=1e-15)
        np.testing.assert_allclose(p.zeta, s if side == "right" else -s, atol=1e-14)
        np.testing.assert_allclose(p.closest, start + s * d, atol=1e-14)
    # zeta increases along t
    x0 = start + 4.0 * d + 0.3 * n
    t = np.array([-n[1], n[0]])
    z0, z1 = (float(project_one(tool, jnp.asarray(x)).zeta) for x in (x0, x0 + 0.01 * t))
    np.testing.assert_allclose(z1 - z0, 0.01, rtol=1e-10)
    # Feet beyond either end: open.
    for s in (-0.01, 10.01):
        assert not bool(project_one(tool, jnp.asarray(start + s * d + 0.5 * n)).valid)
    # Behind the tool deeper than d_capture: open.
    assert not bool(project_one(tool, jnp.asarray(start + 5.0 * d - 2.5 * n)).valid)


def test_flat_die_slip_is_relative_tangential_displacement():
    """Spec 1.4: for a straight tool, zeta(x + dx; q + dq) - zeta(x; q) = (dx - dq e_q) . t."""
    die = Tool.line((-2.0, 0.395), (50.0, 0.395))  # sheet below: n = (0, -1), t = (1, 0)
    e_q = np.array([0.0, -1.0])
    x, q = np.array([10.0, 0.39]), 0.004
    dx, dq = np.array([0.013, -0.002]), 0.001
    p0 = project_one(die, jnp.asarray(x), jnp.asarray(q * e_q))
    p1 = project_one(die, jnp.asarray(x + dx), jnp.asarray((q + dq) * e_q))
    np.testing.assert_allclose(p0.normal, [0.0, -1.0])
    np.testing.assert_allclose(p1.zeta - p0.zeta, (dx - dq * e_q) @ np.asarray(p0.tangent), atol=1e-15)
    np.testing.assert_allclose(p0.gap, (x - np.array([0.0, 0.395 - q])) @ np.array([0.0, -1.0]), atol=1e-15)


# ---------------------------------------------------------------------------------------------------
# Chains: parallel curves, brute force, junctions and corners


@pytest.mark.parametrize("make", [bead_lower_die, blankholder_upper_die, blankholder_lower_tool])
@pytest.mark.parametrize("offset_normal", [0.4, -0.45])
def test_chain_parallel_curve_recovers_gap_zeta_closest(make, offset_normal):
    """Points at signed distance g along the normal of the chain point at arc length s project back to
    (g, s): the right primitive is chosen everywhere, junctions included, and gap, normal and zeta are
    continuous and zeta monotone along the chain."""
    tool = make()
    side = 1.0 if tool.normal_side == "right" else -1.0
    total = float(chain_length(tool))
    # Dense samples plus every junction exactly.
    junctions = np.cumsum([float(p.length()) for p in tool.primitives])[:-1]
    s = np.sort(np.concatenate([np.linspace(0.0, total, 1501), junctions]))
    if make is blankholder_lower_tool:
        # The land/flank corners of the lower tool are sharp (concave for the sheet): on the sheet side
        # both faces claim the points nearer than the offset; skip that neighbourhood.
        corners = junctions[[0, 3]]
        s = s[np.min(np.abs(s[:, None] - corners[None, :]), axis=1) > abs(offset_normal) + 1e-9]
    feet = [walk(tool, si) for si in s]
    points = np.array([f[0] for f in feet])
    normals = np.array([f[1] for f in feet])
    p = project_many(tool, jnp.asarray(points + offset_normal * normals))
    assert np.all(p.valid)
    np.testing.assert_allclose(p.gap, offset_normal, atol=1e-11)
    np.testing.assert_allclose(p.normal, normals, atol=1e-11)
    np.testing.assert_allclose(p.closest, points, atol=1e-10)
    np.testing.assert_allclose(p.zeta, side * s, atol=1e-10)
    assert np.all(side * np.diff(np.asarray(p.zeta)) >= 0)  # monotone along the walk
    # Continuity at the scale of the sampling: the normal jumps only at the sharp corners.
    jumps = np.sum(np.linalg.norm(np.diff(np.asarray(p.normal), axis=0), axis=1) > 0.1)
    assert jumps == (2 if make is blankholder_lower_tool else 0)


def test_chain_brute_force_signed_distance():
    """Random points in a band around the blankholder die: |gap| is the distance to a dense outline,
    the sign says on which side, and the closest point is the nearest outline point."""
    tool = blankholder_upper_die()
    outline = np.asarray(tool_outline(tool, n=4001))
    rng = np.random.default_rng(RNG_SEED)
    total = float(chain_length(tool))
    s = rng.uniform(0.0, total, 200)
    g = rng.uniform(-0.9, 0.9, 200)
    feet = [walk(tool, si) for si in s]
    xs = np.array([f[0] + gi * f[1] for f, gi in zip(feet, g)])
    p = project_many(tool, jnp.asarray(xs))
    assert np.all(p.valid)
    # Distance to every chord of the polyline, and the nearest point on it.
    a, ab = outline[:-1], np.diff(outline, axis=0)
    along = np.einsum("pki,ki->pk", xs[:, None, :] - a[None], ab) / np.maximum(np.sum(ab * ab, axis=1), 1e-300)
    feet_poly = a[None] + np.clip(along, 0.0, 1.0)[..., None] * ab[None]
    dist = np.linalg.norm(xs[:, None, :] - feet_poly, axis=2)
    nearest = np.argmin(dist, axis=1)
    rows = np.arange(len(xs))
    # Chord sagitta of the outline, R dtheta^2 / 8, is below 5e-7 mm for every arc here.
    np.testing.assert_allclose(np.abs(p.gap), dist[rows, nearest], atol=1e-6)
    np.testing.assert_allclose(np.sign(p.gap), np.sign(g))
    # xbar is the foot of the normal through x, and it lies on the tool (within the sagitta).
    np.testing.assert_allclose(xs - np.asarray(p.closest), np.asarray(p.gap)[:, None] * np.asarray(p.normal),
                               atol=1e-12)
    c = np.asarray(p.closest)
    along = np.einsum("pki,ki->pk", c[:, None, :] - a[None], ab) / np.maximum(np.sum(ab * ab, axis=1), 1e-300)
    on_tool = np.min(np.linalg.norm(c[:, None, :] - a[None] - np.clip(along, 0.0, 1.0)[..., None] * ab[None],
                                    axis=2), axis=1)
    assert np.max(on_tool) < 1e-6


def test_junction_is_continuous_across_the_normal_line():
    """Across the land -> fillet and fillet -> groove junctions of the blankholder die, at 1e-7 mm on
    either side of the common normal line: gap, normal and zeta agree to first order."""
    tool = blankholder_upper_die()
    junctions = np.cumsum([float(p.length()) for p in tool.primitives])[:-1]
    for sj in junctions[1:3]:
        for g in (0.5, -0.5):
            a, b = (walk(tool, sj + e) for e in (-1e-7, 1e-7))
            pa = project_one(tool, jnp.asarray(a[0] + g * a[1]))
            pb = project_one(tool, jnp.asarray(b[0] + g * b[1]))
            assert bool(pa.valid) and bool(pb.valid)
            np.testing.assert_allclose(pb.gap, pa.gap, atol=1e-12)
            np.testing.assert_allclose(pb.normal, pa.normal, atol=1e-7)
            np.testing.assert_allclose(pb.zeta - pa.zeta, 2e-7, rtol=1e-4)


def test_sharp_corners():
    """Convex corner (a roof, sheet above): the vertex's fan is open, and inside the tool the nearer
    face is chosen. Concave corner (lower blankholder land/flank): the nearer face is chosen."""
    roof = Tool((Segment((-5.0, 0.0), (0.0, 2.0)), Segment((0.0, 2.0), (5.0, 0.0))), normal_side="left")
    assert not bool(project_one(roof, jnp.array([0.0, 3.0])).valid)  # in the fan
    n_left = np.array([-2.0, 5.0]) / math.sqrt(29.0)
    # (-0.1, 1) lies in the strips of both faces: gaps -0.891 (left face) and -0.966 (right face).
    p = project_one(roof, jnp.array([-0.1, 1.0]))
    assert bool(p.valid)
    np.testing.assert_allclose(p.normal, n_left, atol=1e-15)
    np.testing.assert_allclose(p.gap, (np.array([-0.1, 1.0]) - np.array([0.0, 2.0])) @ n_left, atol=1e-14)
    p = project_one(roof, jnp.array([0.1, 1.0]))
    np.testing.assert_allclose(p.normal, n_left * np.array([-1.0, 1.0]), atol=1e-15)

    lower = blankholder_lower_tool(H=9.0, R=6.0)
    p = project_one(lower, jnp.array([-6.3, -8.8]))  # 0.2 above the land, 0.3 left of flank
    np.testing.assert_allclose([p.gap, *p.normal], [0.2, 0.0, 1.0], atol=1e-14)
    p = project_one(lower, jnp.array([-6.1, -8.6]))  # 0.4 above the land, 0.1 left
    np.testing.assert_allclose([p.gap, *p.normal], [0.1, -1.0, 0.0], atol=1e-14)


def test_behind_bead_die_is_open():
    """A point above the lower bead die's rounded end (behind the tool, beyond its arc's extent) is open;
    one in front of the rounded end projects on the arc with n radially outward."""
    tool = bead_lower_die()
    assert not bool(project_one(tool, jnp.array([-39.0, -2.5])).valid)
    x = np.array([-39.0, -1.0])
    p = project_one(tool, jnp.asarray(x))
    radial = (x - np.array([-40.0, -2.0])) / math.sqrt(2.0)
    np.testing.assert_allclose(p.normal, radial, atol=1e-15)
    np.testing.assert_allclose(p.gap, math.sqrt(2.0) - 2.0, atol=1e-15)
    np.testing.assert_allclose(p.zeta, -(math.pi + 50.0 + 0.5 * math.pi), atol=1e-13)  # 45 deg into it


# ---------------------------------------------------------------------------------------------------
# Objectivity


def test_translation_objectivity():
    """gap, n, t, zeta of (x + d, offset + d) equal those of (x, offset); xbar moves by d."""
    tool = blankholder_upper_die()
    rng = np.random.default_rng(RNG_SEED + 1)
    total = float(chain_length(tool))
    feet = [walk(tool, si) for si in rng.uniform(0.0, total, 40)]
    xs = np.array([f[0] + 0.3 * f[1] for f in feet]) + np.array([0.7, -0.4])
    offset = np.array([0.7, -0.4])
    p0 = project_many(tool, jnp.asarray(xs), jnp.asarray(offset))
    for d in (np.array([13.0, -4.0]), np.array([-0.25, 11.0])):
        p1 = project_many(tool, jnp.asarray(xs + d), jnp.asarray(offset + d))
        assert np.all(p0.valid) and np.all(p1.valid)
        for a, b in [(p0.gap, p1.gap), (p0.normal, p1.normal), (p0.tangent, p1.tangent), (p0.zeta, p1.zeta)]:
            np.testing.assert_allclose(b, a, atol=1e-12)
        np.testing.assert_allclose(p1.closest, np.asarray(p0.closest) + d, atol=1e-12)


# ---------------------------------------------------------------------------------------------------
# Derivatives


def jacobian_fd(args, path, h=1e-5):
    """Central differences of `flat_args` w.r.t. the leaf path(args), shape (8, *leaf.shape)."""
    leaf = np.asarray(path(args))
    columns = []
    for i in range(leaf.size):
        step = np.zeros(leaf.size)
        step[i] = h
        step = step.reshape(leaf.shape)
        plus, minus = (eqx.tree_at(path, args, jnp.asarray(leaf + sign * step)) for sign in (1.0, -1.0))
        columns.append((np.asarray(value_flat(plus)) - np.asarray(value_flat(minus))) / (2 * h))
    return np.stack(columns, axis=-1).reshape((8, *leaf.shape))


@pytest.mark.parametrize("concave", [False, True])
def test_arc_jacobians_against_finite_differences(concave):
    """jacfwd of (gap, n, t, zeta, xbar) w.r.t. x, offset, radius and centre against central differences
    (rel 1e-6); jacrev agrees with jacfwd."""
    centre = np.array([0.4, -5.0])
    arc = Circle(centre, 5.0) if not concave else Arc(centre, 7.0, 0.9 * math.pi, 0.1 * math.pi, concave=True)
    tool = Tool((arc,), "right")
    x, offset = np.array([1.7, 0.6]), np.array([0.2, -0.3])
    args = (tool, jnp.asarray(x), jnp.asarray(offset))
    assert bool(project_one(*args).valid)
    fwd, rev = jacfwd_flat(args), jacrev_flat(args)
    for a, b in zip(jax.tree.leaves(fwd), jax.tree.leaves(rev)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)
    paths = {"x": lambda a: a[1], "offset": lambda a: a[2], "radius": lambda a: a[0].primitives[0].radius,
             "centre": lambda a: a[0].primitives[0].centre}
    ad = {name: path(fwd) for name, path in paths.items()}
    for name, path in paths.items():
        np.testing.assert_allclose(ad[name], jacobian_fd(args, path), rtol=1e-6, atol=1e-9, err_msg=name)
    # Closed forms for the convex circle: dg/dx = n, dg/dR = -1, dg/dc = -n, dn/dx = (I - n n^T) / rho.
    if not concave:
        rel = x - offset - centre
        rho = np.linalg.norm(rel)
        n = rel / rho
        np.testing.assert_allclose(ad["x"][0], n, rtol=1e-14)
        np.testing.assert_allclose(ad["radius"][0], -1.0, rtol=1e-14)
        np.testing.assert_allclose(ad["centre"][0], -n, rtol=1e-14)
        np.testing.assert_allclose(ad["x"][1:3], (np.eye(2) - np.outer(n, n)) / rho, atol=1e-15)


@pytest.mark.parametrize("make", [blankholder_upper_die, bead_lower_die])
def test_chain_directional_derivatives_and_dot_product(make):
    """Along random directions in (every tool leaf, x, offset), for points on each primitive: the JVP
    matches central differences, and <w, J v> = <J^T w, v>."""
    tool = make()
    rng = np.random.default_rng(RNG_SEED + 2)
    lengths = [float(p.length()) for p in tool.primitives]
    starts = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    for k, (s0, length) in enumerate(zip(starts, lengths)):
        point, normal = walk(tool, s0 + 0.37 * length)  # well inside primitive k
        x = point + 0.2 * normal + 0.3
        args = (tool, jnp.asarray(x), jnp.asarray(np.full(2, 0.3)))
        assert bool(project_one(*args).valid)
        v = random_direction(rng, args)
        jv = np.asarray(jvp_flat(args, v))
        np.testing.assert_allclose(jv, central_difference(args, v), rtol=1e-6, atol=1e-8,
                                   err_msg=f"primitive {k}")
        w = jnp.asarray(rng.standard_normal(8))
        np.testing.assert_allclose(float(w @ jv), tree_dot(vjp_flat(args, w), v), rtol=1e-12,
                                   err_msg=f"primitive {k}")


def test_open_pair_has_zero_finite_derivatives():
    """Open pairs: forward and reverse derivatives in every direction are exactly 0 (and finite)."""
    tool = blankholder_upper_die()
    rng = np.random.default_rng(RNG_SEED + 4)
    for x in ([-20.0, 3.5], [0.0, 12.0], [-9.0, 5.5]):  # behind the land, the groove, the fillet
        args = (tool, jnp.asarray(x), jnp.zeros(2))
        assert not bool(project_one(*args).valid)
        assert np.all(np.asarray(jvp_flat(args, random_direction(rng, args))) == 0.0)
        cotangent = vjp_flat(args, jnp.asarray(rng.standard_normal(8)))
        assert all(np.all(np.asarray(leaf) == 0.0) for leaf in jax.tree.leaves(cotangent))


def _pair_jacobians(part, X, u, u_ref, q, q_ref):
    """The pair's projection Jacobian d(n, g_N, zeta_increment)/d(u, q) (4, 3) in closed form and by
    ``jax.jacfwd``, and the projection's validity, for one point."""
    def local(z):
        pr = part.projection(X, z[:2], u_ref, z[2], q_ref)
        return jnp.concatenate([pr.normal, pr.gap[None], pr.zeta_increment[None]]), pr

    ad, pr = jax.jacfwd(local, has_aux=True)(jnp.concatenate([u, q[None]]))
    return part.jacobian(pr), ad, pr.valid


_pair_jacobians_many = jax.jit(jax.vmap(_pair_jacobians, in_axes=(None, 0, 0, 0, None, None)))


PAIR_TOOLS = [blankholder_upper_die, blankholder_lower_tool, bead_lower_die, lambda: Tool.circle((0.0, -5.0), 5.0)]
DRIVE = np.array([0.3, -1.0]) / np.hypot(0.3, 1.0)   # a slanted closing direction


def _pair_points(tool, rng):
    """Pair data near every primitive of ``tool`` (on both sides of it, and some too deep to count): the
    reference positions X (tool at q_ref), displacements u (tool at q), u_ref, and q, q_ref."""
    lengths = [float(p.length()) for p in tool.primitives]
    starts = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    points = []
    for s0, length in zip(starts, lengths):
        for frac in rng.uniform(0.05, 0.95, 12):
            point, normal = walk(tool, s0 + frac * length)
            points.append(point + rng.uniform(-1.5, 1.0) * normal)
        points.append(walk(tool, s0 + 0.5 * length)[0] - 2.5 * walk(tool, s0 + 0.5 * length)[1])   # too deep: open
    n = len(points)
    q, q_ref = jnp.asarray(0.35), jnp.asarray(0.2)
    X = np.asarray(points) + float(q_ref) * DRIVE - 0.01
    u = rng.uniform(-0.05, 0.05, (n, 2)) + float(q - q_ref) * DRIVE
    u_ref = u - rng.uniform(-0.03, 0.03, (n, 2))
    return jnp.asarray(X), jnp.asarray(u), jnp.asarray(u_ref), q, q_ref


def _pair_tool(tool, friction=None, frictional=False):
    from jaxfric.contact.pair_batches import PairTool
    return PairTool(tool.primitives, jnp.asarray(float(tool.side)), tool.d_capture, jnp.asarray(DRIVE), friction,
                    frictional)


@pytest.mark.parametrize("make", PAIR_TOOLS)
def test_closed_form_pair_jacobian_is_the_forward_derivative(make):
    """`PairTool.jacobian` (the pairs' derivatives in every contact law) equals jacfwd of the projection, at
    points near every primitive (convex and concave arcs, segments, either normal side), in contact and
    open, with a slanted closing direction, slip increments and a moved tool."""
    tool = make()
    X, u, u_ref, q, q_ref = _pair_points(tool, np.random.default_rng(RNG_SEED + 5))
    closed, ad, valid = _pair_jacobians_many(_pair_tool(tool), X, u, u_ref, q, q_ref)
    valid = np.asarray(valid)
    assert valid.sum() > 0.6 * valid.size and (~valid).sum() >= len(tool.primitives) - 1, (valid.sum(), valid.size)
    np.testing.assert_allclose(np.asarray(closed), np.asarray(ad), rtol=1e-12, atol=1e-13)
    assert np.all(np.asarray(closed)[~valid] == 0.0)


@pytest.mark.parametrize("law", ["penalty_pressure_law", "auglag_smoothed"])
def test_penalty_pair_force_jacobian_is_the_forward_derivative(law):
    """The regularised laws' pair force Jacobian d f / d(u, q), by the chain rule of the projection's
    closed-form derivatives and the law's in (g_N, slip), equals forward mode through the whole pair, on
    the bead's lower die (arcs and a segment; the concave arcs' derivatives are checked above): the penalty
    law with a friction coefficient of the pressure, and the augmented Lagrangian with multipliers and
    smoothing; open, sticking and slipping pairs."""
    from jaxfric.contact.formulations import AugmentedLagrangian, Penalty
    from jaxfric.contact.friction import Polynomial
    from jaxfric.contact.rigid import _pair, _pair_and_jacobian
    tool = bead_lower_die()
    rng = np.random.default_rng(RNG_SEED + 6)
    X, u, u_ref, q, q_ref = _pair_points(tool, rng)
    n = X.shape[0]
    lam_n = jnp.zeros(n) if law.startswith("penalty") else jnp.asarray(rng.uniform(0.0, 50.0, n))
    lam_t = jnp.asarray(rng.uniform(-10.0, 10.0, n))
    contact = (Penalty(1e4, 1.7e3) if law != "auglag_smoothed" else
               AugmentedLagrangian(1e4, 1.7e3, smoothing=2.0))
    part = _pair_tool(tool, Polynomial(c_p=-2e-6) if law.endswith("pressure_law") else None, frictional=True)
    length, speed, mu = 0.4, 0.0, jnp.asarray(0.17)

    def both(X, u, u_ref, lam_n, lam_t):
        one = lambda u, q: _pair(part, contact, X, u, q, mu, lam_n, lam_t, u_ref, q_ref, length, speed)[0]  # noqa: E731
        ad = jnp.concatenate([jax.jacfwd(one, argnums=0)(u, q), jax.jacfwd(one, argnums=1)(u, q)[:, None]], 1)
        (f, aux), closed = _pair_and_jacobian(part, contact, X, u, q, mu, lam_n, lam_t, u_ref, q_ref, length, speed)
        return closed, ad, aux[2]

    closed, ad, status = jax.jit(jax.vmap(both))(X, u, u_ref, lam_n, lam_t)
    status = np.asarray(status)
    assert {0, 1, 2} <= set(status.tolist()), status   # open, sticking and slipping pairs
    scale = float(jnp.max(jnp.abs(ad)))
    np.testing.assert_allclose(np.asarray(closed), np.asarray(ad), rtol=1e-11, atol=1e-13 * scale)


# ---------------------------------------------------------------------------------------------------
# Transformations


def test_vmap_points_and_tools_and_no_retrace():
    rng = np.random.default_rng(RNG_SEED + 3)
    tool = Tool.circle((0.0, 0.0), 3.0)
    xs = rng.uniform(-5.0, 5.0, (500, 2))
    batched = project_many(tool, jnp.asarray(xs))
    project_jit = jax.jit(project)
    one_by_one = [project_jit(tool, jnp.asarray(x), jnp.zeros(2)) for x in xs[:20]]
    # A few ulps, not 1: XLA may fuse (and round) the batched gap expression differently.
    np.testing.assert_allclose(batched.gap[:20], [p.gap for p in one_by_one], rtol=1e-14)
    np.testing.assert_array_equal(batched.valid[:20], [bool(p.valid) for p in one_by_one])

    # Tools of identical structure, stacked leaf by leaf, vmapped.
    tools = [Tool.circle((0.0, 0.0), r) for r in (2.0, 3.0, 4.0)]
    stacked = jax.tree.map(lambda *leaves: jnp.stack(leaves), *tools)
    x = jnp.array([0.0, 3.5])
    gaps = jax.jit(jax.vmap(project, in_axes=(0, None, None)))(stacked, x, jnp.zeros(2)).gap
    np.testing.assert_allclose(gaps, [1.5, 0.5, -0.5], rtol=1e-14)

    # New dimensions reuse the compiled code.
    @jax.jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def gap_of(tool, x):
        return project(tool, x, jnp.zeros(2)).gap

    for r in (2.0, 3.0, 4.0):
        np.testing.assert_allclose(gap_of(Tool.circle((0.0, 0.0), r), x), 3.5 - r, rtol=1e-14)
    gap_of(Tool.circle((0.0, 0.0), 1.0, d_capture=0.5), x)


def test_outline_and_length():
    tool = bead_lower_die()
    outline = np.asarray(tool_outline(tool, offset=(0.0, 1.0), n=5))
    assert outline.shape == (5 + 2 + 5, 2)
    np.testing.assert_allclose(outline[0], [-92.0, -1.0], atol=1e-14)
    np.testing.assert_allclose(outline[-1], [-38.0, -1.0], atol=1e-14)
    np.testing.assert_allclose(chain_length(tool), 50.0 + 2.0 * math.pi, rtol=1e-15)
    dlength = jax.grad(lambda t: chain_length(t))(tool)
    np.testing.assert_allclose(dlength.primitives[0].radius, 0.5 * math.pi, rtol=1e-15)


# ---------------------------------------------------------------------------------------------------
# Construction checks


@pytest.mark.parametrize("build, field", [
    (lambda: Arc((0.0, 0.0), -1.0, 0.0, 1.0), "radius"),
    (lambda: Arc((0.0, 0.0), 0.0, 0.0, 1.0), "radius"),
    (lambda: Arc((0.0, np.nan), 1.0, 0.0, 1.0), "centre"),
    (lambda: Arc((0.0, 0.0), 1.0, 0.0, np.inf), "angle_end"),
    (lambda: Arc((0.0, 0.0), 1.0, 0.5, 0.5), "angle_end"),
    (lambda: Arc((0.0, 0.0), 1.0, 0.0, 7.0), "angle_end"),
    (lambda: Circle((0.0, 0.0), np.inf), "radius"),
    (lambda: Segment((1.0, 2.0), (1.0, 2.0)), "end"),
    (lambda: Segment((np.inf, 2.0), (1.0, 2.0)), "start"),
    (lambda: Segment((0.0, 0.0, 0.0), (1.0, 2.0)), "start"),
    (lambda: Tool.line((0.0, 0.0), (1.0, 0.0), d_capture=0.0), "d_capture"),
    (lambda: Tool.line((0.0, 0.0), (1.0, 0.0), normal_side="below"), "normal_side"),
    (lambda: Tool(()), "primitives"),
    (lambda: Tool((Segment((0.0, 0.0), (1.0, 0.0)), Segment((1.1, 0.0), (2.0, 0.0)))), "primitives"),
    # The bead lower die with its arcs listed in ascending angles (as the spec's table reads) runs
    # against the chain.
    (lambda: Tool((Arc((-90.0, -2.0), 2.0, 0.5 * math.pi, math.pi), Segment((-90.0, 0.0), (-40.0, 0.0))),
                  normal_side="left"), "primitives"),
    (lambda: Tool((Arc((0.0, 0.0), 1.0, 0.0, 1.0, concave=True),)), "primitives"),
])
def test_bad_input_raises_value_error_naming_the_field(build, field):
    with pytest.raises(ValueError, match=field):
        build()


def test_valid_constructions():
    # A full circle may be given in either sense, on either side.
    Tool((Arc((0.0, 0.0), 1.0, 2 * math.pi, 0.0),), normal_side="right")
    Tool((Circle((0.0, 0.0), 1.0),), normal_side="left")
    # Construction inside jit (traced leaves): checks skipped, projection works.
    gap = jax.jit(lambda r: project(Tool.circle((0.0, 0.0), r), jnp.array([2.0, 0.0]), jnp.zeros(2)).gap)(1.5)
    np.testing.assert_allclose(gap, 0.5, rtol=1e-15)
