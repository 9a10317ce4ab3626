"""The simulated curve that an identification (:mod:`jaxfric.identification.fit`) fits: the drawing force along a
frozen step sequence, at the measured displacements or averaged over windows, with its Jacobian in the
parameters by forward-mode differentiation through the whole loading path.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from ..numerics.lru import LRU
from ..numerics.newton import NewtonOptions
from .fit_data import bin_means
from .params import Parameterization, plan_steps, replay_function

__all__ = ["Curve", "curve_function", "forward_jacobian", "replay_options", "refined_plan", "REPLAY_ITERATIONS",
           "PROGRAMS"]

REPLAY_ITERATIONS = 60  # Newton iterations per step allowed in the frozen-sequence replays


class Curve:
    """The fitted observations (the simulated force at the measured displacements, or its means over
    the windows ``edges``) along one frozen step sequence, with their Jacobian.

    Args:
        par: the parameterised scene.
        plan_history: the step sequence (``time``, ``phase`` columns of an adaptive run).
        x: (m,) measured displacements (mm); edges: window edges (mm), or None (pointwise).
        newton: Newton's options (None: the scene's), with at least :data:`REPLAY_ITERATIONS` iterations.

    ``curve(p)`` returns (observations, Jacobian (m, n), pointwise force, result code, cutbacks). The step
    sequence is data of the compiled function (:func:`~jaxfric.identification.params.plan_steps`): the curves
    of one parameterisation, measurement and Newton's options share it (:data:`PROGRAMS`), so that a new
    sequence of about the same length (a fit's re-plan) compiles nothing.
    """

    def __init__(self, par: Parameterization, plan_history: dict, x: np.ndarray, edges, newton: NewtonOptions | None):
        self.times = np.asarray(plan_history["time"][1:])
        newton = replay_options(par, newton)
        self._steps = plan_steps(par, plan_history)
        key = (id(par), newton, np.asarray(x).tobytes(), None if edges is None else np.asarray(edges).tobytes())
        self._fn = PROGRAMS.get(key, lambda: (par, _compiled_curve(par, x, edges, newton)))[1]

    def __call__(self, p):
        jac, (obs, pointwise, code, cuts) = self._fn(jnp.asarray(p, jnp.float64), self._steps)
        return np.asarray(obs), np.asarray(jac), np.asarray(pointwise), int(code), int(cuts)


# Compiled curves by (parameterisation, Newton's options, measurement): each entry holds its
# parameterisation, so that the key's id() names no other object while the entry lives.
PROGRAMS: LRU = LRU(4)


def replay_options(par: Parameterization, newton: NewtonOptions | None = None) -> NewtonOptions:
    """Newton's options of a replay: ``newton`` (None: the scene's) with at least
    :data:`REPLAY_ITERATIONS` iterations per step."""
    newton = par.scene.newton if newton is None else newton
    return dataclasses.replace(newton, max_iterations=max(newton.max_iterations, REPLAY_ITERATIONS))


def _compiled_curve(par: Parameterization, x, edges, newton: NewtonOptions):
    """``fn(p, steps) -> (Jacobian, (observations, pointwise force, result code, cutbacks))``, jitted, the
    step sequence ``steps`` an argument (not differentiated)."""
    return jax.jit(forward_jacobian(curve_function(par, x, edges, newton), len(par.names)))


def curve_function(par: Parameterization, x, edges, newton: NewtonOptions):
    """``curve(p, steps) -> (observations, (observations, pointwise force, result code, cutbacks))``: the
    replay of the step sequence ``steps`` at parameter values ``p`` (n,), not compiled."""
    replay = replay_function(par, newton)

    def curve(p, steps):
        h, code = replay(p, steps)
        rows = jnp.arange(h.time.shape[0], dtype=h.n_rows.dtype)
        # Unfilled rows get displacements beyond every measured one (interp needs increasing x).
        xr = jnp.where(rows < h.n_rows, h.observed["drawing_displacement"], 1e30 * (1.0 + rows.astype(float)))
        fr = jnp.where(rows < h.n_rows, h.observed["drawing_force"], 0.0)
        pointwise = jnp.interp(jnp.asarray(x), xr, fr)
        obs = pointwise if edges is None else bin_means(xr, fr, jnp.asarray(edges))
        return obs, (obs, pointwise, code, jnp.sum(h.cutbacks))

    return curve


def forward_jacobian(curve, n: int):
    """``jac(p, steps) -> (Jacobian (m, n), aux)`` of ``curve(p, steps) -> (observations (m,), aux)`` by
    forward mode: ``jax.jacfwd`` (a ``vmap`` of the JVP) for several parameters; for one, the JVP
    itself: batching the whole loading path's loops for a single tangent doubles the tracing, which every
    fit pays, its programs in the cache or not, and saves nothing in compilation or in the replay
    (docs/results.md, identification: the curve's program)."""
    if n > 1:
        return jax.jacfwd(curve, has_aux=True)

    @functools.wraps(curve)   # the compiled program keeps the curve's name (experiments/suite_compile.py)
    def jac(p, steps):
        _, obs_dot, aux = jax.jvp(lambda q: curve(q, steps), (p,), (jnp.ones_like(p),), has_aux=True)
        return obs_dot[:, None], aux

    return jac


def refined_plan(history: dict, substeps: int) -> dict:
    """The step sequence of ``history`` with every accepted step split into ``substeps`` equal steps
    (the time, phase and predicted columns that :func:`jaxfric.identification.params.path_function`
    replays). A step that started from the converged state keeps that mark on its first part; its later
    parts start from the prediction (the previous part's increment), unless the run withheld the
    prediction there (a step in the same phase as the one before, neither predicted nor retried)."""
    if substeps == 1:
        return history
    t, phase, cuts, predicted = (np.asarray(history[k]) for k in ("time", "phase", "cutbacks", "predicted"))
    times, phases, marks = [t[0]], [phase[0]], [predicted[0]]
    for k in range(1, len(t)):
        withheld = k > 1 and predicted[k] == 0 and cuts[k] == 0 and phase[k] == phase[k - 1]
        for j in range(1, substeps + 1):
            times.append(t[k] if j == substeps else t[k - 1] + (t[k] - t[k - 1]) * j / substeps)
            phases.append(phase[k])
            marks.append(predicted[k] if j == 1 else int(not withheld))
    return {"time": np.array(times), "phase": np.array(phases), "predicted": np.array(marks)}
