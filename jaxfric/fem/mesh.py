"""Structured quadrilateral meshes of strips, numbered column by column.

Node (i, j), i = 0..nx along x and j = 0..ny through the thickness, has index ``i*(ny+1) + j``;
element (i, j) has index ``i*ny + j`` and nodes (i,j), (i+1,j), (i+1,j+1), (i,j+1) counter-clockwise.
With this numbering the stiffness of a strip is block-tridiagonal in blocks of ``2*(ny+1)`` dofs,
one block per column of nodes, which is what :mod:`jaxfric.numerics.linalg` exploits.

Only ``nx`` and ``ny`` are static; node coordinates are array leaves, so a length or a thickness
can be a traced (differentiated) parameter.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..numerics._checks import check_finite, check_finite_array, check_int, check_positive, is_concrete

__all__ = ["StripMesh", "strip_mesh", "graded_coordinates", "MAX_ELEMENTS"]

MAX_ELEMENTS = 1_000_000  # nx * ny: beyond any mesh a 2D strip needs, and far from int32 limits


class StripMesh(eqx.Module):
    """A structured ``nx`` x ``ny`` mesh of Q4 elements, numbered column by column.

    Attributes:
        nodes: (n_nodes, 2) reference coordinates X in mm, node (i, j) at row ``i*(ny+1)+j``.
        nx, ny: number of element columns (along x) and rows (through the thickness); static.
    """

    nodes: jax.Array
    nx: int = eqx.field(static=True)
    ny: int = eqx.field(static=True)

    def __check_init__(self):
        for name in ("nx", "ny"):
            check_int(name, getattr(self, name))
        expected = ((self.nx + 1) * (self.ny + 1), 2)
        if tuple(self.nodes.shape) != expected:
            raise ValueError(f"mesh field 'nodes' must have shape {expected}, got {self.nodes.shape}")
        check_finite_array("nodes", self.nodes)

    # ---- sizes (static) -------------------------------------------------------------------------
    @property
    def n_nodes(self) -> int:
        return (self.nx + 1) * (self.ny + 1)

    @property
    def n_elements(self) -> int:
        return self.nx * self.ny

    @property
    def n_dofs(self) -> int:
        return 2 * self.n_nodes

    @property
    def block_size(self) -> int:
        """Dofs per column of nodes: the block size of the block-tridiagonal stiffness."""
        return 2 * (self.ny + 1)

    # ---- topology (static numpy, computed from nx, ny) ------------------------------------------
    def node_index(self, i, j):
        return np.asarray(i) * (self.ny + 1) + np.asarray(j)

    @property
    def elements(self) -> np.ndarray:
        """(n_el, 4) int64 connectivity, counter-clockwise from the lower-left node."""
        i_grid, j_grid = np.meshgrid(np.arange(self.nx), np.arange(self.ny), indexing="ij")
        i, j = i_grid.ravel(), j_grid.ravel()
        return np.stack(
            [self.node_index(i, j), self.node_index(i + 1, j),
             self.node_index(i + 1, j + 1), self.node_index(i, j + 1)], axis=1
        ).astype(np.int64)

    @property
    def left(self) -> np.ndarray:
        """Nodes on x = x_left (i = 0), bottom to top."""
        return self.node_index(0, np.arange(self.ny + 1))

    @property
    def right(self) -> np.ndarray:
        """Nodes on x = x_right (i = nx), bottom to top."""
        return self.node_index(self.nx, np.arange(self.ny + 1))

    @property
    def bottom(self) -> np.ndarray:
        """Bottom-surface nodes (j = 0), left to right."""
        return self.node_index(np.arange(self.nx + 1), 0)

    @property
    def top(self) -> np.ndarray:
        """Top-surface nodes (j = ny), left to right."""
        return self.node_index(np.arange(self.nx + 1), self.ny)

    def node_set(self, name: str) -> np.ndarray:
        """Named node set: 'left', 'right', 'bottom', 'top' or 'all'."""
        if name == "all":
            return np.arange(self.n_nodes)
        if name not in ("left", "right", "bottom", "top"):
            raise ValueError(f"unknown node set {name!r}; use 'left', 'right', 'bottom', 'top' or 'all'")
        return getattr(self, name)

    @classmethod
    def from_coordinates(cls, xs, ys) -> StripMesh:
        """Tensor-product mesh from 1D node coordinates ``xs`` (nx+1,) and ``ys`` (ny+1,)."""
        xp = _array_module(xs, ys)
        xs = xp.asarray(xs, dtype=np.float64)
        ys = xp.asarray(ys, dtype=np.float64)
        for name, c in (("xs", xs), ("ys", ys)):
            if c.ndim != 1 or c.shape[0] < 2:
                raise ValueError(f"mesh field '{name}' must be a 1D array of at least 2 coordinates")
            if xp is np and not np.all(np.diff(c) > 0):
                raise ValueError(f"mesh field '{name}' must be strictly increasing")
        X, Y = xp.meshgrid(xs, ys, indexing="ij")
        nodes = jnp.asarray(xp.stack([X.ravel(), Y.ravel()], axis=1))
        return cls(nodes=nodes, nx=xs.shape[0] - 1, ny=ys.shape[0] - 1)


def graded_coordinates(start, stop, n: int, ratio=1.0):
    """n+1 coordinates from ``start`` to ``stop`` whose successive spacings grow by ``ratio``.

    ``ratio`` = 1 gives a uniform spacing; ``ratio`` > 1 refines towards ``start``, < 1 towards ``stop``.
    Differentiable in ``start``, ``stop`` and ``ratio``; computed in NumPy where none of them is traced.
    """
    xp = _array_module(start, stop, ratio)
    k = xp.arange(n + 1, dtype=np.float64)
    ratio = xp.asarray(ratio, dtype=np.float64)
    # Cumulative geometric series normalised to [0, 1]; the uniform limit is taken exactly.
    is_uniform = xp.abs(ratio - 1.0) < 1e-12
    safe_ratio = xp.where(is_uniform, 2.0, ratio)
    with np.errstate(over="ignore", invalid="ignore"):   # an overflowing grading is named by strip_mesh
        s = xp.where(is_uniform, k / n, (safe_ratio**k - 1.0) / (safe_ratio**n - 1.0))
    return xp.asarray(start, dtype=np.float64) + (xp.asarray(stop, dtype=np.float64) - start) * s


def _array_module(*values):
    """NumPy for concrete values, jax.numpy where any is traced: a mesh built from numbers runs no JAX
    operation one by one, each of which would compile a program of its own (seconds per scene)."""
    return np if is_concrete(values) else jnp


def strip_mesh(x_left, x_right, y_bottom, thickness, nx: int, ny: int,
               grading_x=1.0, grading_y=1.0) -> StripMesh:
    """Mesh of the strip [x_left, x_right] x [y_bottom, y_bottom + thickness] (mm).

    Args:
        x_left, x_right: strip ends (mm); x_right > x_left.
        y_bottom: y of the bottom surface (mm).
        thickness: strip thickness t > 0 (mm).
        nx, ny: elements along x and through the thickness (>= 1).
        grading_x, grading_y: ratio of successive element sizes (1 = uniform).
    """
    check_int("nx", nx, 1, MAX_ELEMENTS)
    check_int("ny", ny, 1, MAX_ELEMENTS)
    if nx * ny > MAX_ELEMENTS:
        raise ValueError(f"fields 'nx' x 'ny' = {nx} x {ny} give {nx * ny:,} elements, more than {MAX_ELEMENTS:,}")
    for name, value in (("x_left", x_left), ("x_right", x_right), ("y_bottom", y_bottom)):
        check_finite(name, value)
    check_positive("thickness", thickness)
    check_positive("length (x_right - x_left)", _difference(x_right, x_left))
    check_positive("grading_x", grading_x)
    check_positive("grading_y", grading_y)
    xs = graded_coordinates(x_left, x_right, int(nx), grading_x)
    ys = graded_coordinates(y_bottom, y_bottom + thickness, int(ny), grading_y)
    # Element sizes that round to zero or overflow: name the grading (or the length) given, not the
    # coordinates 'xs' / 'ys' that StripMesh.from_coordinates would name.
    for c, n, grading, name, length in ((xs, nx, grading_x, "grading_x", "length (x_right - x_left)"),
                                        (ys, ny, grading_y, "grading_y", "thickness")):
        if is_concrete(c) and not (np.all(np.isfinite(c)) and np.all(np.diff(np.asarray(c)) > 0)):
            field = length if is_concrete(grading) and float(grading) == 1.0 else name
            raise ValueError(f"field '{field}' gives elements of zero or non-finite size over {n} elements "
                             f"({name} = {grading!r})")
    return StripMesh.from_coordinates(xs, ys)


def _difference(a, b):
    if isinstance(a, jax.core.Tracer) or isinstance(b, jax.core.Tracer):
        return a - b
    return float(np.asarray(a)) - float(np.asarray(b))
