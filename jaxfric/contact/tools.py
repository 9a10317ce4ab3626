"""Rigid analytical tools: chains of line segments and circular arcs, and the projection of a point on them
(benchmarks spec section 0 "Rigid tools", "Contact candidates", "Capture depth", and section 1.4).

Conventions, stated once for the whole module
---------------------------------------------
- Units: lengths in mm; angles in radians, measured counter-clockwise from +x.
- A `Tool` is an ordered chain of primitives, listed in *walking order*: a `Segment` runs from `start`
  to `end`, an `Arc` from `angle_start` to `angle_end` (either sweep sense), and each primitive ends
  where the next one starts (checked at construction).
- `normal_side` (static) says on which side of the walking direction the sheet lies: "right" (default)
  or "left". The unit normal n points from the tool into the sheet; the tangent is t = (-n_y, n_x), n
  turned by +90 degrees. Hence with "right", t is the walking direction; with "left", t points
  backwards. Examples: a die above the sheet, listed left to right, is "right" (n = (0, -1) on a
  horizontal land); a tool below the sheet, listed left to right, is "left" (n = (0, 1)).
- Arcs: a *convex* arc has the tool inside its circle and n radially outward; a *concave* arc (a
  groove) has the tool outside its circle and n towards the centre. The sweep sense follows from the
  normal side: with "right", convex arcs run counter-clockwise (angle_end > angle_start) and concave
  arcs clockwise; with "left", the reverse. Construction checks this for partial arcs (a wrong sense
  means the angles were listed against the chain); a full circle may be given in either sense.
- Gap: g_N = (x - xbar) . n, positive on the sheet side, negative when x penetrates the tool.
- Arc length: zeta = s for "right" and zeta = -s for "left", with s the arc length from the chain's
  first point to xbar along the walking direction; so zeta increases along t. It is measured on the
  un-translated tool (the tool's own frame): the point x - offset is projected on the tool at rest,
  which makes g_N, n, t and zeta exactly invariant under a common translation of x and the tool.
  A full circle has a seam at `angle_start`, where zeta jumps by its circumference: put the seam
  where the sheet never touches (see `Circle`).

Choice of the primitive (spec section 0, "Contact candidates")
---------------------------------------------------------------
x - offset is projected on each primitive's supporting line or circle. A primitive *qualifies* when the
foot of that perpendicular lies inside its extent (widened by 1e-9 mm, so that a point projecting
exactly on a junction is not lost to rounding). Among the qualifying primitives the one with the
smallest |g_N| (the nearest foot) is taken; the pair is open ("invalid") when none qualifies, or when
the penetration is deeper than `d_capture`. The depth test is applied after the choice: the closest
primitive decides how deep the point is.

- Tangent-continuous junctions (all benchmark tools): the two primitives share their normal line at
  the junction, so near the tool (closer than the radii of the arcs) their regions border each other
  exactly along that line, without gap or overlap. On the line both give the same g_N, n and zeta: the
  projection is continuous across the junction, and derivatives are those of the primitive chosen.
- Sharp convex corners (sheet outside the corner): the fan of points whose nearest tool point is the
  vertex qualifies for no primitive and is open. The fan lies on the sheet side (g_N > 0 to every
  face), so nothing in contact is lost; a node that moves into the tool enters the strips of both
  faces, which overlap there, and the nearer face (smaller |g_N|) is the correct exit direction.
- Sharp concave corners (sheet inside the corner): on the sheet side both faces qualify and the nearer
  one is the closest point.

Open pairs return g_N = GAP_OPEN (1e30, finite), n = t = closest = (0, 0) and zeta = 0, with finite
(zero) derivatives. Every branch is guarded by the double-`where` trick, so neither values nor
forward/reverse derivatives carry NaN, even for a point exactly at an arc centre.

Every dimension (segment ends, centres, radii, angles, d_capture) is a float64 array leaf: a new value
neither recompiles nor blocks differentiation. Only the structure (number, kind and order of the
primitives, concave flags, normal side) is static. `project` acts on ONE point; vmap outward (over
points, or over tools of identical structure stacked leaf by leaf).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxfric.numerics._checks import check_finite, check_positive, is_concrete
from jaxfric.numerics.tensor import safe_norm

__all__ = ["GAP_OPEN", "Segment", "Arc", "Circle", "Tool", "Projection", "project", "project_chain", "chain_length",
           "tool_outline"]

GAP_OPEN = 1e30  # gap of an open pair: large and finite, so that products with zero stay zero
_EXTENT_TOL = 1e-9  # mm; widens each extent so that junction points are never lost to rounding
_JOIN_TOL = 1e-6  # mm (relative to the tool's size when larger than 1 mm); chain continuity check
_TWO_PI = 2.0 * math.pi
_SIDES = {"right": 1, "left": -1}


def _vec2(name: str, value) -> jax.Array:
    arr = jnp.asarray(value, dtype=jnp.float64)
    if arr.shape != (2,):
        raise ValueError(f"field '{name}' must be a 2-vector (x, y) in mm, got shape {arr.shape}")
    if is_concrete(arr) and not np.all(np.isfinite(np.asarray(arr))):
        raise ValueError(f"field '{name}' must be finite, got {np.asarray(arr)}")
    return arr


def _scalar(name: str, value) -> jax.Array:
    arr = jnp.asarray(value, dtype=jnp.float64)
    if arr.shape != ():
        raise ValueError(f"field '{name}' must be a scalar, got shape {arr.shape}")
    return arr


def _wrap_angle(angle: jax.Array) -> jax.Array:
    """angle mapped to [-pi, pi); derivative 1 everywhere."""
    return jnp.mod(angle + math.pi, _TWO_PI) - math.pi


class _Foot(NamedTuple):
    """Projection of a point on one primitive's supporting line or circle (tool at rest)."""

    gap: jax.Array  # () mm, signed, > 0 on the sheet side
    normal: jax.Array  # (2,) unit normal into the sheet side
    s: jax.Array  # () mm, arc length from the primitive's start along the walking direction
    ds: jax.Array  # () mm, increase of s caused by the increment (see `project`)
    closest: jax.Array  # (2,) mm, the foot of the perpendicular
    inside: jax.Array  # () bool, the foot lies inside the primitive's extent
    curvature: jax.Array  # () 1/mm: a motion dx of the point turns the normal by curvature (t . dx) t
    rate: jax.Array  # () ds / d(t . x): 1 on a segment, radius / distance from the centre on an arc


class Segment(eqx.Module):
    """Straight segment of a tool chain, walked from `start` to `end`.

    With the tool's normal_side "right" the sheet is on the right of start -> end, n = (d_y, -d_x) with
    d the unit direction start -> end, and t = d; with "left", n = (-d_y, d_x) and t = -d.

    Attributes:
        start: (2,) first point (mm).
        end: (2,) last point (mm), distinct from `start`.
    """

    start: jax.Array
    end: jax.Array

    def __init__(self, start, end):
        self.start = _vec2("start", start)
        self.end = _vec2("end", end)

    def __check_init__(self):
        if is_concrete((self.start, self.end)) and np.all(np.asarray(self.start) == np.asarray(self.end)):
            raise ValueError(f"Segment: field 'end' equals field 'start' = {np.asarray(self.start)}: "
                             "a segment must have a non-zero length")

    def length(self) -> jax.Array:
        """|end - start| (mm)."""
        return safe_norm(self.end - self.start)

    def start_point(self) -> jax.Array:
        return self.start

    def end_point(self) -> jax.Array:
        return self.end

    def outline(self, n: int) -> jax.Array:
        """(2, 2) end points; a straight piece needs no more for plotting."""
        del n
        return jnp.stack([self.start, self.end])

    def foot(self, y: jax.Array, dy: jax.Array, inc: jax.Array, side: int) -> _Foot:
        """Foot of the perpendicular from y + dy + inc (2,) on the supporting line, and the increase of
        s caused by ``inc``; side = +1 right, -1 left."""
        chord = self.end - self.start
        length = safe_norm(chord)
        # Guarded division: a zero length is rejected at construction, but a traced one must not NaN.
        direction = chord / jnp.where(length > 0, length, jnp.ones_like(length))
        normal = side * jnp.stack([direction[1], -direction[0]])
        rel = ((y - self.start) + dy) + inc  # see `project`: the large parts cancel first
        s = rel @ direction
        inside = (length > 0) & (s >= -_EXTENT_TOL) & (s <= length + _EXTENT_TOL)
        zero = jnp.zeros_like(s)
        return _Foot(rel @ normal, normal, s, inc @ direction, self.start + s * direction, inside, zero, zero + 1.0)


class Arc(eqx.Module):
    """Circular arc of a tool chain, walked from `angle_start` to `angle_end`.

    The point at angle a is centre + radius (cos a, sin a). Convex (default): the tool is inside the
    circle, n is radially outward. Concave: the tool is outside the circle (a groove), n points to the
    centre. |angle_end - angle_start| <= 2 pi; 2 pi is a full circle (see `Circle`).

    Attributes:
        centre: (2,) centre of the circle (mm).
        radius: () radius (mm), > 0.
        angle_start: () angle of the first point (rad).
        angle_end: () angle of the last point (rad).
        concave: static flag, True for a groove.
    """

    centre: jax.Array
    radius: jax.Array
    angle_start: jax.Array
    angle_end: jax.Array
    concave: bool = eqx.field(static=True)

    def __init__(self, centre, radius, angle_start, angle_end, concave: bool = False):
        self.centre = _vec2("centre", centre)
        self.radius = _scalar("radius", radius)
        self.angle_start = _scalar("angle_start", angle_start)
        self.angle_end = _scalar("angle_end", angle_end)
        self.concave = bool(concave)

    def __check_init__(self):
        check_positive("radius", self.radius)
        check_finite("angle_start", self.angle_start)
        check_finite("angle_end", self.angle_end)
        if is_concrete((self.angle_start, self.angle_end)):
            sweep = abs(float(self.angle_end) - float(self.angle_start))
            if sweep == 0.0:
                raise ValueError("Arc: field 'angle_end' equals field 'angle_start': an arc must have a "
                                 "non-zero sweep")
            if sweep > _TWO_PI * (1.0 + 1e-12):
                raise ValueError(f"Arc: |angle_end - angle_start| = {sweep} exceeds 2 pi: an arc may "
                                 "cover the circle at most once")

    def sweep(self) -> jax.Array:
        """|angle_end - angle_start| (rad)."""
        return jnp.abs(self.angle_end - self.angle_start)

    def is_full_circle(self) -> bool:
        """Concrete values only: the arc closes on itself (used by the construction checks)."""
        return abs(float(self.angle_end) - float(self.angle_start)) >= _TWO_PI * (1.0 - 1e-12)

    def length(self) -> jax.Array:
        """radius * |sweep| (mm)."""
        return self.radius * self.sweep()

    def _point(self, angle: jax.Array) -> jax.Array:
        return self.centre + self.radius * jnp.stack([jnp.cos(angle), jnp.sin(angle)])

    def start_point(self) -> jax.Array:
        return self._point(self.angle_start)

    def end_point(self) -> jax.Array:
        return self._point(self.angle_end)

    def outline(self, n: int) -> jax.Array:
        """(n, 2) points from angle_start to angle_end."""
        return jax.vmap(self._point)(jnp.linspace(self.angle_start, self.angle_end, n))

    def walk_sense(self, side: int) -> int:
        """+1 if the arc is walked counter-clockwise on a tool with this normal side, else -1."""
        # Right side: n = t turned -90 deg. Outward n (convex) then needs t, the walk, counter-clockwise.
        return side if not self.concave else -side

    def foot(self, y: jax.Array, dy: jax.Array, inc: jax.Array, side: int) -> _Foot:
        """Radial projection of y + dy + inc (2,) on the circle, and the increase of s caused by ``inc``
        (radius times the angle turned, from the cross and dot products of the old radius vector with
        ``inc``, so that a small increment is not lost against the radius); side = +1 right, -1 left."""
        walk = self.walk_sense(side)
        base = y - self.centre  # see `project`: the large parts cancel first
        shift = dy + inc  # small: the motion relative to the tool
        rel0 = base + dy
        rel = base + shift
        rho = safe_norm(rel)
        off_centre = rho > 0
        # Double where: at the centre the direction is undefined (the pair is open); a dummy unit vector
        # keeps atan2 and the division finite, so that no NaN reaches any derivative.
        rel_safe = jnp.where(off_centre, rel, jnp.array([1.0, 0.0]))
        radial = rel_safe / jnp.where(off_centre, rho, jnp.ones_like(rho))
        polar = jnp.arctan2(rel_safe[1], rel_safe[0])
        # Measured from the mid angle, so that the extent is |offset| <= half sweep with no wrap-around
        # inside it; for a full circle the only discontinuity is the seam at angle_start.
        half = 0.5 * self.sweep()
        from_mid = _wrap_angle(walk * (polar - 0.5 * (self.angle_start + self.angle_end)))
        inside = off_centre & (jnp.abs(from_mid) <= half + _EXTENT_TOL / self.radius)
        s = self.radius * (from_mid + half)
        # rho - R without cancelling at the magnitude of R: the part that varies with the unknowns,
        # 2 base.shift + |shift|^2, is small and kept apart from the constant |base|^2 - R^2.
        excess = ((base @ base - self.radius**2) + (2.0 * base + shift) @ shift) / (rho + self.radius)
        if self.concave:
            normal, gap = -radial, -excess
        else:
            normal, gap = radial, excess
        # Angle from rel0 to rel: atan2(rel0 x inc, |rel0|^2 + rel0 . inc); guarded at the centre.
        cross = rel0[0] * inc[1] - rel0[1] * inc[0]
        dot = rel0 @ rel0 + rel0 @ inc
        ok = (jnp.abs(cross) + jnp.abs(dot)) > 0
        turned = jnp.arctan2(jnp.where(ok, cross, 0.0), jnp.where(ok, dot, 1.0))
        # The normal is the radial direction (or its opposite), which a motion along t turns by 1/rho; an
        # arc length on the circle is R / rho times the motion along t at the distance rho.
        inv_rho = 1.0 / jnp.where(off_centre, rho, jnp.ones_like(rho))
        return _Foot(gap, normal, s, walk * self.radius * turned, self.centre + self.radius * radial, inside,
                     -inv_rho if self.concave else inv_rho, self.radius * inv_rho)


def Circle(centre, radius, seam=-0.5 * math.pi) -> Arc:
    """Full convex circle (a roller or cylinder) as an `Arc` from `seam` to `seam` + 2 pi.

    Args:
        centre: (2,) mm.
        radius: () mm, > 0.
        seam: () rad, where zeta jumps by the circumference. The default, -pi/2 (the bottom), suits a
            cylinder the sheet touches from above; pass pi/2 for one it touches from below.
    """
    seam = _scalar("seam", seam)
    return Arc(centre, radius, seam, seam + _TWO_PI, concave=False)


def _end_points_numpy(prim) -> np.ndarray:
    """(2, 2) first and last point of a primitive with concrete leaves."""
    if isinstance(prim, Segment):
        return np.stack([np.asarray(prim.start), np.asarray(prim.end)])
    angles = np.array([float(prim.angle_start), float(prim.angle_end)])
    return np.asarray(prim.centre) + float(prim.radius) * np.stack([np.cos(angles), np.sin(angles)], axis=1)


class Tool(eqx.Module):
    """Rigid tool: an ordered, connected chain of `Segment`s and `Arc`s (conventions: module docstring).

    Attributes:
        primitives: tuple of Segment / Arc in walking order (static count and kinds).
        d_capture: () mm, > 0: a pair that penetrates deeper than this is open (spec default 2 mm).
        normal_side: static, "right" or "left": side of the walking direction where the sheet lies.
    """

    primitives: tuple
    d_capture: jax.Array
    normal_side: str = eqx.field(static=True)

    def __init__(self, primitives, normal_side: str = "right", d_capture=2.0):
        self.primitives = tuple(primitives)
        self.normal_side = normal_side
        self.d_capture = _scalar("d_capture", d_capture)

    def __check_init__(self):
        if self.normal_side not in _SIDES:
            raise ValueError(f"Tool: field 'normal_side' must be 'right' or 'left', got {self.normal_side!r}")
        if not self.primitives:
            raise ValueError("Tool: field 'primitives' is empty: a tool needs at least one primitive")
        for k, prim in enumerate(self.primitives):
            if not isinstance(prim, (Segment, Arc)):
                raise ValueError(f"Tool: field 'primitives'[{k}] must be a Segment or an Arc, got {type(prim)}")
        check_positive("d_capture", self.d_capture)
        if not is_concrete(self.primitives):
            return
        side = _SIDES[self.normal_side]
        for k, prim in enumerate(self.primitives):
            if isinstance(prim, Arc) and not prim.is_full_circle():
                sense = 1 if float(prim.angle_end) > float(prim.angle_start) else -1
                if sense != prim.walk_sense(side):
                    kind = "concave" if prim.concave else "convex"
                    needed = "counter-clockwise" if prim.walk_sense(side) > 0 else "clockwise"
                    raise ValueError(
                        f"Tool: field 'primitives'[{k}] is a {kind} arc on a tool with normal_side="
                        f"'{self.normal_side}', so it must run {needed} along the chain; its angles "
                        f"({float(prim.angle_start)} -> {float(prim.angle_end)}) run the other way. "
                        "Swap angle_start and angle_end, or check the concave flag and normal_side.")
        # Plain numpy: construction should not dispatch (and compile) small JAX ops one by one.
        ends = [_end_points_numpy(p) for p in self.primitives]
        tol = _JOIN_TOL * max(1.0, max(float(np.max(np.abs(e))) for e in ends))
        for k in range(len(self.primitives) - 1):
            end, start = ends[k][1], ends[k + 1][0]
            if np.linalg.norm(end - start) > tol:
                raise ValueError(f"Tool: field 'primitives' is not a connected chain: primitive {k} ends at "
                                 f"{end} but primitive {k + 1} starts at {start}")

    @property
    def side(self) -> int:
        """Static: +1 for normal_side "right", -1 for "left"."""
        return _SIDES[self.normal_side]

    @classmethod
    def circle(cls, centre, radius, d_capture=2.0, seam=-0.5 * math.pi) -> Tool:
        """A full convex circle (roller, cylinder): centre (2,) mm, radius () mm; seam as in `Circle`."""
        return cls((Circle(centre, radius, seam),), "right", d_capture)

    @classmethod
    def line(cls, start, end, normal_side: str = "right", d_capture=2.0) -> Tool:
        """A single segment start (2,) -> end (2,) mm, sheet on `normal_side` of that direction."""
        return cls((Segment(start, end),), normal_side, d_capture)


class Projection(NamedTuple):
    """Closest-point projection of one point on a tool (spec section 1.4).

    Attributes:
        gap: () g_N = (x - xbar) . n (mm), negative when penetrating; GAP_OPEN when invalid.
        normal: (2,) unit n at xbar, from the tool into the sheet side; 0 when invalid.
        tangent: (2,) t = (-n_y, n_x); 0 when invalid.
        zeta: () arc-length coordinate of xbar along the chain (mm), tool frame, increasing along t;
            0 when invalid.
        closest: (2,) xbar in the current (translated) position (mm); 0 when invalid.
        valid: () bool, False for an open pair (no qualifying primitive, or deeper than d_capture).
        zeta_increment: () change of zeta caused by `increment` on the chosen primitive (mm); 0 without
            an increment or when invalid.
        curvature: () 1/mm, how the normal turns as the point moves: d n = curvature (t . d x) t (0 on a
            segment, 1/rho on a convex arc and -1/rho on a concave one, rho the point's distance from
            the centre); 0 when invalid.
        slip_rate: () d zeta / d(t . x), the arc length the foot travels per unit motion of the point
            along t (1 on a segment, R / rho on an arc); 0 when invalid. With d g_N = n . d x, these give
            the projection's derivatives in closed form (:meth:`jaxfric.contact.pair_batches.PairTool.jacobian`).
    """

    gap: jax.Array
    normal: jax.Array
    tangent: jax.Array
    zeta: jax.Array
    closest: jax.Array
    valid: jax.Array
    zeta_increment: jax.Array
    curvature: jax.Array
    slip_rate: jax.Array


def project(tool: Tool, x: jax.Array, offset: jax.Array, displacement=None, increment=None) -> Projection:
    """Project ONE point on a rigidly translated tool.

    Args:
        tool: the tool at rest.
        x: (2,) position of the point (mm); with ``displacement``, its reference position X.
        offset: (2,) rigid translation of the tool from rest (mm), e.g. q e_q.
        displacement: optional (2,) displacement u of the point: the point is then X + u. Passing X and
            u apart keeps the gap accurate to the precision of the (small) relative motion u - offset:
            each primitive forms (X - anchor) + (u - offset), where the first difference of large
            coordinates is exact for a point near the tool, instead of rounding X + u to the ulp of X.
            With a stiff penalty (eps_N = 1e9 N/mm), ulp(X) = 5e-17 mm would already be 5e-8 N/mm of
            force noise per pair, above Newton's tolerance.
        increment: optional (2,) motion of the point relative to the tool since a reference (the last
            converged step): the point is then X + u + increment and ``zeta_increment`` is the change of
            zeta it causes, computed from the increment itself. The slip zeta - zeta_n formed from two
            absolute arc lengths of ~100 mm would carry ulp(100) = 1.4e-14 mm of noise, which a
            tangential penalty of 1e8 N/mm turns into 1e-6 N/mm.

    Returns:
        Projection; the primitive is chosen as described in the module docstring. Differentiable in
        x, offset and every tool leaf, forward and reverse; vmap over points or stacked tools.
    """
    return project_chain(tool.primitives, tool.side, tool.d_capture, x, offset, displacement, increment)


def project_chain(primitives: tuple, side, d_capture, x: jax.Array, offset: jax.Array, displacement=None,
                  increment=None) -> Projection:
    """:func:`project` on a chain given by its parts: ``primitives`` (static kinds and order), ``side`` +1
    where the sheet lies on the right of the walking direction and -1 on the left (a number, or a ()
    array: it enters the arithmetic only as a factor of +-1, so tools of either side can be stacked and
    vmapped together, with the same results), and ``d_capture`` (mm)."""
    # The point in the tool's own frame is x + dy + inc.
    dy = -offset if displacement is None else displacement - offset
    inc = jnp.zeros(2, dtype=jnp.float64) if increment is None else increment
    feet, zetas = [], []
    travelled = jnp.zeros((), dtype=jnp.float64)
    for prim in primitives:  # static structure: unrolled at trace time
        foot = prim.foot(x, dy, inc, side)
        feet.append(foot)
        zetas.append(side * (travelled + foot.s))
        travelled = travelled + prim.length()
    gap = jnp.stack([f.gap for f in feet])
    inside = jnp.stack([f.inside for f in feet])
    # The nearest qualifying foot; the index is piecewise constant, so derivatives are the chosen one's.
    k = jnp.argmin(jnp.where(inside, jnp.abs(gap), jnp.inf))
    chosen_gap = gap[k]
    normal = jnp.stack([f.normal for f in feet])[k]
    valid = inside[k] & (chosen_gap >= -d_capture)

    zero2 = jnp.zeros(2, dtype=jnp.float64)
    normal = jnp.where(valid, normal, zero2)
    return Projection(
        gap=jnp.where(valid, chosen_gap, GAP_OPEN),
        normal=normal,
        tangent=jnp.stack([-normal[1], normal[0]]),
        zeta=jnp.where(valid, jnp.stack(zetas)[k], 0.0),
        zeta_increment=jnp.where(valid, side * jnp.stack([f.ds for f in feet])[k], 0.0),
        closest=jnp.where(valid, jnp.stack([f.closest for f in feet])[k] + offset, zero2),
        valid=valid,
        curvature=jnp.where(valid, jnp.stack([f.curvature for f in feet])[k], 0.0),
        slip_rate=jnp.where(valid, jnp.stack([f.rate for f in feet])[k], 0.0),
    )


def chain_length(tool: Tool) -> jax.Array:
    """Total arc length of the chain (mm), differentiable in the tool's dimensions."""
    return sum((prim.length() for prim in tool.primitives), jnp.zeros((), dtype=jnp.float64))


def tool_outline(tool: Tool, offset=(0.0, 0.0), n: int = 64) -> jax.Array:
    """(k, 2) polyline of the translated tool, in walking order, for plotting (mm); np.asarray-able.

    Args:
        tool: the tool at rest.
        offset: (2,) rigid translation (mm).
        n: static number of points per arc (segments contribute their two end points).
    """
    points = jnp.concatenate([prim.outline(n) for prim in tool.primitives])
    return points + jnp.asarray(offset, dtype=jnp.float64)
