import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfric as jf
from jaxfric.fem.assembly import internal_force, internal_force_and_tangent, mesh_geometry
from jaxfric.loadpath.model import initial_state


def test_numbering_follows_the_spec():
    mesh = jf.strip_mesh(0.0, 4.0, 0.0, 1.0, nx=4, ny=2)
    assert mesh.n_nodes == 15 and mesh.n_elements == 8 and mesh.block_size == 6
    # node (i, j) -> i*(ny+1) + j; element (i, j) -> i*ny + j, nodes counter-clockwise
    np.testing.assert_allclose(mesh.nodes[mesh.node_index(3, 1)], [3.0, 0.5])
    np.testing.assert_array_equal(mesh.elements[1 * 2 + 1], [4, 7, 8, 5])
    np.testing.assert_array_equal(mesh.left, [0, 1, 2])
    np.testing.assert_array_equal(mesh.right, [12, 13, 14])
    np.testing.assert_array_equal(mesh.bottom, [0, 3, 6, 9, 12])
    np.testing.assert_array_equal(mesh.top, [2, 5, 8, 11, 14])
    # every element has positive area
    assert float(jnp.min(mesh_geometry(mesh).weight)) > 0


def test_graded_coordinates():
    xs = jf.graded_coordinates(0.0, 10.0, 5, ratio=2.0)
    h = np.diff(np.asarray(xs))
    np.testing.assert_allclose(h[1:] / h[:-1], 2.0, rtol=1e-12)
    np.testing.assert_allclose([xs[0], xs[-1]], [0.0, 10.0], atol=1e-14)
    np.testing.assert_allclose(jf.graded_coordinates(0.0, 1.0, 4), [0, 0.25, 0.5, 0.75, 1.0], atol=1e-15)
    # differentiable in the end point
    d = jax.jacfwd(lambda s: jf.graded_coordinates(0.0, s, 4, 1.5))(2.0)
    np.testing.assert_allclose(d, np.asarray(jf.graded_coordinates(0.0, 1.0, 4, 1.5)), rtol=1e-12)


def test_tangent_is_block_tridiagonal_and_matches_dense_jacobian():
    """The scattered block-tridiagonal tangent equals the dense autodiff Jacobian of f_int."""
    mesh = jf.strip_mesh(0.0, 3.0, 0.0, 1.0, nx=3, ny=2, grading_x=1.3)
    material = jf.J2Material(E=1000.0, nu=0.3, sigma_y=1.0, A=10.0, n=0.5)
    model = jf.StripModel(mesh, material, (jf.Phase("p", [jf.DirichletBC(mesh.left)]),))
    geo = mesh_geometry(mesh)
    states = initial_state(model).material
    u = 0.05 * jax.random.normal(jax.random.PRNGKey(0), (mesh.n_nodes, 2))

    a = jax.jit(lambda v: internal_force_and_tangent(mesh, material, "fbar", geo, v, states))(u)
    dense = jax.jit(jax.jacfwd(lambda v: internal_force(
        mesh, material, "fbar", geo, v.reshape(-1, 2), states).f_int.reshape(-1)))(u.reshape(-1))
    np.testing.assert_allclose(a.tangent.to_dense(), dense, rtol=1e-10, atol=1e-8 * float(jnp.max(jnp.abs(dense))))
    assert float(jnp.max(a.states.eqps)) > 0  # the point is plastic: the tangent is the consistent one


@pytest.mark.parametrize("n_chunks", [1, 2, 3])
def test_element_chunks_hold_one_copy_of_the_element_code_and_give_the_same_values(n_chunks):
    """11 elements in chunks of 11 // c (padded to equal chunks): the values of one vmap over all of
    them, and one element evaluation in the traced program (``lax.map`` would evaluate a remainder
    that is not a whole chunk with a second copy: two return-mapping loops instead of one)."""
    from jaxfric.fem import assembly

    mesh = jf.strip_mesh(0.0, 11.0, 0.0, 1.0, nx=11, ny=1)
    material = jf.J2Material(E=1000.0, nu=0.3, sigma_y=1.0, A=10.0, n=0.5)
    model = jf.StripModel(mesh, material, (jf.Phase("p", [jf.DirichletBC(mesh.left)]),))
    geo = mesh_geometry(mesh)
    states = initial_state(model).material
    u = 0.05 * jax.random.normal(jax.random.PRNGKey(1), (mesh.n_nodes, 2))

    def traced(chunk):
        def assemble(v):   # a new function per setting: JAX reuses a function's trace
            return internal_force_and_tangent(mesh, material, "fbar", geo, v, states)

        with assembly.element_chunk(chunk):
            return jax.jit(assemble)(u), str(jax.make_jaxpr(assemble)(u)).count("while[")

    whole, loops_one = traced(1000)   # one chunk of all 11
    chunked, loops = traced(11 // n_chunks)
    assert loops_one >= 1 and loops == loops_one, (loops, loops_one)
    for a, b in zip(jax.tree_util.tree_leaves(chunked), jax.tree_util.tree_leaves(whole)):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-13 * float(jnp.max(jnp.abs(b))))
    assert float(jnp.max(whole.states.eqps)) > 0


def test_shared_trace_traces_once_per_chunk_setting():
    """A ``shared_trace`` function called twice with the same argument structure inside one traced
    program (a loop's eval_shape and its body) is traced once; under another element-chunk setting it
    is traced again, so a sweep's smaller chunks are never replaced by a single run's trace."""
    from jaxfric.fem import assembly

    seen = []

    @assembly.shared_trace
    def f(x):
        seen.append(assembly._CHUNK.get())
        return jnp.sin(x) * 2.0

    def program():   # a new outer function per use: JAX reuses a function's trace
        def loop(x):
            shape = jax.eval_shape(f, x)
            return jax.lax.fori_loop(0, 3, lambda i, y: f(y), jnp.zeros(shape.shape, shape.dtype) + x)
        return loop

    x = jnp.arange(3.0)
    np.testing.assert_allclose(jax.jit(program())(x), jnp.sin(jnp.sin(jnp.sin(x) * 2) * 2) * 2, rtol=1e-15)
    assert seen == [assembly.ELEMENT_CHUNK], seen
    jax.make_jaxpr(program())(x)     # the same setting: the trace is reused
    assert seen == [assembly.ELEMENT_CHUNK], seen
    with assembly.element_chunk(7):
        jax.make_jaxpr(program())(x)
    assert seen == [assembly.ELEMENT_CHUNK, 7], seen


def test_a_step_traces_the_element_tangent_once(monkeypatch):
    """One load step with exact contact, and one with the augmented Lagrangian (whose Newton solve
    sits in the augmentation loop), each trace the element tangent once: the loops' shapes reuse the
    trace of their bodies (before, twice and four times)."""
    from jaxfric.contact import exact_iterate, system
    from jaxfric.fem import assembly
    from jaxfric.loadpath.step import solve_step
    from jaxfric.scenes import make

    calls = []
    original = assembly.internal_force_and_tangent

    def counted(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(exact_iterate, "internal_force_and_tangent", counted)
    monkeypatch.setattr(system, "internal_force_and_tangent", counted)
    for algorithm in ("lcp_ssn", "auglag"):
        calls.clear()
        scene = make("nine", "mu017", algorithm, {"mesh": "12x1"})
        state = initial_state(scene.model)
        jax.make_jaxpr(lambda s: solve_step(scene.model, s, 0, 0.01, scene.newton))(state)
        assert len(calls) == 1, (algorithm, len(calls))


@pytest.mark.parametrize("kwargs, field", [
    (dict(thickness=0.0), "thickness"),
    (dict(thickness=-1.0), "thickness"),
    (dict(thickness=float("nan")), "thickness"),
    (dict(x_right=-1.0), "length"),
    (dict(nx=0), "nx"),
    (dict(ny=0), "ny"),
    (dict(nx=2.5), "nx"),
    (dict(x_right=float("inf")), "x_right"),
])
def test_bad_mesh_input_names_the_field(kwargs, field):
    args = dict(x_left=0.0, x_right=1.0, y_bottom=0.0, thickness=1.0, nx=2, ny=2)
    args.update(kwargs)
    with pytest.raises(ValueError, match=field):
        jf.strip_mesh(**args)


def test_bad_model_input_names_the_field():
    mesh = jf.strip_mesh(0.0, 1.0, 0.0, 1.0, 2, 2)
    mat = jf.J2Material.elastic(1.0, 0.3)
    with pytest.raises(ValueError, match="formulation"):
        jf.StripModel(mesh, mat, (jf.Phase("p"),), formulation="q8")
    with pytest.raises(ValueError, match="phases"):
        jf.StripModel(mesh, mat, ())
    for points in (1, 17, 2.0, True):
        with pytest.raises(ValueError, match="thickness_points"):
            jf.StripModel(mesh, mat, (jf.Phase("p"),), thickness_points=points)
    with pytest.raises(ValueError, match="n_steps"):
        jf.Phase("p", n_steps=0)
    with pytest.raises(ValueError, match="components"):
        jf.DirichletBC(mesh.left, components=(2,))
    with pytest.raises(ValueError, match="outside the mesh"):
        jf.StripModel(mesh, mat, (jf.Phase("p", [jf.DirichletBC([99])]),))
