"""Scene config values as differentiable inputs of a model.

    >>> par = parameterize("nine", ["mu", "R1"], variant="mu017", overrides={"mesh": "40x2"})
    >>> model = par.model(jnp.array([0.2, 5.0]))      # traceable: jax.jvp / jax.grad flow through

A scene is built by ordinary Python from its config (validation, mesh sizes, step counts), so a config
value cannot simply be a tracer. Instead the scene is built at the start values ``p0`` and at a few
nearby values, and every array leaf of the model that moves with a parameter is written as
``leaf(p) = leaf(p0) + sum_i (p_i - p0_i) * slope_i``. This is exact, not an approximation, for the
parameters that enter the model affinely, which covers the friction coefficients (the per-tool mu and
eps_t = mu eps_n), the tool geometry (cylinder and bead radii, heights, strokes: centres, radii and
segment end points are affine in them), the prescribed forces and the material constants (stored as
given). Each parameterization checks it: the builds at p0 + h e_i and p0 + 2 h e_i must lie on a line
(to 1e-9 of the leaf's size), with no cross terms between parameters (p0 + h e_i + h e_j), and the
model's static structure (mesh size, step counts, which tools have friction, observation settings) must
not change. A parameter that fails (a mesh size, a step count, one that changes which tools carry
friction, or one that enters nonlinearly) is rejected with a one-line ValueError naming it.

What stays fixed at the start values: the static structure, in particular the number of nominal steps
of each phase (a bead height H changes the closing stroke, not the number of closing steps).
"""

from __future__ import annotations

import dataclasses
import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import scenes
from ..fem.loading import with_steps
from ..loadpath.run import run
from ..loadpath.simulate import simulate, simulate_fixed, tangent_anchor
from ..numerics.newton import NewtonOptions

__all__ = ["Parameterization", "parameterize", "adaptive_run", "path_function", "replay_function", "plan_steps",
           "value_filter", "AFFINE_RTOL"]

AFFINE_RTOL = 1e-9  # affinity check, relative to the size of a leaf and of its change


def value_filter(model):
    """The filter (an ``eqx.partition`` spec) of the leaves of ``model`` that a parameterization writes as
    functions of the parameters: every array but the phases' nominal increments, which it holds at the
    start values with the rest of the structure (a stroke changes the closing distance, not the number of
    closing steps)."""
    spec = jax.tree_util.tree_map(eqx.is_array, model)
    fixed = lambda m: [a for phase in m.phases for a in (phase.tau_ends, phase.n_steps)]  # noqa: E731
    return eqx.tree_at(fixed, spec, replace=[False] * (2 * len(model.phases)))


def _leaves(model):
    dyn, static = eqx.partition(model, value_filter(model))
    return [np.asarray(a) for a in jax.tree_util.tree_leaves(dyn)], jax.tree_util.tree_structure(dyn), static


@dataclasses.dataclass(frozen=True)
class Parameterization:
    """A scene whose model is a traceable function of some of its config values.

    Attributes:
        names: the parameter names (scene config fields), in order.
        p0: (n,) start values (the variant's, then the overrides').
        scene: the :class:`~jaxfric.scenes.Scene` built at ``p0`` (observe, control, outputs).
        moved: per parameter, the number of model leaves that depend on it.
    """

    names: tuple
    p0: np.ndarray
    scene: scenes.Scene
    moved: tuple
    _base: tuple = dataclasses.field(repr=False)      # leaves at p0
    _slopes: tuple = dataclasses.field(repr=False)    # per leaf: None or (n, *leaf.shape)
    _treedef: object = dataclasses.field(repr=False)
    _static: object = dataclasses.field(repr=False)

    def model(self, p):
        """The model at parameter values ``p`` ((n,) array, traced or concrete)."""
        p = jnp.asarray(p, jnp.float64)
        dp = p - jnp.asarray(self.p0)
        leaves = [jnp.asarray(b) if s is None else jnp.asarray(b) + jnp.tensordot(dp, jnp.asarray(s), axes=1)
                  for b, s in zip(self._base, self._slopes)]
        return eqx.combine(jax.tree_util.tree_unflatten(self._treedef, leaves), self._static)


def _on_line(leaves, base, change) -> bool:
    """Whether every leaf equals base + change to AFFINE_RTOL of the leaf's size and of its change."""
    for a, b, d in zip(leaves, base, change):
        size = np.max(np.abs(b), initial=0.0) + np.max(np.abs(a - b), initial=0.0)
        if np.max(np.abs(a - b - d), initial=0.0) > AFFINE_RTOL * max(size, 1e-300):
            return False
    return True


def _step(value: float) -> float:
    # Small enough not to cross a structural threshold, large enough that slopes are exact to round-off.
    return 1e-3 * max(abs(value), 1e-3)


def parameterize(scene: str, names, *, variant: str | None = None, algorithm: str = "penalty",
                 overrides: dict | None = None) -> Parameterization:
    """Make the config fields ``names`` of ``scene`` differentiable inputs of its model.

    Raises ValueError (one line, naming the field) for an unknown field, a field that is not a real
    number, or one that changes the model's structure or enters it nonlinearly.
    """
    names = tuple(names)
    if not names:
        raise ValueError("field 'param' needs at least one parameter name")
    if len(set(names)) != len(names):
        raise ValueError(f"field 'param' names a parameter twice: {', '.join(names)}")
    overrides = dict(overrides or {})
    base = scenes.make(scene, variant, algorithm, overrides)
    config = base.config
    assert dataclasses.is_dataclass(config)  # a scene's config is its config dataclass (Scene.config: object)
    start = []
    for name in names:
        if name == "mesh" or name not in {f.name for f in dataclasses.fields(config)}:
            known = ", ".join(f.name for f in dataclasses.fields(config))
            raise ValueError(f"unknown parameter {name!r} of scene '{scene}'; config fields: {known}")
        value = getattr(base.config, name)
        kind, _ = scenes._field_type(scene, name)
        if kind is not float or value is None or isinstance(value, bool):
            raise ValueError(f"parameter {name!r} of scene '{scene}' is not differentiable: it is "
                             f"{'unset (None)' if value is None else 'not a real number'} ({value!r})")
        start.append(float(value))
    p0 = np.array(start)
    leaves0, treedef0, static0 = _leaves(base.model)

    def build(p):
        try:
            s = scenes.make(scene, variant, algorithm, {**overrides, **dict(zip(names, map(float, p)))})
        except ValueError as err:
            raise ValueError(f"parameters {', '.join(names)} near {[float(v) for v in p0]}: {err}") from None
        leaves, treedef, static = _leaves(s.model)
        changed = [n for n, a, b in zip(names, p, p0) if a != b]
        if (treedef != treedef0 or not eqx.tree_equal(static, static0) or s.observe != base.observe
                or [a.shape for a in leaves] != [a.shape for a in leaves0]):
            raise ValueError(f"parameter {' and '.join(changed)!r} of scene '{scene}' is not differentiable: "
                             f"it changes the model's structure (mesh, step counts, friction on/off or "
                             f"observation settings)")
        return leaves

    n = len(names)
    h = np.array([_step(v) for v in p0])
    for i in range(n):
        # Step into the admissible side: a bead nose radius R at its limit H can only decrease.
        try:
            build(p0 + 2 * h[i] * np.eye(n)[i])
        except ValueError:
            h[i] = -h[i]
    slopes = []
    for i, name in enumerate(names):
        one, two = build(p0 + h[i] * np.eye(n)[i]), build(p0 + 2 * h[i] * np.eye(n)[i])
        slope = [(a - b) / h[i] for a, b in zip(one, leaves0)]
        if not _on_line(two, leaves0, [2 * h[i] * s for s in slope]):
            raise ValueError(f"parameter {name!r} of scene '{scene}' is not differentiable here: it enters "
                             f"the model nonlinearly")
        slopes.append(slope)
    for i, j in itertools.combinations(range(n), 2):
        both = build(p0 + h[i] * np.eye(n)[i] + h[j] * np.eye(n)[j])
        if not _on_line(both, leaves0, [h[i] * si + h[j] * sj for si, sj in zip(slopes[i], slopes[j])]):
            raise ValueError(f"parameters {names[i]!r} and {names[j]!r} of scene '{scene}' are not "
                             f"differentiable together: they enter the model jointly (a cross term, "
                             f"e.g. eps_t = max(mu) eps_n); fit them one at a time")
    per_leaf: list[np.ndarray | None] = []  # per leaf: None or (n, *leaf.shape)
    moved = [0] * n
    for k in range(len(leaves0)):
        stack = np.stack([slopes[i][k] for i in range(n)])
        if np.any(stack != 0):
            per_leaf.append(stack)
            for i in range(n):
                moved[i] += int(np.any(stack[i] != 0))
        else:
            per_leaf.append(None)
    for name, m in zip(names, moved):
        if m == 0:
            raise ValueError(f"parameter {name!r} of scene '{scene}' does not enter the model of algorithm "
                             f"'{algorithm}' (nothing to differentiate)")
    return Parameterization(names=names, p0=p0, scene=base, moved=tuple(moved), _base=tuple(leaves0),
                            _slopes=tuple(per_leaf), _treedef=treedef0, _static=static0)



def adaptive_run(par: Parameterization, p, newton: NewtonOptions | None = None):
    """The ordinary adaptive run (:func:`jaxfric.loadpath.run.run`, no progress bar, no exception) of the model
    at parameter values ``p``: the step sequence that :func:`path_function` replays. ``newton``:
    default the scene's options."""
    scene = par.scene
    newton = scene.newton if newton is None else newton
    return run(par.model(jnp.asarray(p)), newton=newton, control=scene.control, observe=scene.observe,
               progress=False, raise_on_failure=False)


def path_function(par: Parameterization, *, newton: NewtonOptions | None = None, reverse: bool = False,
                  checkpoint: bool = True, plan: dict | None = None, final: bool = False):
    """``f(p) -> (history, result code)`` along the step sequence of the adaptive run at the start
    values: differentiable through every step of the loading path. ``final``: ``f(p) -> (history, result
    code, final state, reference node coordinates)``, for outputs of the final configuration (the mesh
    at ``p``: a geometry or thickness parameter moves its nodes).

    ``history`` is the simulation's :class:`~jaxfric.loadpath.simulate.History`: ``history.observed`` holds the
    scene's columns (``drawing_force``, ``clamping_force``, ...), rows 0 .. ``history.n_rows`` - 1
    filled (row 0: the initial state), e.g. the last drawing force is
    ``history.observed["drawing_force"][history.n_rows - 1]``. Why frozen steps: the adaptive controller would
    choose other steps at other parameter values, and the forces would then change by the discretisation
    noise of the new sequence, which no derivative describes.

    ``reverse=False``: the steps are replayed by the adaptive loop (:func:`~jaxfric.loadpath.simulate.simulate`
    with the accepted steps as nominal steps), which still cuts a step that fails at other values, so
    the replay completes wherever the original run would; forward mode (``jax.jvp``, ``jax.jacfwd``).
    ``reverse=True``: replayed in a fixed-length scan (:func:`~jaxfric.loadpath.simulate.simulate_fixed`,
    checkpointed per step when ``checkpoint``), which ``jax.grad``/``jax.vjp`` differentiate; a step
    that fails is not cut but stops the replay (non-zero code, the rows after it zero). Newton at the
    edge of its convergence region, where an adaptive run leaves some steps, can fail on a change of
    round-off alone (the blankholder's close: a replay of its own steps with the parameters as traced
    values instead of arguments fails at step 56), so reverse mode suits paths whose steps converge
    with margin. ``plan``: the history (``RunResult.history``) of a completed run whose steps to replay
    instead (for example an adaptive run at other values); default: an adaptive run at the start
    values, and ValueError if it fails.
    """
    scene = par.scene
    newton = scene.newton if newton is None else newton
    if plan is None:
        res = adaptive_run(par, par.p0, newton)
        if not res.converged:
            raise ValueError(f"the adaptive run at the start values does not complete: {res.message}")
        plan = res.history
    times, step_phase = np.asarray(plan["time"][1:]), np.asarray(plan["phase"][1:])
    fresh = np.asarray(plan["predicted"][1:]) == 0   # retries and withheld predictions start converged

    if reverse:
        def f(p):
            model = par.model(p)
            model = eqx.tree_at(lambda m: m.phases, model, with_steps(model.phases, times, step_phase))
            sim = simulate_fixed(model, newton=newton, observe=scene.observe, checkpoint=checkpoint, fresh=fresh,
                                 anchor=tangent_anchor(p))
            return (sim.history, sim.code, sim.final, model.mesh.nodes) if final else (sim.history, sim.code)
        return f
    replay, steps = replay_function(par, newton, final=final), plan_steps(par, plan)
    return lambda p: replay(p, steps)


def plan_steps(par: Parameterization, plan: dict) -> tuple:
    """The step sequence of ``plan`` (a run's history) as the data of :func:`replay_function`: per phase,
    its steps' ends and counts, padded to a power of two (:func:`jaxfric.fem.loading.with_steps`), so that
    sequences of nearly the same length have the same shapes."""
    phases = with_steps(par.scene.model.phases, np.asarray(plan["time"][1:]), np.asarray(plan["phase"][1:]),
                        padded=True)
    return tuple((phase.tau_ends, phase.n_steps) for phase in phases)


def replay_function(par: Parameterization, newton: NewtonOptions | None = None, final: bool = False):
    """``g(p, steps) -> (history, result code)``: the model at parameter values ``p`` run by the adaptive
    loop with the nominal steps ``steps`` (:func:`plan_steps`), which are data: one compiled ``g`` (or
    its derivative) replays every step sequence of the same padded length. Forward mode; the history
    buffer is the scene's (``StepControl.max_steps``), which bounds the steps of a replay. ``final``: the
    final state and the reference node coordinates too (:func:`path_function`)."""
    scene = par.scene
    newton = scene.newton if newton is None else newton

    def g(p, steps):
        model = par.model(p)
        phases = tuple(eqx.tree_at(lambda ph: (ph.tau_ends, ph.n_steps), phase, tuple(step))
                       for phase, step in zip(model.phases, steps))
        model = eqx.tree_at(lambda m: m.phases, model, phases)
        sim = simulate(model, newton=newton, control=scene.control, observe=scene.observe, anchor=tangent_anchor(p))
        return (sim.history, sim.code, sim.final, model.mesh.nodes) if final else (sim.history, sim.code)

    return g
