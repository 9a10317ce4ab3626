"""Prescribed motions, Dirichlet conditions and phases of a load path.

Pseudo-time: phase k (numbered from 0 here) covers [k, k+1]; inside it the phase-local time
tau = t - k runs from 0 to 1 and every prescribed motion is a function of tau. A phase lists the
Dirichlet conditions active during it, so the set of constrained dofs can change from phase to
phase (for example a right end held during clamping and pulled during drawing).

Motion parameters are array leaves: an imposed stretch or a rotation angle can be differentiated.
A phase's nominal increments are array leaves too, so that a longer stroke or finer increments reuse
the compiled program. Node lists, constrained components and the number of increment segments are
static structure.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..numerics._checks import check_finite, check_finite_array, is_concrete

__all__ = ["Motion", "Ramp", "Affine", "RigidMotion", "DirichletBC", "Phase", "with_steps", "constraint_masks",
           "prescribed_values", "Schedule", "schedule"]


def _vec2(name, value):
    try:
        arr = jnp.asarray(value, dtype=jnp.float64)
    except (TypeError, ValueError):
        raise ValueError(f"field '{name}' must be a 2-vector of numbers, got {value!r}") from None
    if arr.shape != (2,):
        raise ValueError(f"field '{name}' must be a 2-vector, got shape {arr.shape}")
    check_finite_array(name, arr)
    return arr


class Motion(eqx.Module):
    """A prescribed displacement field: ``motion(X, tau) -> u`` for reference points X (n, 2)."""

    def __call__(self, X, tau):
        raise NotImplementedError


class Ramp(Motion):
    """Uniform displacement u = start + tau (end - start) (mm)."""

    start: jax.Array
    end: jax.Array

    def __init__(self, start=(0.0, 0.0), end=(0.0, 0.0)):
        self.start = _vec2("start", start)
        self.end = _vec2("end", end)

    def __call__(self, X, tau):
        u = self.start + tau * (self.end - self.start)
        return jnp.broadcast_to(u, X.shape)


class Affine(Motion):
    """Affine displacement field u = tau (H X + c): a homogeneous deformation gradient I + tau H."""

    gradient: jax.Array
    shift: jax.Array

    def __init__(self, gradient, shift=(0.0, 0.0)):
        self.gradient = jnp.asarray(gradient, dtype=jnp.float64)
        if self.gradient.shape != (2, 2):
            raise ValueError(f"field 'gradient' must be a 2x2 matrix, got shape {self.gradient.shape}")
        self.shift = _vec2("shift", shift)

    def __call__(self, X, tau):
        return tau * (X @ self.gradient.T + self.shift)


class RigidMotion(Motion):
    """Rigid rotation about ``pivot`` by angle theta(tau), then translation s(tau), both linear in tau.

        x = pivot + Q(theta) (X - pivot) + s,   Q(theta) = [[cos, -sin], [sin, cos]]  (counter-clockwise)

    Angles in radians, shifts in mm.
    """

    pivot: jax.Array
    angle_start: jax.Array
    angle_end: jax.Array
    shift_start: jax.Array
    shift_end: jax.Array

    def __init__(self, pivot=(0.0, 0.0), angle_start=0.0, angle_end=0.0,
                 shift_start=(0.0, 0.0), shift_end=(0.0, 0.0)):
        check_finite("angle_start", angle_start)
        check_finite("angle_end", angle_end)
        self.pivot = _vec2("pivot", pivot)
        self.angle_start = jnp.asarray(angle_start, dtype=jnp.float64)
        self.angle_end = jnp.asarray(angle_end, dtype=jnp.float64)
        self.shift_start = _vec2("shift_start", shift_start)
        self.shift_end = _vec2("shift_end", shift_end)

    def __call__(self, X, tau):
        theta = self.angle_start + tau * (self.angle_end - self.angle_start)
        shift = self.shift_start + tau * (self.shift_end - self.shift_start)
        c, s = jnp.cos(theta), jnp.sin(theta)
        Q = jnp.stack([jnp.stack([c, -s]), jnp.stack([s, c])])
        return self.pivot + (X - self.pivot) @ Q.T + shift - X


class DirichletBC(eqx.Module):
    """Components ``components`` of the nodes ``nodes`` follow ``motion``.

    Attributes:
        nodes: node indices (static tuple).
        components: constrained components, a subset of (0, 1) for (x, y) (static tuple).
        motion: the prescribed displacement as a function of phase-local time.
    """

    nodes: tuple = eqx.field(static=True)
    components: tuple = eqx.field(static=True)
    motion: Motion

    def __init__(self, nodes, components=(0, 1), motion: Motion | None = None):
        arr = np.asarray(nodes).ravel()
        if arr.size == 0:
            raise ValueError("field 'nodes' of a DirichletBC must not be empty")
        if not np.issubdtype(arr.dtype, np.integer):  # int(0.5) would silently constrain node 0
            raise ValueError(f"field 'nodes' of a DirichletBC must hold integer node indices, got {nodes!r}")
        nodes = tuple(int(n) for n in arr)
        components = tuple(int(c) for c in components)
        if not components or any(c not in (0, 1) for c in components) or len(set(components)) != len(components):
            raise ValueError(f"field 'components' must be a non-empty subset of (0, 1), got {components}")
        self.nodes = nodes
        self.components = components
        self.motion = Ramp() if motion is None else motion


class Phase(eqx.Module):
    """One phase of the load path.

    Attributes:
        name: phase name (static).
        bcs: Dirichlet conditions active during the phase.
        tau_ends, n_steps: the nominal increments, as data (arrays of one entry per segment: a change of
            stroke or increment compiles no new program; their count is structure): from the previous
            breakpoint to ``tau_ends[i]`` the phase is divided into ``n_steps[i]`` equal steps. The last
            end is 1. The step controller may cut these steps and grows them back, never beyond the
            nominal value.

    The constructor takes either ``n_steps`` (equal nominal steps over the whole phase, the same as
    ``increments=((1.0, n_steps),)``) or ``increments`` as ``((tau_end, n_steps), ...)``;
    :attr:`increments` gives them back in that form.
    """

    name: str = eqx.field(static=True)
    bcs: tuple
    tau_ends: np.ndarray
    n_steps: np.ndarray

    def __init__(self, name: str, bcs=(), n_steps: int | None = 10, increments=None):
        self.name = str(name)
        # A string is iterable too: "abc" must not become three conditions named by letters.
        if isinstance(bcs, (str, bytes)) or not hasattr(bcs, "__iter__"):
            raise ValueError(f"field 'bcs' of phase {name!r} must be a sequence of DirichletBC, got {bcs!r}")
        self.bcs = tuple(bcs)
        if not all(isinstance(bc, DirichletBC) for bc in self.bcs):
            raise ValueError(f"field 'bcs' of phase {name!r} must hold DirichletBC only, got {bcs!r}")
        if increments is None:
            if isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer)) or n_steps < 1:
                raise ValueError(f"field 'n_steps' of phase {name!r} must be an integer >= 1, got {n_steps!r}")
            increments = ((1.0, int(n_steps)),)
        increments = tuple((float(e), int(n)) for e, n in increments)
        real = tuple(inc for inc in increments if inc != (1.0, 0))   # (1, 0): empty padding, only at the end
        ends = [e for e, _ in real]
        if (not real or any(n < 1 for _, n in real) or not np.all(np.diff([0.0] + ends) > 0) or ends[-1] != 1.0
                or increments[:len(real)] != real):
            raise ValueError(f"field 'increments' of phase {name!r} must have increasing breakpoints "
                             f"ending at 1 and step counts >= 1 (then only empty (1, 0) entries), got {increments}")
        self.tau_ends = np.array([e for e, _ in increments], np.float64)
        self.n_steps = np.array([n for _, n in increments], np.int64)

    @property
    def increments(self) -> tuple:
        """The nominal increments as ``((tau_end, n_steps), ...)`` (of a phase whose values are known: not
        inside a compiled function that takes the model as an argument)."""
        return tuple((float(e), int(n)) for e, n in zip(_concrete("tau_ends", self.tau_ends),
                                                          _concrete("n_steps", self.n_steps)) if n > 0)


def _concrete(name: str, value) -> np.ndarray:
    if not is_concrete(value):
        raise ValueError(f"field '{name}' of a phase is traced here, and this needs its values: give them "
                         f"outside the compiled function (for a run's history buffer: StepControl.max_steps)")
    return np.asarray(value)


def with_steps(phases, times, phase_index, padded: bool = False) -> tuple:
    """``phases`` with their nominal increments replaced by the given steps: ``times`` (increasing
    global pseudo-times, each the end of one step) and the phase index of each step. Used to replay
    the accepted steps of an adaptive run as the nominal steps of another (the step controller still
    cuts a step that fails, and grows back to the given step, never beyond).

    ``padded``: each phase's steps are followed by empty (1, 0) segments up to the next power of two, so
    that replays of step sequences of nearly the same length have arrays of the same shapes and share
    one compiled program (the controller passes over empty segments: the same steps either way)."""
    times, phase_index = np.asarray(times, float), np.asarray(phase_index, int)
    out = []
    for k, phase in enumerate(phases):
        tau = times[phase_index == k] - k
        if tau.size == 0 or abs(tau[-1] - 1.0) > 1e-9:
            raise ValueError(f"field 'times' must cover phase {phase.name!r} up to its end")
        tau[-1] = 1.0
        steps = [(float(t), 1) for t in tau]
        if padded:
            steps += [(1.0, 0)] * (2 ** int(np.ceil(np.log2(len(steps)))) - len(steps))
        out.append(Phase(phase.name, phase.bcs, increments=tuple(steps)))
    return tuple(out)


@dataclasses.dataclass(frozen=True)
class Schedule:
    """The nominal increments of all phases, flattened into segments of global pseudo-time: arrays,
    NumPy where the phases' increments are known, traced where they are data of a compiled function."""

    seg_end: np.ndarray | jax.Array     # global time at the end of each segment
    seg_dt: np.ndarray | jax.Array      # nominal increment in each segment
    seg_phase: np.ndarray               # phase index of each segment (structure: always NumPy)
    seg_steps: np.ndarray | jax.Array   # nominal steps in each segment

    @property
    def n_nominal_steps(self) -> int:
        return int(np.sum(_concrete("n_steps", self.seg_steps)))

    def nominal_steps(self) -> tuple[np.ndarray, np.ndarray]:
        """End times (n_nominal_steps,) of all nominal steps, and the phase index of each."""
        ends, counts = _concrete("tau_ends", self.seg_end), _concrete("n_steps", self.seg_steps)
        starts = np.concatenate([[0.0], ends[:-1]])
        times = [s + (e - s) * np.arange(1, n + 1) / n for s, e, n in zip(starts, ends, counts)]
        phases = [np.full(n, p) for n, p in zip(counts, self.seg_phase)]
        return np.concatenate(times), np.concatenate(phases)


def schedule(phases) -> Schedule:
    """The segments of ``phases``' nominal increments (computed with NumPy where their values are known,
    in the compiled function where they are traced: the same IEEE operations either way)."""
    xp = np if is_concrete([(ph.tau_ends, ph.n_steps) for ph in phases]) else jnp
    seg_end, seg_dt, seg_steps, seg_phase = [], [], [], []
    for k, phase in enumerate(phases):
        ends = xp.asarray(phase.tau_ends, xp.float64)
        starts = xp.concatenate([xp.zeros(1, xp.float64), ends[:-1]])
        seg_end.append(k + ends)
        # Empty padding segments (no steps, no length) get a zero increment, never taken.
        seg_dt.append((ends - starts) / xp.maximum(xp.asarray(phase.n_steps), 1).astype(xp.float64))
        seg_steps.append(xp.asarray(phase.n_steps))
        seg_phase.append(np.full(np.shape(phase.tau_ends)[0], k, np.int32))
    return Schedule(xp.concatenate(seg_end), xp.concatenate(seg_dt), np.concatenate(seg_phase),
                    xp.concatenate(seg_steps))


def constraint_masks(n_nodes: int, phases) -> np.ndarray:
    """(n_phases, 2 n_nodes) bool: which dofs are prescribed in each phase (static)."""
    masks = np.zeros((len(phases), 2 * n_nodes), dtype=bool)
    for k, phase in enumerate(phases):
        for bc in phase.bcs:
            nodes = np.asarray(bc.nodes)
            if nodes.min() < 0 or nodes.max() >= n_nodes:
                raise ValueError(f"a DirichletBC of phase {phase.name!r} names nodes outside the mesh")
            for c in bc.components:
                masks[k, 2 * nodes + c] = True
    return masks


def prescribed_values(nodes_ref: jax.Array, phases, phase: jax.Array, tau: jax.Array) -> jax.Array:
    """Prescribed displacement of every dof at phase-local time ``tau`` of phase ``phase``: (2 n_nodes,).

    Entries of unconstrained dofs are 0. Later conditions in a phase override earlier ones on shared dofs.
    """

    def branch(k):
        def values(tau):
            u = jnp.zeros(nodes_ref.shape, nodes_ref.dtype)
            for bc in phases[k].bcs:
                idx = np.asarray(bc.nodes)
                disp = bc.motion(nodes_ref[idx], tau)
                for c in bc.components:
                    u = u.at[idx, c].set(disp[:, c])
            return u.reshape(-1)
        return values

    if len(phases) == 1:
        return branch(0)(tau)
    return jax.lax.switch(phase, [branch(k) for k in range(len(phases))], tau)
