"""The one Newton loop (:func:`jaxfric.numerics.newton.newton_pass`) with a problem of its own: the loop,
not the problem, decides convergence, line search and result codes."""

from typing import Any, ClassVar

import jax.numpy as jnp
import pytest

import jaxfric  # noqa: F401  (float64)
from jaxfric.numerics.newton import (
    AbstractNewtonProblem,
    Evaluation,
    NewtonOptions,
    Trial,
    newton_loop,
    newton_result,
)
from jaxfric.numerics.results import Result


class Arctan(AbstractNewtonProblem):
    """R(x) = atan(x - 1), whose full Newton steps from |x - 1| > 1.39 overshoot further each time;
    ``solved`` and ``in_band`` stand for a direction solver's failure and a contact left out of a band."""

    solved: Any = True
    in_band: Any = None
    searches_first_step: ClassVar[bool] = True

    def start(self, x0, args) -> Trial:
        return Trial(jnp.zeros_like(x0), jnp.array(1.0), jnp.array(jnp.inf), jnp.array(True), jnp.zeros(1, jnp.int32))

    def evaluate(self, x, trial, args) -> Evaluation:
        r = jnp.arctan(x - 1.0)
        return Evaluation(r, jnp.array(1.0), jnp.all(jnp.isfinite(r)), jnp.array(True), x, merit=jnp.sum(r**2),
                          in_band=None if self.in_band is None else jnp.array(self.in_band))

    def settled(self, new, old, trial):
        return jnp.array(True)

    def direction(self, x, point, args, first) -> Trial:
        dx = -jnp.arctan(x - 1.0) * (1.0 + (x - 1.0) ** 2)
        return Trial(dx, jnp.array(1.0), point.merit, jnp.array(self.solved), jnp.ones(1, jnp.int32))

    def aux(self, x, point, args):
        return point.residual


def _solve(problem, x0, line_search=True):
    options = NewtonOptions(line_search=line_search, max_iterations=25)
    c = newton_loop(problem, None, jnp.array([x0]), jnp.array([x0]), options)
    return c, newton_result(c, problem, None)


def test_the_line_search_carries_newton_where_full_steps_diverge():
    _, plain = _solve(Arctan(), 3.0, line_search=False)
    assert int(plain.code) != Result.SUCCESS
    c, searched = _solve(Arctan(), 3.0)
    assert int(searched.code) == Result.SUCCESS
    assert abs(float(searched.x[0]) - 1.0) < 1e-9
    # Every direction's solver count is summed, one per direction taken.
    assert 0 < int(c.stats[0]) <= int(searched.iterations)


@pytest.mark.parametrize(("problem", "code"), [(Arctan(solved=False), Result.LCP_FAILED),
                                               (Arctan(in_band=False), Result.CONTACT_BAND)])
def test_the_loop_reports_the_problem_s_failures(problem, code):
    _, sol = _solve(problem, 1.5)
    assert int(sol.code) == code
