"""Node-to-rigid-surface contact of the sheet with rigid tools, inside the global Newton system.

A scene declares, per tool, its geometry (:class:`jaxfric.contact.tools.Tool`), its closing direction e_q,
its candidate sheet nodes, its friction coefficient per phase, and per phase how it moves:

- :class:`Move` (displacement-driven): q = q_start + a + tau (b - a), relative to its position at the
  start of the phase (``Move(0, 0)`` holds it where it is);
- :class:`Force` (force-driven, spec 1.8): its position q is an extra unknown, balanced by the
  prescribed closing force P(tau) = P_0 + tau (P_end - P_0), with P_0 the tool's clamping force at
  the start of the phase unless given.

Global system (unknowns x = (u, q_f), q_f the positions of the tools that are force-driven in some
phase; a scene with none has no extra unknown):

    R_u = f_int(u) - f_c(u, q)                        (free dofs; prescribed dofs: u - u_presc)
    R_q = sum_{pairs of the tool} e_q . f_c,a - P     (force-driven phase; otherwise q - q_presc)

with f_c,a = R_N n + R_T t the force on the sheet at pair a (spec 1.4). The contact forces depend on
each pair's node and tool only, so dR_u/du keeps the block-tridiagonal structure (a 2x2 block per
pair on the diagonal) and the tools add a border (:class:`jaxfric.numerics.linalg.Bordered`). The Jacobian of
every pair force is the chain rule of the projection's derivatives (n, t, g_N and the slip with respect to the
node and the tool position, in closed form: :meth:`jaxfric.contact.pair_batches.PairTool.jacobian`) and the
pair law's with respect to g_N and the slip (``jax.jacfwd``).

A force-driven tool that has lost every contact cannot balance its force, and its balance row no
longer depends on its position (a singular Newton matrix). Its row then asks it to close the nearest
gap (see :func:`jaxfric.contact.system._tool_rows`), so one Newton step puts it back on the sheet, where the
balance row takes over; with P = 0 it rests touching the sheet with zero force.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..numerics._checks import check_nonnegative, is_concrete
from .friction import FrictionLaw, tributary_lengths
from .laws import augmented_pair
from .pair_batches import PairTool, map_pairs
from .preselection import expand, gather
from .status import OPEN
from .tools import GAP_OPEN, Tool

__all__ = ["Move", "Force", "RigidTool", "ContactState", "ContactStep", "PairResult", "initial_contact_state",
           "evaluate_pairs", "tool_forces", "split_pairs", "pair_nodes", "pair_mu", "pair_friction",
           "pair_speeds", "pair_speed_periods", "has_friction_law", "max_penetration"]


class Move(eqx.Module):
    """Displacement-driven phase: q = q_start + start + tau (end - start) (mm, along e_q)."""

    start: jax.Array
    end: jax.Array

    def __init__(self, start=0.0, end=0.0):
        self.start = jnp.asarray(start, jnp.float64)
        self.end = jnp.asarray(end, jnp.float64)

    def position(self, q_start, tau):
        return q_start + self.start + tau * (self.end - self.start)


class Force(eqx.Module):
    """Force-driven phase: closing force P = P_0 + tau (end - P_0) (N/mm); P_0 = ``start``, or the
    tool's clamping force at the start of the phase when ``start`` is None."""

    end: jax.Array
    start: jax.Array | None

    def __init__(self, end, start=None):
        check_nonnegative("force end", end)
        if start is not None:
            check_nonnegative("force start", start)
        self.end = jnp.asarray(end, jnp.float64)
        self.start = None if start is None else jnp.asarray(start, jnp.float64)

    def force(self, f_start, tau):
        p0 = f_start if self.start is None else self.start
        return p0 + tau * (self.end - p0)


class RigidTool(eqx.Module):
    """A rigid tool in a scene.

    Attributes:
        name: static name (outputs).
        geometry: the tool at rest.
        drive: (2,) unit closing direction e_q (towards the sheet).
        candidates: static tuple of candidate sheet-node indices.
        controls: one :class:`Move` or :class:`Force` per phase.
        mu: (n_phases,) friction coefficient per phase.
        frictional: static; whether the tool's pairs carry a friction term. Declared, or when not
            given, False only for a concrete mu of 0 in every phase (a traced mu keeps the term). A tool
            declared frictional with mu = 0 builds the same program as with any other mu, so a
            derivative or a fit can start from mu = 0.
        friction: None (Coulomb: mu) or a :class:`~jaxfric.contact.friction.FrictionLaw` of the contact
            pressure and sliding speed about mu (needs a frictional tool).
        capacity: static; None (every candidate's pair is evaluated at every Newton iterate), or how
            many candidates nearest to the tool each load step evaluates
            (:mod:`jaxfric.contact.preselection`, :func:`~jaxfric.contact.preselection.tool_capacity`).
    """

    name: str = eqx.field(static=True)
    geometry: Tool
    drive: jax.Array
    candidates: tuple = eqx.field(static=True)
    controls: tuple
    mu: jax.Array
    frictional: bool = eqx.field(static=True)
    friction: FrictionLaw | None = None
    capacity: int | None = eqx.field(static=True, default=None)

    def __init__(self, name, geometry: Tool, drive, candidates, controls, mu, frictional: bool | None = None,
                 friction: FrictionLaw | None = None, capacity: int | None = None):
        self.name = str(name)
        self.geometry = geometry
        self.drive = jnp.asarray(drive, jnp.float64)
        self.candidates = tuple(int(a) for a in np.asarray(candidates).ravel())
        self.controls = tuple(controls)
        # Undeclared: decided from the argument as given (inside jit, even a converted constant is a tracer).
        if frictional is None:
            frictional = (not is_concrete(mu)) or bool(np.any(np.asarray(mu) > 0))
        if isinstance(frictional, np.bool_):
            frictional = bool(frictional)
        if not isinstance(frictional, bool):
            raise ValueError(f"tool {self.name!r}: field 'frictional' must be True, False or None, got {frictional!r}")
        self.frictional = frictional
        mu = jnp.asarray(mu, jnp.float64)
        self.mu = jnp.broadcast_to(mu, (len(self.controls),)) if mu.ndim == 0 else mu
        self.friction = friction
        self.capacity = None if capacity is None else int(capacity)

    def __check_init__(self):
        if self.drive.shape != (2,):
            raise ValueError(f"tool {self.name!r}: field 'drive' must be a 2-vector")
        if is_concrete(self.drive) and abs(float(jnp.linalg.norm(self.drive)) - 1.0) > 1e-12:
            raise ValueError(f"tool {self.name!r}: field 'drive' must be a unit vector, got {self.drive}")
        if not self.candidates:
            raise ValueError(f"tool {self.name!r}: field 'candidates' is empty")
        if self.capacity is not None and not 1 <= self.capacity < len(self.candidates):
            raise ValueError(f"tool {self.name!r}: field 'capacity' must be None or from 1 to the number of "
                             f"candidates less one ({len(self.candidates) - 1}), got {self.capacity}")
        if not all(isinstance(c, (Move, Force)) for c in self.controls):
            raise ValueError(f"tool {self.name!r}: field 'controls' must hold one Move or Force per phase")
        if self.mu.shape != (len(self.controls),):
            raise ValueError(f"tool {self.name!r}: field 'mu' must be a scalar or one value per phase")
        if is_concrete(self.mu) and not np.all(np.isfinite(self.mu) & (np.asarray(self.mu) >= 0)):
            raise ValueError(f"tool {self.name!r}: field 'mu' must be finite and >= 0, got {self.mu}")
        if self.friction is not None and not isinstance(self.friction, FrictionLaw):
            raise ValueError(f"tool {self.name!r}: field 'friction' must be None or a FrictionLaw, got "
                             f"{type(self.friction).__name__}")
        if self.friction is not None and not self.frictional:
            raise ValueError(f"tool {self.name!r}: field 'friction' (a friction law) on a tool declared "
                             f"frictionless (frictional=False)")
        if not self.frictional and is_concrete(self.mu) and np.any(np.asarray(self.mu) > 0):
            raise ValueError(f"tool {self.name!r}: field 'mu' = {self.mu} on a tool declared frictionless "
                             f"(frictional=False); declare it frictional or give mu = 0")

    @property
    def force_driven(self) -> bool:
        """Static: whether any phase drives this tool by a force (it then owns an extra unknown)."""
        return any(isinstance(c, Force) for c in self.controls)


class ContactState(eqx.Module):
    """Contact history and outputs after a converged step (m pairs, n_t tools).

    Attributes:
        q: (n_t,) tool positions along e_q from rest (mm).
        q_start, f_start: (n_t,) position and clamping force at the start of the current phase.
        force: (n_t,) clamping force sum_a e_q . f_c,a (N/mm).
        rn, rt: (m,) normal and tangential forces (N/mm); rt is R_T,n of the next step.
        zeta: (m,) arc-length coordinate of each node's projection (tool frame, mm).
        gap: (m,) normal gap (mm; GAP_OPEN when the node projects on no primitive).
        normal: (m, 2) tool normal at the projection.
        status: (m,) int8 0 open, 1 stick, 2 slip.
        speed: (m,) sliding speed over the step (mm/s; 0 in steps without a duration), which a friction
            law reads in the next step (:mod:`jaxfric.contact.friction`).
    """

    q: jax.Array
    q_start: jax.Array
    f_start: jax.Array
    force: jax.Array
    rn: jax.Array
    rt: jax.Array
    zeta: jax.Array
    gap: jax.Array
    normal: jax.Array
    status: jax.Array
    speed: jax.Array


class ContactStep(eqx.Module):
    """Everything the contact terms of one load step depend on (differentiable data)."""

    tools: tuple
    law: Any             # the contact formulation (jaxfric.contact.formulations); pair laws read its penalties
    mu: tuple            # per tool, () coefficient of this phase
    lam_n: tuple         # per tool, (n_k,) frozen normal multipliers (0 for the penalty method; exact
                         # contact: the last converged R_N, which only guesses Lemke's starting basis)
    lam_t: tuple         # per tool, (n_k,) frozen tangential multipliers (R_T,n for the penalty method)
    u_ref: tuple         # per tool, (n_k, 2) candidate displacements at the slip reference configuration
    q_ref: jax.Array     # (n_t,) tool positions at the slip reference configuration
    q_presc: jax.Array   # (n_t,) prescribed positions (used where not force-driven)
    force: jax.Array     # (n_t,) prescribed forces (used where force-driven)
    force_mask: jax.Array  # (n_t,) bool: force-driven in this phase
    dt: Any = 0.0        # () duration of the step (s; 0: none): the pairs' sliding speeds after it
    speed: tuple = ()    # per tool, (n_k,) sliding speeds of the last step (mm/s), which a friction law reads
    near: tuple = ()     # per tool, (capacity,) the candidates this step evaluates, or None: all
                         # (jaxfric.contact.preselection); () for none at all
    clearance: tuple = ()  # per tool, () the smallest distance bound of the others at the step's start (mm)

    def selected(self, k: int):
        """The candidates of tool k this step evaluates (None: all)."""
        return self.near[k] if self.near else None

    def pair_displacements(self, u: jax.Array) -> jax.Array:
        """(m, 2) the displacement of every pair's node, tool after tool, from ``u`` (n_nodes, 2)."""
        return u[pair_nodes(self.tools)]


class PairResult(NamedTuple):
    """Per tool: forces on the sheet and their derivatives at every candidate pair."""

    f: jax.Array          # (n_k, 2) force on the sheet
    df_dx: jax.Array      # (n_k, 2, 2) d f / d x_node
    df_dq: jax.Array      # (n_k, 2) d f / d q
    rn: jax.Array
    rt: jax.Array
    status: jax.Array
    gap: jax.Array
    zeta: jax.Array
    normal: jax.Array
    slip: jax.Array       # slip since the reference configuration (mm)


def _pair_law(tool: PairTool, law, gap, slip, valid, mu, lam_n, lam_t, length, speed):
    """The pair law's forces (:class:`jaxfric.contact.laws.PairForce`) at the gap and slip of a projection."""
    smoothing = law.smoothing if law.smooth else None
    if tool.frictional:
        friction = tool.friction
        coefficient = mu if friction is None else (lambda rn: friction.coefficient(mu, rn / length, speed))
        return augmented_pair(gap, slip, lam_n, lam_t, coefficient, law.eps_n, law.eps_t, valid, smoothing)
    # static: a frictionless tool builds no tangential term at all
    return augmented_pair(gap, 0.0, lam_n, 0.0, 0.0, law.eps_n, 0.0, valid, smoothing)


def _pair_outputs(proj, force):
    """The force on the sheet, R_N n + R_T t, and the pair's outputs."""
    f = force.normal * proj.normal + force.tangential * proj.tangent
    return f, (force.normal, force.tangential, force.status, proj.gap, proj.zeta, proj.normal,
               proj.zeta_increment)


def _pair_and_jacobian(tool: PairTool, law, X, u, q, mu, lam_n, lam_t, u_ref, q_ref, length, speed):
    """:func:`_pair_outputs` and d f / d(u, q) (2, 3) by the chain rule: the projection's derivatives in
    closed form (:meth:`PairTool.jacobian`), the law's with respect to (g_N, slip) by forward mode,

        d f = n d R_N + t d R_T + R_N d n + R_T d t,   d R = dR/d(g_N, s) d(g_N, s),

    the same derivative as forward mode through the whole pair, for a smaller program."""
    proj = tool.projection(X, u, u_ref, q, q_ref)

    def law_of(gs):
        force = _pair_law(tool, law, gs[0], gs[1], proj.valid, mu, lam_n, lam_t, length, speed)
        return jnp.stack([force.normal, force.tangential]), force

    d_force, force = jax.jacfwd(law_of, has_aux=True)(jnp.stack([proj.gap, proj.zeta_increment]))
    J = tool.jacobian(proj)                      # rows n_x, n_y, g_N, slip; columns u_x, u_y, q
    d_r = d_force @ J[2:]                        # (2, 3): d R_N, d R_T
    d_n = J[:2]
    d_t = jnp.stack([-d_n[1], d_n[0]])           # t = (-n_y, n_x)
    df = (proj.normal[:, None] * d_r[0] + proj.tangent[:, None] * d_r[1]
          + force.normal * d_n + force.tangential * d_t)
    return _pair_outputs(proj, force), df


def _pair(tool: PairTool, law, X, u, q, mu, lam_n, lam_t, u_ref, q_ref, length=None, speed=0.0):
    proj = tool.projection(X, u, u_ref, q, q_ref)
    return _pair_outputs(proj, _pair_law(tool, law, proj.gap, proj.zeta_increment, proj.valid, mu, lam_n, lam_t,
                                         length, speed))


def evaluate_pairs(step: ContactStep, nodes_ref: jax.Array, u: jax.Array, q: jax.Array,
                   jacobian: bool) -> list:
    """Forces (and with ``jacobian`` their derivatives) of every pair, tool by tool; tools of one
    structure are evaluated as one batch (:func:`jaxfric.contact.pair_batches.map_pairs`).

    Args:
        step: the contact data of this step.
        nodes_ref, u: (n_nodes, 2) reference node positions and displacements (mm), kept apart for an
            accurate gap (see :func:`jaxfric.contact.tools.project`).
        q: (n_t,) current tool positions (mm).
    """
    def pair_fn(tool: PairTool, tool_values, pair_values):
        q_k, mu, q_ref = tool_values
        u_a, X_a, lam_n, lam_t, u_ref, length, speed = pair_values

        if jacobian:  # d f / d x_node = d f / d u_node
            (f, aux), df = _pair_and_jacobian(tool, step.law, X_a, u_a, q_k, mu, lam_n, lam_t, u_ref, q_ref, length,
                                              speed)
            return f, aux, df[:, :2], df[:, 2]
        return (*_pair(tool, step.law, X_a, u_a, q_k, mu, lam_n, lam_t, u_ref, q_ref, length, speed), None, None)

    def pair_args(k):
        tool = step.tools[k]
        idx = np.asarray(tool.candidates)
        law = tool.friction is not None
        lengths = tributary_lengths(nodes_ref[idx]) if law else jnp.ones(len(idx))
        speeds = step.speed[k] if law else jnp.zeros(len(idx))
        return tuple(gather(step.selected(k), a) for a in (u[idx], nodes_ref[idx], step.lam_n[k], step.lam_t[k],
                                                            step.u_ref[k], lengths, speeds))

    results = map_pairs(step.tools, pair_fn, lambda k: (q[k], step.mu[k], step.q_ref[k]), pair_args)
    out = []
    for k, (f, aux, dfdx, dfdq) in enumerate(results):
        near, n_k = step.selected(k), len(step.tools[k].candidates)
        if jacobian:
            dfdx, dfdq = expand(near, (dfdx, dfdq), n_k)
        # The pairs left out are open: no force, the open pair's gap (jaxfric.contact.preselection).
        f, rn, rt, status, gap, zeta, normal, slip = (expand(near, a, n_k, GAP_OPEN if i == 4 else 0.0)
                                                      for i, a in enumerate((f, *aux)))
        out.append(PairResult(f, dfdx, dfdq, rn, rt, status, gap, zeta, normal, slip))
    return out


def tool_forces(step: ContactStep, pairs: list) -> jax.Array:
    """(n_t,) clamping force of every tool: sum over its pairs of e_q . f_c (N/mm)."""
    return jnp.stack([jnp.sum(p.f @ tool.drive) for tool, p in zip(step.tools, pairs)])


def initial_contact_state(tools, nodes: jax.Array) -> ContactState:
    """Tools at rest, no force; zeta of every candidate's projection in the reference configuration."""
    n_t = len(tools)
    zeros_t = jnp.zeros(n_t)
    projections = map_pairs(tools, lambda tool, _, X: tool.project(X, jnp.zeros(2)), lambda k: (),
                            lambda k: nodes[np.asarray(tools[k].candidates)], friction=False)
    zeta, gap, normal = (jnp.concatenate([getattr(p, f) for p in projections]) for f in ("zeta", "gap", "normal"))
    m = zeta.shape[0]
    return ContactState(q=zeros_t, q_start=zeros_t, f_start=zeros_t, force=zeros_t, rn=jnp.zeros(m),
                        rt=jnp.zeros(m), zeta=zeta, gap=gap, normal=normal, status=jnp.full(m, OPEN, jnp.int8),
                        speed=jnp.zeros(m))


def pair_nodes(tools) -> np.ndarray:
    """(m,) sheet node of every candidate pair, tool after tool (static)."""
    return np.concatenate([np.asarray(t.candidates) for t in tools])


def pair_mu(tools, mu) -> jax.Array:
    """(m,) friction coefficient of every candidate pair, from ``mu`` per tool (tool after tool)."""
    return jnp.concatenate([jnp.full(len(t.candidates), mu[k]) for k, t in enumerate(tools)])


def has_friction_law(tools) -> bool:
    """Static: whether any tool carries a friction law (:mod:`jaxfric.contact.friction`)."""
    return any(t.friction is not None for t in tools)


def pair_speeds(step: ContactStep) -> jax.Array:
    """(m,) the pairs' sliding speeds of the last step (mm/s), tool after tool."""
    return jnp.concatenate(step.speed) if step.speed else jnp.zeros(sum(len(t.candidates) for t in step.tools))


def pair_speed_periods(tools) -> jax.Array:
    """(m,) the time constant of the speed filter of every candidate pair (s), tool after tool: its tool's
    friction law's ``period``, 0 without a law (:func:`jaxfric.contact.friction.sliding_speed`)."""
    return jnp.concatenate([jnp.full(len(t.candidates), 0.0 if t.friction is None else t.friction.period)
                            for t in tools])


def pair_friction(tools, mu, nodes_ref, rn, speed=None) -> jax.Array:
    """(m,) friction coefficient of every candidate pair at normal forces ``rn`` (m,) (N/mm) and sliding
    speeds ``speed`` (m,) (mm/s; None: at rest): ``mu`` per tool, through a tool's friction law where it
    has one (:mod:`jaxfric.contact.friction`); ``nodes_ref``: the mesh's reference node positions."""
    base = pair_mu(tools, mu)
    if not has_friction_law(tools):
        return base
    parts, start = [], 0
    for k, t in enumerate(tools):   # static loop
        n_k = len(t.candidates)
        b = base[start:start + n_k]
        if t.friction is not None:
            lengths = tributary_lengths(nodes_ref[np.asarray(t.candidates)])
            v = 0.0 if speed is None else speed[start:start + n_k]
            b = t.friction.coefficient(b, jnp.maximum(rn[start:start + n_k], 0.0) / lengths, v)
        parts.append(b)
        start += n_k
    return jnp.concatenate(parts)


def max_penetration(status, gap) -> jax.Array:
    """Largest penetration max(0, -g_N) over the closed pairs (mm)."""
    return jnp.max(jnp.where(status > 0, jnp.maximum(-gap, 0.0), 0.0))


def split_pairs(tools, values):
    """Split a per-pair array (m, ...) into per-tool pieces."""
    sizes = np.cumsum([len(t.candidates) for t in tools])[:-1]
    return tuple(jnp.split(values, sizes))

