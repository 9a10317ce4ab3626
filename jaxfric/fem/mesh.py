"""Structured quadrilateral meshes of strips, numbered column by column.

Node (i, j), i = 0..nx along x and j = 0..ny through the thickness, has index ``i*(ny+1) + j``;
element (i, j) has index ``i*ny + j`` and nodes (i,j), (i+1,j), (i+1,j+1), (i,j+1) counter-clockwise.
With this numbering the stiffness of a strip is block-tridiagonal in blocks of ``2*(ny+1)`` dofs,
one block per column of nodes, which is what :mod:`jaxfric.numerics.linalg` exploits.

``order=2``: elements quadratic along the strip (six nodes, linear through the thickness). Each element
has a column of mid-side nodes, so the node columns are c = 0..2 nx (corner columns even, mid columns
odd) and element (i, j) has nodes (2i,j), (2i+1,j), (2i+2,j), (2i+2,j+1), (2i+1,j+1), (2i,j+1),
counter-clockwise. An element couples three node columns, so the stiffness is block-tridiagonal in
blocks of two columns, (2i, 2i+1) for block i; the last block pairs the strip's last column with a
padding column of nodes that no element uses (:attr:`StripMesh.padding`, beyond the strip's right end),
which the assembly holds at rest by a unit spring (:mod:`jaxfric.fem.assembly`). The node sets
(``left``, ``right``, ``bottom``, ``top``) never contain it.

Only ``nx``, ``ny`` and ``order`` are static; node coordinates are array leaves, so a length or a thickness
can be a traced (differentiated) parameter.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..numerics._checks import check_finite, check_finite_array, check_int, check_positive, is_concrete

__all__ = ["StripMesh", "strip_mesh", "graded_coordinates", "connectivity", "block_rows", "MAX_ELEMENTS", "ORDERS"]

MAX_ELEMENTS = 1_000_000  # nx * ny: beyond any mesh a 2D strip needs, and far from int32 limits
ORDERS = (1, 2)           # the elements' polynomial order along the strip


class StripMesh(eqx.Module):
    """A structured ``nx`` x ``ny`` mesh of quadrilaterals, numbered column by column.

    Attributes:
        nodes: (n_nodes, 2) reference coordinates X in mm, node (i, j) at row ``i*(ny+1)+j`` (i: the node
            column, 0 .. ``order`` nx, then the padding column with ``order=2``).
        nx, ny: number of element columns (along x) and rows (through the thickness); static.
        order: 1, bilinear Q4 elements; 2, elements quadratic along the strip (module docstring); static.
    """

    nodes: jax.Array
    nx: int = eqx.field(static=True)
    ny: int = eqx.field(static=True)
    order: int = eqx.field(static=True, default=1)

    def __check_init__(self):
        for name in ("nx", "ny"):
            check_int(name, getattr(self, name))
        if self.order not in ORDERS:
            raise ValueError(f"mesh field 'order' must be one of {ORDERS}, got {self.order!r}")
        expected = (self.n_nodes, 2)
        if tuple(self.nodes.shape) != expected:
            raise ValueError(f"mesh field 'nodes' must have shape {expected}, got {self.nodes.shape}")
        check_finite_array("nodes", self.nodes)

    # ---- sizes (static) -------------------------------------------------------------------------
    @property
    def n_columns(self) -> int:
        """Node columns of the strip, ``order`` nx + 1 (without the padding column)."""
        return self.order * self.nx + 1

    @property
    def n_stored_columns(self) -> int:
        """Node columns stored, ``order`` (nx + 1): the strip's and, with ``order=2``, the padding column."""
        return self.order * (self.nx + 1)

    @property
    def n_nodes(self) -> int:
        return self.n_stored_columns * (self.ny + 1)

    @property
    def nodes_per_element(self) -> int:
        return 2 * (self.order + 1)

    @property
    def n_elements(self) -> int:
        return self.nx * self.ny

    @property
    def n_dofs(self) -> int:
        return 2 * self.n_nodes

    @property
    def block_size(self) -> int:
        """Dofs per block of the block-tridiagonal stiffness: ``order`` columns of nodes."""
        return 2 * self.order * (self.ny + 1)

    @property
    def num_blocks(self) -> int:
        """Blocks of the block-tridiagonal stiffness, nx + 1."""
        return self.nx + 1

    def block_rows(self, nodes) -> tuple[np.ndarray, np.ndarray]:
        """For node indices ``nodes`` (n,): their block of the stiffness (n,) and their x and y dofs' rows
        within it (n, 2) (:func:`block_rows`)."""
        return block_rows(nodes, self.ny, self.order)

    # ---- topology (static numpy, computed from nx, ny) ------------------------------------------
    def node_index(self, i, j):
        return np.asarray(i) * (self.ny + 1) + np.asarray(j)

    @property
    def elements(self) -> np.ndarray:
        """(n_el, 4 or 6) int64 connectivity, counter-clockwise from the lower-left node (:func:`connectivity`)."""
        return connectivity(self.nx, self.ny, self.order)

    @property
    def left(self) -> np.ndarray:
        """Nodes on x = x_left (column 0), bottom to top."""
        return self.node_index(0, np.arange(self.ny + 1))

    @property
    def right(self) -> np.ndarray:
        """Nodes on x = x_right (the strip's last column), bottom to top."""
        return self.node_index(self.n_columns - 1, np.arange(self.ny + 1))

    @property
    def bottom(self) -> np.ndarray:
        """Bottom-surface nodes (j = 0), left to right."""
        return self.node_index(np.arange(self.n_columns), 0)

    @property
    def top(self) -> np.ndarray:
        """Top-surface nodes (j = ny), left to right."""
        return self.node_index(np.arange(self.n_columns), self.ny)

    @property
    def padding(self) -> np.ndarray:
        """The padding column's nodes (``order=2``; none otherwise): in no element and no node set."""
        return self.node_index(np.arange(self.n_columns, self.n_stored_columns)[:, None],
                               np.arange(self.ny + 1)[None, :]).ravel()

    def node_set(self, name: str) -> np.ndarray:
        """Named node set: 'left', 'right', 'bottom', 'top' or 'all' (the strip's nodes)."""
        if name == "all":
            return np.arange(self.n_columns * (self.ny + 1))
        if name not in ("left", "right", "bottom", "top"):
            raise ValueError(f"unknown node set {name!r}; use 'left', 'right', 'bottom', 'top' or 'all'")
        return getattr(self, name)

    @classmethod
    def from_coordinates(cls, xs, ys, order: int = 1) -> StripMesh:
        """Tensor-product mesh from 1D node coordinates ``xs`` (nx+1,) and ``ys`` (ny+1,); with ``order=2``
        ``xs`` are the element ends, and the mid-side columns are put half way between them."""
        xp = _array_module(xs, ys)
        xs = xp.asarray(xs, dtype=np.float64)
        ys = xp.asarray(ys, dtype=np.float64)
        for name, c in (("xs", xs), ("ys", ys)):
            if c.ndim != 1 or c.shape[0] < 2:
                raise ValueError(f"mesh field '{name}' must be a 1D array of at least 2 coordinates")
            if xp is np and not np.all(np.diff(c) > 0):
                raise ValueError(f"mesh field '{name}' must be strictly increasing")
        nx = xs.shape[0] - 1
        if order == 2:
            # Corner and mid-side columns interleaved, then the padding column one half element further.
            mid = 0.5 * (xs[:-1] + xs[1:])
            pad = xs[-1:] + 0.5 * (xs[-1:] - xs[-2:-1])
            xs = xp.concatenate([xp.stack([xs[:-1], mid], axis=1).ravel(), xs[-1:], pad])
        X, Y = xp.meshgrid(xs, ys, indexing="ij")
        nodes = jnp.asarray(xp.stack([X.ravel(), Y.ravel()], axis=1))
        return cls(nodes=nodes, nx=nx, ny=ys.shape[0] - 1, order=order)


def connectivity(nx: int, ny: int, order: int = 1) -> np.ndarray:
    """(nx ny, 2 (order + 1)) int64 nodes of every element of an ``nx`` x ``ny`` strip of elements of
    ``order`` along it, counter-clockwise from the lower-left node (module docstring): the numbering alone,
    with no coordinates."""
    i_grid, j_grid = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    c, j = order * i_grid.ravel(), j_grid.ravel()
    along = range(order + 1)
    return np.stack([(c + k) * (ny + 1) + j for k in along]
                    + [(c + order - k) * (ny + 1) + j + 1 for k in along], axis=1).astype(np.int64)


def block_rows(nodes, ny: int, order: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """For node indices ``nodes`` (n,) of a strip with ``ny`` layers and elements of ``order`` along it: their
    block of the block-tridiagonal stiffness (n,), ``order`` node columns per block, and their x and y dofs'
    rows within it (n, 2)."""
    nodes = np.asarray(nodes)
    column, j = nodes // (ny + 1), nodes % (ny + 1)
    within = (column % order) * (ny + 1) + j
    return column // order, 2 * within[:, None] + np.arange(2)[None, :]


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
               grading_x=1.0, grading_y=1.0, order: int = 1) -> StripMesh:
    """Mesh of the strip [x_left, x_right] x [y_bottom, y_bottom + thickness] (mm).

    Args:
        x_left, x_right: strip ends (mm); x_right > x_left.
        y_bottom: y of the bottom surface (mm).
        thickness: strip thickness t > 0 (mm).
        nx, ny: elements along x and through the thickness (>= 1).
        grading_x, grading_y: ratio of successive element sizes (1 = uniform).
        order: the elements' order along the strip, 1 (Q4) or 2 (module docstring).
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
    return StripMesh.from_coordinates(xs, ys, order)


def _difference(a, b):
    if isinstance(a, jax.core.Tracer) or isinstance(b, jax.core.Tracer):
        return a - b
    return float(np.asarray(a)) - float(np.asarray(b))
