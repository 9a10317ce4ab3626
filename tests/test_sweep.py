"""Batched sweeps (jaxfric.loadpath.sweep): one vmapped simulation equals the looped single runs."""

import numpy as np
import pytest

import jaxfric as jf
from jaxfric import scenes
from jaxfric.loadpath.sweep import stack_models, sweep

# The structure of test_output's flat-die run, so that the single runs reuse its compilation.
OVERRIDES = {"mesh": "24x2", "n_clamp": "2", "U_draw": "0.003", "U_fine": "0.001", "dU_fine": "0.0005",
             "dU": "0.001", "steady_window": "0.002,0.003"}
MUS = (0.08, 0.15, 0.3)


def test_vmapped_mu_sweep_equals_single_runs():
    built = [scenes.make("flat_die", "const_force", "penalty", {**OVERRIDES, "mu": m}) for m in MUS]
    out = sweep([s.model for s in built], control=built[0].control, observe=built[0].observe)  # flat loop
    assert out.n_members == len(MUS)
    for i, s in enumerate(built):
        single = jf.run(s.model, control=s.control, observe=s.observe, progress=False)
        batched = out.history(i)
        assert out.converged(i)
        for name in ("time", "newton_iters", "cutbacks", "drawing_force", "clamping_force", "tool_position"):
            a, b = batched[name], single.history[name]
            assert a.shape == b.shape, name
            scale = max(float(np.max(np.abs(b))), 1e-300)
            # Batched and single kernels may round differently; 1e-10 of the column's scale.
            assert float(np.max(np.abs(a - b))) <= 1e-10 * scale, (name, i)
    # The members differ where mu does: the drawing force grows with mu at global sliding.
    finals = [out.history(i)["drawing_force"][-1] for i in range(len(MUS))]
    assert finals[0] < finals[1] < finals[2]


def test_only_differing_leaves_are_batched():
    a = scenes.make("flat_die", "const_force", "penalty", {**OVERRIDES, "mu": 0.1}).model
    b = scenes.make("flat_die", "const_force", "penalty", {**OVERRIDES, "mu": 0.2}).model
    _, axes, _ = stack_models([a, b])
    # mu (per phase) and eps_t = mu eps_n differ; the mesh and everything else are shared.
    assert sum(ax == 0 for ax in axes) == 2 and len(axes) > 10


def test_structure_mismatch_is_refused():
    a = scenes.make("flat_die", "const_force", "penalty", {**OVERRIDES, "mu": 0.1}).model
    b = scenes.make("flat_die", "const_force", "penalty", {**OVERRIDES, "mesh": "12x2"}).model
    with pytest.raises(ValueError, match="member 1"):
        stack_models([a, b])
    with pytest.raises(ValueError, match="models"):
        stack_models([])


def test_flat_loop_runs_the_penalty_law_only():
    """The one-iteration-per-pass loop (the penalty sweeps' default) refuses the laws that loop inside
    a step; the sweep of those keeps the nested loops (``flat=False``)."""
    model = scenes.make("flat_die", "const_force", "auglag", OVERRIDES).model
    with pytest.raises(ValueError, match="'contact'"):
        jf.simulate_flat(model)


def test_element_chunks_do_not_change_the_assembly():
    """The sweep traces its members with smaller element chunks (jaxfric.fem.assembly.element_chunk): the
    forces and material states are those of the default chunking, whatever the chunk size (48 elements
    in chunks of 5: ten chunks, the last one partial; the tangent goes through the same element map)."""
    import jax
    import jax.numpy as jnp

    from jaxfric.fem.assembly import element_chunk, internal_force, mesh_geometry
    from jaxfric.loadpath.model import initial_state

    model = scenes.make("flat_die", "const_force", "penalty", OVERRIDES).model
    state = initial_state(model)
    rng = np.random.default_rng(0)
    u = jnp.asarray(0.02 * rng.standard_normal(state.u.shape))   # a strain large enough to yield
    geo = mesh_geometry(model.mesh)

    def assemble(chunk):
        with element_chunk(chunk):
            return jax.jit(lambda u: internal_force(model.mesh, model.material, model.formulation,
                                                    geo, u, state.material))(u)

    ref, small = assemble(512), assemble(5)
    assert model.mesh.elements.shape[0] == 48
    for a, b in zip(jax.tree_util.tree_leaves(small), jax.tree_util.tree_leaves(ref)):
        scale = max(float(jnp.max(jnp.abs(b))), 1e-300)
        assert float(jnp.max(jnp.abs(a - b))) <= 1e-13 * scale
    assert float(ref.det_min) > 0.0 and float(jnp.max(ref.states.eqps)) > 0.0   # plastic, not inverted


def test_sweep_with_the_cyclic_solve_equals_the_thomas_runs():
    """The GPU's path on the CPU: a sweep traced with the cyclic-reduction solve (and a GPU's chunk)
    follows the single runs' Thomas path: same steps and iterations, forces to 1e-10 of their scale
    as in the test above (measured 3.5e-12: two solvers round differently)."""
    from jaxfric.fem.assembly import ELEMENT_CHUNK
    from jaxfric.numerics.linalg import block_solver

    built = [scenes.make("flat_die", "const_force", "penalty", {**OVERRIDES, "mu": m}) for m in MUS[1:]]
    with block_solver("cyclic"):
        out = sweep([s.model for s in built], control=built[0].control, observe=built[0].observe,
                    chunk=ELEMENT_CHUNK)
    for i, s in enumerate(built):
        single = jf.run(s.model, control=s.control, observe=s.observe, progress=False)
        batched = out.history(i)
        assert out.converged(i)
        assert np.array_equal(batched["newton_iters"], single.history["newton_iters"])
        for name in ("time", "drawing_force", "clamping_force", "tool_position"):
            a, b = batched[name], single.history[name]
            scale = max(float(np.max(np.abs(b))), 1e-300)
            assert float(np.max(np.abs(a - b))) <= 1e-10 * scale, (name, i)


_SHARDED = """
import json, sys
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
from jaxfric import scenes
from jaxfric.loadpath.sweep import sweep
overrides, mus = json.loads(sys.argv[1])
built = [scenes.make("flat_die", "const_force", "penalty", {**overrides, "mu": m}) for m in mus]
models, control, observe = [s.model for s in built], built[0].control, built[0].observe
sharded = sweep(models, control=control, observe=observe)
placed = sweep(models, control=control, observe=observe, devices=jax.devices()[:1])
worst = 0.0
for i in range(len(mus)):
    a, b = sharded.history(i), placed.history(i)
    for name in ("time", "newton_iters", "drawing_force", "clamping_force"):
        assert a[name].shape == b[name].shape, name
        scale = max(float(np.max(np.abs(b[name]))), 1e-300)
        worst = max(worst, float(np.max(np.abs(a[name] - b[name]))) / scale)
print(json.dumps({"devices": len(jax.devices()), "n_devices": sharded.n_devices, "worst": worst,
                  "converged": [sharded.converged(i) for i in range(len(mus))],
                  "final": [float(sharded.history(i)["drawing_force"][-1]) for i in range(len(mus))]}))
"""


def test_sweep_sharded_over_two_host_devices_equals_the_one_device_sweep():
    """Three members over two CPU devices (XLA's forced host device count, in a child process since it
    is read when JAX starts): padded to four, two per device, each device running its own loop under
    shard_map. The histories equal the one-device sweep's to 1e-10 of each column's scale (the two
    programs batch different member counts, so they may round differently)."""
    import json
    import os
    import subprocess
    import sys

    env = dict(os.environ, XLA_FLAGS=(os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"))
    done = subprocess.run([sys.executable, "-c", _SHARDED, json.dumps([OVERRIDES, MUS])], env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["devices"] == 2 and out["n_devices"] == 2
    assert all(out["converged"]) and out["worst"] <= 1e-10, out
    assert out["final"][0] < out["final"][1] < out["final"][2]
