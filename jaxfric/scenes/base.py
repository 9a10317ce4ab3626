"""What every benchmark scene provides (benchmarks spec sections 0 and 6; outputs spec).

A scene module (``flat_die``, ``bead``, ``nine``, ``blankholder``) defines a frozen config dataclass
whose fields are the spec's config keys with their defaults, a ``VARIANTS`` mapping from variant name to
field overrides, and ``build(config, algorithm, variant) -> Scene``. A :class:`Scene` is everything a
run needs: the model (jit-able), the static functions that turn a converged state into history columns
and into the contact snapshot of ``contact.npz``, and the output metadata (instants, steady window, plot
region).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from ..loadpath.controller import StepControl
from ..loadpath.model import StripModel
from ..numerics.newton import NewtonOptions

__all__ = ["Scene"]

@dataclasses.dataclass(frozen=True)
class Scene:
    """One runnable scene variant.

    Attributes:
        name, variant, algorithm: identifiers (outputs spec section 1).
        config: the resolved config dataclass (every spec value of the run).
        model: the :class:`~jaxfric.loadpath.model.StripModel` (tools in the spec's tool order).
        observe: static ``observe(model, state) -> dict`` of per-step scalars: at least
            ``drawing_displacement, drawing_force, clamping_force, tool_position, max_penetration,
            n_active, n_slip`` and the scene's extra columns (benchmarks spec, scene Outputs).
        snapshot: static ``snapshot(model, state) -> dict`` of the arrays of ``contact.npz`` per instant
            (``x, eqps, rn, rt, normal, gap, mu, status, tool_offset``).
        control: the step controller settings.
        phase_names: the scene's phase vocabulary, in order.
        tool_names: tool names in tool order (``contact.npz`` ``tool_names``).
        clamping_tool: index of the clamping tool.
        instants: instant names in scene order.
        steady_window: (a, b) in drawing displacement (mm).
        roi: plot region (x_min, x_max, y_min, y_max) in mm.
        y_scale: display exaggeration of y in the figures (1: equal aspect).
        parameters: JSON-ready resolved configuration (``summary.json`` ``parameters``).
        newton: Newton's options for this scene (default: the spec's 25 iterations per attempt).
    """

    name: str
    variant: str
    algorithm: str
    config: object
    model: StripModel
    observe: Callable
    snapshot: Callable
    control: StepControl
    phase_names: tuple
    tool_names: tuple
    clamping_tool: int
    instants: tuple
    steady_window: tuple
    roi: tuple
    y_scale: float
    parameters: dict
    newton: NewtonOptions = NewtonOptions()
