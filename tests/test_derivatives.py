"""Derivatives through the whole loading path: implicit differentiation of every step, plastic history
threaded through the steps. Finite differences are central, in float64, with Newton tolerances tight
enough (rtol 1e-12) that solver noise stays far below the tolerance of the comparison."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfric as jf
from models import STEEL, clamped_pull

TIGHT = jf.NewtonOptions(rtol=1e-12, atol=1e-10)
SIGMA_Y, LENGTH = 200.0, 10.0


def cycle_model(sigma_y, length, formulation="fbar"):
    # Pull to 2.5x the yield strain and back: the final reaction is compressive and path dependent.
    return clamped_pull(length=length, sigma_y=sigma_y, nx=6, ny=2, pull=0.05, n_steps=3, formulation=formulation)


def final_reaction(params, fixed=False, formulation="fbar"):
    sigma_y, length = params[0], params[1]
    model = cycle_model(sigma_y, length, formulation)
    sim = (jf.simulate_fixed(model, newton=TIGHT) if fixed else jf.simulate(model, newton=TIGHT))
    return sim.history.observed["reaction_right"][sim.history.n_rows - 1, 0]


forward = jax.jit(final_reaction)
forward_eas = jax.jit(lambda p: final_reaction(p, formulation="eas"))
P0 = jnp.array([SIGMA_Y, LENGTH])


def central_difference(f, p, direction, h):
    return (f(p + h * direction) - f(p - h * direction)) / (2 * h)


def test_cycle_is_plastic_and_path_dependent():
    model = cycle_model(SIGMA_Y, LENGTH)
    res = jf.run(model, newton=TIGHT, progress=False)
    assert res.converged
    assert res.history["max_eqps"][-1] > 1e-3
    # Back at zero end displacement, the plastically elongated strip pushes on the grip.
    assert res.history["reaction_right"][-1, 0] < -1.0


@pytest.mark.parametrize("index, name, formulation", [
    (0, "sigma_y", "fbar"), (1, "length", "fbar"),
    # 35 s; the fast suite checks the eas element's derivatives (test_solver.py)
    pytest.param(1, "length", "eas", marks=pytest.mark.slow)])
def test_jvp_matches_central_differences(index, name, formulation):
    """With ``eas`` the enhanced parameters are differentiated implicitly (lax.custom_root) inside
    every element; measured agreement 5e-9 (length) and 6e-10 (sigma_y)."""
    f = forward_eas if formulation == "eas" else forward
    direction = jnp.zeros(2).at[index].set(1.0)
    value, tangent = jax.jvp(f, (P0,), (direction,))
    h = 1e-4 * float(P0[index])
    fd = central_difference(f, P0, direction, h)
    assert float(value) < 0
    np.testing.assert_allclose(float(tangent), float(fd), rtol=1e-5, err_msg=f"d reaction / d {name}")


@pytest.mark.slow  # 35 s; the fast suite checks reverse against forward mode in test_gradients.py
def test_reverse_mode_through_the_fixed_step_scan_agrees_with_forward_mode():
    grad = jax.jit(jax.grad(lambda p: final_reaction(p, fixed=True)))(P0)
    jac_fwd = jax.jit(jax.jacfwd(lambda p: final_reaction(p, fixed=True)))(P0)
    np.testing.assert_allclose(grad, jac_fwd, rtol=1e-9)
    # The fixed-step scan and the adaptive loop take the same (nominal) steps here.
    np.testing.assert_allclose(jac_fwd, jax.jacfwd(forward)(P0), rtol=1e-9)


def test_dot_product_test_of_the_implicit_step_derivative():
    """<w, J v> = <J^T w, v> for the map (sigma_y, length, E) -> final displacement field."""

    def final_u(p):
        model = cycle_model(p[0], p[1])
        model = eqx.tree_at(lambda m: m.material.E, model, p[2])
        return jf.simulate_fixed(model, newton=TIGHT).final.u.reshape(-1)

    p = jnp.array([SIGMA_Y, LENGTH, 200000.0])
    v = jax.random.normal(jax.random.PRNGKey(1), (3,)) * p * 1e-3
    out, Jv = jax.jit(lambda p, v: jax.jvp(final_u, (p,), (v,)))(p, v)
    w = jax.random.normal(jax.random.PRNGKey(2), out.shape)
    JTw = jax.jit(lambda p, w: jax.vjp(final_u, p)[1](w)[0])(p, w)
    lhs, rhs = float(jnp.dot(w, Jv)), float(jnp.dot(JTw, v))
    assert abs(lhs - rhs) <= 1e-10 * max(abs(lhs), abs(rhs))


def test_new_parameter_values_do_not_retrace():
    # The model an argument: its increments are data, so the history buffer's length is given.
    control = jf.StepControl(max_steps=200)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def run(model):
        return jf.simulate(model, control=control).final.u

    for sigma_y, length in [(200.0, 10.0), (250.0, 9.0), (180.0, 11.0)]:
        run(cycle_model(sigma_y, length))
    with pytest.raises(ValueError, match="field 'max_steps'"):
        eqx.filter_jit(lambda m: jf.simulate(m).final.u)(cycle_model(200.0, 10.0))
    # The public entry point compiles once per structure as well.
    jf.run(cycle_model(200.0, 10.0), progress=False)
    cache = jf.run.__globals__["_COMPILED"]
    before = list(cache.values())     # held: a new program cannot reuse an evicted one's id
    jf.run(cycle_model(230.0, 9.5), progress=False)
    assert {id(c) for c in cache.values()} <= {id(c) for c in before}


def test_vmap_over_yield_stress_equals_looped_runs():
    sigmas = jnp.array([180.0, 200.0, 240.0])
    batched = jax.jit(jax.vmap(lambda s: final_reaction(jnp.array([s, LENGTH]))))(sigmas)
    looped = jnp.array([forward(jnp.array([s, LENGTH])) for s in sigmas])
    np.testing.assert_allclose(batched, looped, rtol=1e-10)


def test_jvp_through_the_midpoint_rule_matches_central_differences():
    """The midpoint rule keeps F_n in the point states: its derivative along the path threads it through
    the steps. Near the clamp the strip's strain path turns, so the rule's answer differs from the
    radial return's (measured 6.6e-10 relative agreement of the derivative)."""
    def reaction(p):
        material = jf.J2Material(**{**STEEL, "sigma_y": p[0]}, integration="midpoint")
        sim = jf.simulate(clamped_pull(length=LENGTH, nx=6, ny=2, pull=0.05, n_steps=3, material=material),
                          newton=TIGHT)
        return sim.history.observed["reaction_right"][sim.history.n_rows - 1, 0]

    f = jax.jit(reaction)
    p0, direction = jnp.array([SIGMA_Y]), jnp.array([1.0])
    value, tangent = jax.jvp(f, (p0,), (direction,))
    fd = central_difference(f, p0, direction, 1e-4 * SIGMA_Y)
    assert abs(float(value) - float(forward(P0))) > 0.1     # not the radial return's answer
    assert float(tangent) == pytest.approx(float(fd), rel=1e-7)
