"""The strip model and its converged state.

A :class:`StripModel` is fixed data (mesh, material, phases, tools, contact formulation); a
:class:`SimState` is the state after a converged step (displacements, plastic history, internal forces,
pseudo-time, phase, contact history), threaded through the load steps explicitly. The functions below
read a converged state: the observations recorded per step, the reactions and the stresses.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..contact.formulations import AbstractContactFormulation
from ..contact.rigid import ContactState, initial_contact_state, max_penetration, pair_nodes
from ..contact.status import SLIP
from ..contact.tools import project
from ..fem.assembly import internal_force, mesh_geometry
from ..fem.element import ENHANCED_UPDATES, FORMULATIONS, QUADRATIC_FORMULATIONS, initial_point_state
from ..fem.loading import Phase, constraint_masks
from ..fem.material import J2Material
from ..fem.mesh import StripMesh
from ..numerics._checks import is_concrete

__all__ = ["StripModel", "SimState", "initial_state", "default_observe", "contact_force_field", "reactions",
           "stresses", "tool_positions"]


def _durations(value):
    """``StripModel.phase_seconds`` as an array of float64 (a traced one kept as it is)."""
    if value is None or isinstance(value, jax.Array):
        return value
    try:
        return np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"field 'phase_seconds' must hold one finite duration >= 0 per phase, got {value!r}") from None


class StripModel(eqx.Module):
    """A strip of elasto-plastic material under a sequence of phases of prescribed displacements,
    optionally in contact with rigid tools.

    Attributes:
        mesh: the strip mesh.
        material: the material law (one quadrature point).
        phases: the load path, one :class:`~jaxfric.fem.loading.Phase` per phase.
        formulation: "fbar" (default: F-bar Q4), "ans" (F-bar on assumed natural strains, for strips
            with the thickness along each element's second parent axis; the Nine and bead scenes'
            default), "anst" (assumed natural strains with a condensed through-thickness mode, same
            orientation), "eas" (enhanced strain Q1/E4) or "q4" (plain Q4, for elastic checks only); static.
            See :mod:`jaxfric.fem.element`.
        thickness_points: Gauss points through each element's thickness (2: the 2 x 2 rule; more
            integrate the stress through the thickness more finely, :func:`jaxfric.fem.element.gauss_rule`);
            static.
        tools: rigid tools (:class:`~jaxfric.contact.rigid.RigidTool`), one control per phase each.
        contact: the contact formulation, needed with tools
            (:class:`~jaxfric.contact.formulations.AbstractContactFormulation`:
            :class:`~jaxfric.contact.formulations.Penalty`,
            :class:`~jaxfric.contact.formulations.AugmentedLagrangian` or
            :class:`~jaxfric.contact.formulations.Complementarity`).
        enhanced_update: how ``anst`` and ``eas`` find their enhanced parameters within a Newton loop
            (static): "iterate" (default), updated with the Newton iterate from each linearisation (the
            enhanced-strain update of Simo and Armero: one material pass per element and iteration), or
            "local", condensed by a local Newton in every element evaluation (the same converged
            answer; :mod:`jaxfric.fem.element`).
        phase_seconds: None, or per phase its duration in seconds (an array, data: a stroke or a speed
            changes no program; 0: none): a step's duration is its share of its phase's, which gives the
            sliding speed of a friction law (:mod:`jaxfric.contact.friction`). None: every phase
            quasi-static.
    """

    mesh: StripMesh
    material: J2Material
    phases: tuple
    formulation: str = eqx.field(static=True, default="fbar")
    tools: tuple = ()
    contact: AbstractContactFormulation | None = None
    thickness_points: int = eqx.field(static=True, default=2)
    enhanced_update: str = eqx.field(static=True, default="iterate")
    phase_seconds: tuple | np.ndarray | jax.Array | None = eqx.field(default=None, converter=_durations)

    def __check_init__(self):
        if not isinstance(self.mesh, StripMesh):
            raise ValueError(f"field 'mesh' must be a StripMesh (jaxfric.strip_mesh), got {self.mesh!r}")
        if not (hasattr(self.material, "update") and hasattr(self.material, "init_state")):
            raise ValueError(f"field 'material' must be a material law such as J2Material, got {self.material!r}")
        if self.formulation not in FORMULATIONS:
            raise ValueError(f"field 'formulation' must be one of {FORMULATIONS}, got {self.formulation!r}")
        if self.mesh.order == 2 and self.formulation not in QUADRATIC_FORMULATIONS:
            raise ValueError(f"field 'formulation' = {self.formulation!r} is not available on elements quadratic "
                             f"along the strip (mesh order 2); choose one of {QUADRATIC_FORMULATIONS}")
        if not (isinstance(self.thickness_points, int | np.integer) and not isinstance(self.thickness_points, bool)
                and 2 <= self.thickness_points <= 16):
            raise ValueError(f"field 'thickness_points' must be an integer from 2 to 16, got {self.thickness_points!r}")
        if self.enhanced_update not in ENHANCED_UPDATES:
            raise ValueError(f"field 'enhanced_update' must be one of {ENHANCED_UPDATES}, got {self.enhanced_update!r}")
        if len(self.phases) == 0 or not all(isinstance(p, Phase) for p in self.phases):
            raise ValueError("field 'phases' must be a non-empty tuple of Phase")
        if isinstance(self.phase_seconds, np.ndarray) and (
                self.phase_seconds.shape != (len(self.phases),)
                or not np.all(np.isfinite(self.phase_seconds) & (self.phase_seconds >= 0))):
            raise ValueError(f"field 'phase_seconds' must hold one finite duration >= 0 per phase, got "
                             f"{self.phase_seconds!r}")
        names = [p.name for p in self.phases]
        if len(set(names)) != len(names):
            raise ValueError(f"field 'phases' has repeated phase names: {names}")
        constraint_masks(self.mesh.n_nodes, self.phases)  # validates node indices
        if self.tools and not isinstance(self.contact, AbstractContactFormulation):
            raise ValueError(f"field 'contact' must be a contact formulation (e.g. Penalty(eps_n, eps_t)) when "
                             f"there are tools, got {self.contact!r}")
        names = [t.name for t in self.tools]
        if len(set(names)) != len(names):
            raise ValueError(f"field 'tools' has repeated tool names: {names}")
        for tool in self.tools:
            if len(tool.controls) != len(self.phases):
                raise ValueError(f"tool {tool.name!r} has {len(tool.controls)} controls for "
                                 f"{len(self.phases)} phases")
            if max(tool.candidates) >= self.mesh.n_nodes or min(tool.candidates) < 0:
                raise ValueError(f"tool {tool.name!r}: field 'candidates' names nodes outside the mesh")
            if is_concrete((self.mesh.nodes, tool.geometry)):
                _check_tool_placement(tool, self.mesh.nodes)

    @property
    def n_phases(self) -> int:
        return len(self.phases)

    @property
    def force_tools(self) -> tuple:
        """Static indices of the tools that are force-driven in some phase (one unknown each)."""
        return tuple(k for k, t in enumerate(self.tools) if t.force_driven)


@jax.jit
def _project_all(geometry, points):
    # Compiled once per tool structure (:func:`_project_chunks` keeps the size): building many scenes
    # does not re-dispatch op by op. A tool geometry's leaves are arrays.
    return jax.vmap(project, in_axes=(None, 0, None))(geometry, points, jnp.zeros(2))


_PLACEMENT_CHUNK = 128   # points per call of _project_all


def _project_chunks(geometry, points: np.ndarray):
    """Gap and validity of ``points`` (n, 2) on ``geometry``, in calls of a fixed number of points (the
    last padded with its last point): tools of one structure (a scene's circles, whatever their
    candidates and the mesh) share one compiled projection."""
    n = points.shape[0]
    size = -(-n // _PLACEMENT_CHUNK) * _PLACEMENT_CHUNK
    padded = np.concatenate([points, np.broadcast_to(points[-1:], (size - n, 2))])
    parts = [_project_all(geometry, padded[k:k + _PLACEMENT_CHUNK]) for k in range(0, size, _PLACEMENT_CHUNK)]
    return (np.concatenate([np.asarray(p.gap) for p in parts])[:n],
            np.concatenate([np.asarray(p.valid) for p in parts])[:n])


def _check_tool_placement(tool, nodes) -> None:
    """Before any computation: a tool must not cut into the sheet at rest, and a force-driven tool
    must have a candidate node that projects on it (otherwise no force can ever balance it)."""
    idx = np.asarray(tool.candidates)
    gap, valid = _project_chunks(tool.geometry, np.asarray(nodes)[idx])
    scale = 1e-9 * max(1.0, float(np.max(np.abs(np.asarray(nodes)))))
    inside = valid & (gap < -scale)
    if inside.any():
        worst = int(np.argmin(np.where(inside, gap, np.inf)))
        raise ValueError(f"tool {tool.name!r} intersects the sheet at the start: node {int(idx[worst])} is "
                         f"{-gap[worst]:.3g} mm inside it; move the tool or the sheet so they at most touch")
    if tool.force_driven and not valid.any():
        raise ValueError(f"tool {tool.name!r} is force-driven but none of its candidate nodes projects on it, "
                         f"so it can never touch the sheet; check its geometry, 'candidates' and 'drive'")


class SimState(eqx.Module):
    """State after a converged step.

    Attributes:
        u: (n_nodes, 2) displacements (mm).
        material: material states at every Gauss point (leading axes (n_el, gp), gp = 2 thickness_points).
        f_int: (n_nodes, 2) internal forces (N/mm); at prescribed dofs these are the reactions.
        time: () pseudo-time.
        phase: () int32 index of the phase of the last step.
        contact: contact history and outputs (:class:`~jaxfric.contact.rigid.ContactState`), or None.
    """

    u: jax.Array
    material: Any
    f_int: jax.Array
    time: jax.Array
    phase: jax.Array
    contact: ContactState | None = None


@eqx.filter_jit
def initial_state(model: StripModel) -> SimState:
    """The state before the first step: zero displacements, virgin material at every Gauss point, the
    tools at their initial positions (with no force), pseudo-time 0 in phase 0.

    One compiled program where it is called outside one (a notebook, a test): run op by op, the tools'
    projections compiled some 200 one-primitive programs, 7.7 s on the Nine's spec mesh against 0.9 s
    (``JAXFRIC_CACHE_DIR=off``, a new process). Inside a run's programs it is inlined."""
    n_el = model.mesh.n_elements
    one = initial_point_state(model.material, model.formulation, model.enhanced_update,
                              model.mesh.nodes_per_element)
    n_points = 2 * model.thickness_points
    states = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (n_el, n_points) + a.shape), one)
    zeros = jnp.zeros((model.mesh.n_nodes, 2))
    contact = initial_contact_state(model.tools, model.mesh.nodes) if model.tools else None
    return SimState(u=zeros, material=states, f_int=zeros, time=jnp.array(0.0),
                    phase=jnp.array(0, jnp.int32), contact=contact)


def default_observe(model: StripModel, state: SimState) -> dict:
    """Reactions on the left and right ends (sums of f_int - f_c over their nodes), the largest eqps,
    and with tools: their positions and clamping forces, the largest penetration and the numbers of
    active (closed) and slipping pairs."""
    reaction = reactions(model, state)
    out = {
        "reaction_left": jnp.sum(reaction[model.mesh.left], axis=0),
        "reaction_right": jnp.sum(reaction[model.mesh.right], axis=0),
        "max_eqps": jnp.max(state.material.eqps),
    }
    if state.contact is not None:
        c = state.contact
        out.update(tool_position=c.q, tool_force=c.force,
                   max_penetration=max_penetration(c.status, c.gap),
                   n_active=jnp.sum(c.status > 0), n_slip=jnp.sum(c.status == SLIP))
    return out


def contact_force_field(model: StripModel, state: SimState) -> jax.Array:
    """(n_nodes, 2) contact forces on the sheet, f_c = R_N n + R_T t summed per node (N/mm)."""
    f_c = jnp.zeros_like(state.u)
    if state.contact is None:
        return f_c
    c = state.contact
    pair_f = c.rn[:, None] * c.normal + c.rt[:, None] * jnp.stack([-c.normal[:, 1], c.normal[:, 0]], 1)
    return f_c.at[pair_nodes(model.tools)].add(pair_f)


def reactions(model: StripModel, state: SimState) -> jax.Array:
    """(n_nodes, 2) reactions f_int - f_c: non-zero at prescribed dofs only, at convergence (N/mm)."""
    return state.f_int - contact_force_field(model, state)


def stresses(model: StripModel, state: SimState) -> jax.Array:
    """Kirchhoff stress (n_el, gp, 3, 3) (MPa) at every Gauss point of a converged state.

    Re-evaluating the update at the converged deformation from the converged history is exact: the
    trial state then lies on (or inside) the yield surface, so the return map is the identity.
    """
    return internal_force(model.mesh, model.material, model.formulation,
                          mesh_geometry(model.mesh, model.thickness_points),
                          state.u, state.material).tau


def tool_positions(state: SimState) -> jax.Array:
    return jnp.zeros(0) if state.contact is None else state.contact.q
