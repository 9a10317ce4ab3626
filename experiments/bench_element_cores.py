"""Does the element loop use both cores? ``python experiments/bench_element_cores.py [--mesh 300x3]``.

Times the Nine scene's element forces and tangents (jitted alone, at a small random displacement from the
initial state) three ways: as the run assembles them (:func:`jaxfric.fem.assembly.internal_force_and_tangent`,
with the scatter into the block-tridiagonal tangent), as one ``vmap`` over all elements, and as two
independent ``vmap`` over the two halves of the elements (which XLA could run side by side). Run it once
as it is and once under ``taskset -c 0``: times no shorter with two cores than with one mean the second
core buys the loop nothing (docs/results.md, run time of the Nine test). Prints the median and the
fastest of 30 calls and the compile time; writes nothing. ``--element E --thickness-points K
--assembled-only`` times one element's assembly (the element part of a Newton iteration); for ``anst``
and ``eas`` with the enhanced parameters carried with the Newton iterate (``--enhanced-update local``: by
the local solve, which ``one vmap`` and ``two halves`` always use).
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxfric import scenes
from jaxfric.fem import assembly
from jaxfric.fem.element import element_force_and_tangent, element_geometry
from jaxfric.loadpath.model import initial_state
from jaxfric.loadpath.step import enhanced_carry


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", default="300x3")
    parser.add_argument("--calls", type=int, default=30)
    parser.add_argument("--element", default=None, help="the scene's element (default: the Nine's)")
    parser.add_argument("--thickness-points", type=int, default=2, help="Gauss points through each element")
    parser.add_argument("--assembled-only", action="store_true", help="time the run's assembly only")
    parser.add_argument("--enhanced-update", default="iterate", choices=("iterate", "local"),
                        help="anst/eas: alpha carried with the Newton iterate (the default) or by the local solve")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    overrides = {"mesh": args.mesh, "thickness_points": args.thickness_points, "enhanced_update": args.enhanced_update}
    if args.element is not None:
        overrides["element"] = args.element
    model = scenes.make("nine", "mu017", "lcp_ssn", overrides).model
    mesh, material, formulation = model.mesh, model.material, model.formulation
    geo = element_geometry(mesh.nodes[mesh.elements], model.thickness_points)
    state = initial_state(model)
    states = state.material
    predictor = enhanced_carry(model, state)   # None: the local solve (or no enhanced parameters)
    u = jnp.asarray(np.random.default_rng(0).normal(scale=1e-3, size=mesh.nodes.shape))

    def elements(u, states, part):
        g = jax.tree_util.tree_map(lambda a: a[part], geo)
        s = jax.tree_util.tree_map(lambda a: a[part], states)
        return jax.vmap(lambda *a: element_force_and_tangent(material, formulation, *a))(
            g.gradients(formulation), g.dN_dX_center, g.weight, u[mesh.elements[part]], s)

    def assembled(u, states):
        a = assembly.internal_force_and_tangent(mesh, material, formulation, geo, u, states, predictor)
        return a.f_int, a.tangent

    def halves(u, states):
        n = mesh.n_elements
        first, second = elements(u, states, slice(0, n // 2)), elements(u, states, slice(n // 2, n))
        return jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), first, second)

    cases = (("as assembled", assembled), ("one vmap", lambda u, s: elements(u, s, slice(None))),
             ("two halves", halves))
    for name, fn in cases[:1] if args.assembled_only else cases:
        t = time.perf_counter()
        compiled = jax.jit(fn).lower(u, states).compile()
        compile_s = time.perf_counter() - t
        jax.block_until_ready(compiled(u, states))
        times = []
        for _ in range(args.calls):
            t = time.perf_counter()
            jax.block_until_ready(compiled(u, states))
            times.append(time.perf_counter() - t)
        print(f"{name:13s} median {1e3 * np.median(times):6.2f} ms, fastest {1e3 * min(times):6.2f} ms, "
              f"compiled in {compile_s:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
