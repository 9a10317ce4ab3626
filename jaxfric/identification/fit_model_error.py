"""The fitting model's discretisation error, carried into the fitted parameters.

A parameter fitted to a force takes all of the model's error in that force: on the Nine test the same
curve gives mu = 0.11 to 0.20 depending on the fit mesh (docs/results.md, mu against the fit mesh),
while the Gauss-Newton interval, which holds the data's noise only, is a few thousandths wide. This
module estimates that error from companion runs, as ``jaxfric run --error-estimate`` does for a run's
steady force:

- per component c (``step``: half the nominal increments; ``mesh``: twice the elements along the strip;
  ``layers``: twice the layers), the adaptive run at the fitted values with that discretisation refined,
  and Richardson's first-order estimate of the error of each fitted observation,
  e_c = (F - F_c) / (1 - 1/2) (:func:`jaxfric.io.output.richardson_error`), signed (model minus limit);
- the components summed, e = sum_c e_c, and carried into the parameters to first order: the data are
  about the converged model's F*(p_true), the fitted model gives F*(p) + e, so J (p_fit - p_true) = -e and
  the estimated bias of the fit is b = -(J^T J)^-1 J^T e (J the fit's Jacobian at the optimum);
- the interval with the model's error: p_fit +/- (t_{0.975} stderr + B), B = sum_c |b_c|. The bias is
  systematic, not a random error, so it is added to the noise's half-width rather than in quadrature (an
  interval that holds the noise's 95 % shifted by up to B); and the components are added by magnitude,
  not with their signs: each estimate is uncertain by up to a factor of 2 (below), and on the Nine the
  components have opposite signs (on 300 x 3 the mesh's -0.0088 in mu and the layers' +0.0044, whose
  signed sum would have the interval miss the data's mu, docs/results.md).

Richardson's estimate with a finer companion lies between 1 and 2 times the true error for an error
that falls at least as fast as the element length (first order or better); where the convergence is
not monotone (the Nine's 2-layer meshes) it says that the fit mesh is not in its asymptotic range, by a
large b. The estimate describes the fitting model; a data curve from another material or geometry
than the model's carries errors no discretisation check sees.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from .. import scenes
from ..io.output import richardson_error
from .accuracy import companion_run
from .fit_data import observations

__all__ = ["COMPONENTS", "model_error"]

#: name -> (config overrides of the refined companion for a scene and its config, ratio of the
#: companion's discretisation parameter to the fit's)
COMPONENTS: dict[str, Callable] = {
    "step": lambda name, config: scenes.scaled_steps(name, config, 0.5),
    "mesh": lambda name, config: scenes.finer_along(name, config),
    "layers": lambda name, config: scenes.finer_through(name, config),
}
RATIO = 0.5  # every companion halves its discretisation parameter


def model_error(scene: str, variant: str, algorithm: str, overrides: dict, params: dict, jac: np.ndarray,
                fitted: np.ndarray, x: np.ndarray, edges, components, say: Callable[[str], None]) -> dict:
    """The estimated bias of the fitted ``params`` from the model's discretisation error (module docstring).

    Args:
        scene, variant, algorithm, overrides: the fitting model; params: {name: fitted value}.
        jac: (m, n) Jacobian of the observations at the optimum; fitted: (m,) the fitting model's
            observations there; x, edges: the measured displacements and window edges (None: pointwise).
        components: names from :data:`COMPONENTS`.

    Returns {"bias": {name: b}, "bound": {name: sum_c |b_c|}, "components": {component: {name: b_c}},
    "observation_error": (m,) e, "wall_s"}. Raises ValueError (one line) when a companion does not complete.
    """
    t0 = time.perf_counter()
    base = scenes.make(scene, variant, algorithm, {**overrides, **params})
    names = list(params)
    pinv = np.linalg.pinv(jac)
    total, per = np.zeros_like(fitted), {}
    for c in components:
        refined = COMPONENTS[c](scene, base.config)
        say(f"  model error: the adaptive run at the fitted values with {c} refined ({refined})")
        _, res = companion_run(base, refined, f"model-error companion with {c} refined")
        e_c = np.array([richardson_error(float(a), float(b), RATIO)
                        for a, b in zip(fitted, observations(res.history, x, edges))])
        total = total + e_c
        per[c] = dict(zip(names, (-pinv @ e_c).tolist()))
        say(f"  model error, {c}: observations off by up to {np.max(np.abs(e_c)):.3g} N/mm; parameters "
            + ", ".join(f"{n} {v:+.3g}" for n, v in per[c].items()))
    bound = {n: float(sum(abs(per[c][n]) for c in per)) for n in names}
    return {"bias": dict(zip(names, (-pinv @ total).tolist())), "bound": bound, "components": per,
            "observation_error": total, "wall_s": time.perf_counter() - t0}
