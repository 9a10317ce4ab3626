"""Matplotlib figures of meshes and load-path histories (imported lazily: the solver never needs it)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.collections import PolyCollection

__all__ = ["plot_mesh", "element_values_mean"]


def element_values_mean(values) -> np.ndarray:
    """Mean over the Gauss points of per-point values (n_el, gp) -> (n_el,)."""
    return np.asarray(values).mean(axis=1)


def plot_mesh(ax, x, elements, values=None, *, label="", cmap="viridis", edgecolor="0.3",
              linewidth=0.2, yscale=1.0):
    """Draw the mesh with current node positions ``x`` (n_nodes, 2); fill elements by ``values``.

    Returns the PolyCollection (pass it to ``fig.colorbar``). ``yscale`` exaggerates y for display.
    """
    x = np.asarray(x) * np.array([1.0, yscale])
    polys = x[np.asarray(elements)]
    coll = PolyCollection(polys, edgecolors=edgecolor, linewidths=linewidth,
                          facecolors="none" if values is None else None, cmap=cmap)
    if values is not None:
        coll.set_array(np.asarray(values))
    ax.add_collection(coll)
    ax.autoscale_view()
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)" if yscale == 1.0 else f"y (mm, x{yscale:g})")
    if label:
        ax.set_title(label)
    return coll


def figure(width_px=1200, height_px=700, dpi=100, **kwargs):
    """A figure of at least the given size in pixels."""
    return plt.subplots(figsize=(width_px / dpi, height_px / dpi), dpi=dpi, **kwargs)
