"""The element tangent's cost: the library's (F-bar's gradient and geometric term and the radial return's
consistent tangent dP/dF in closed form), the same with dP/dF by ``jacfwd`` of the point law
(``tangent_material_ad``), and everything by automatic differentiation (``tangent_ad``: dP/dF by
``jacfwd``, the kinematics forward, and forward over reverse for the geometric term); and, for where
an element evaluation's time goes, the library's with the element axis last in every array
(``tangent_element_axis_last``: ``vmap`` over the last axis, the transpositions inside the program) and
the point law alone (``point_law``: the radial return's stress and consistent tangent at every Gauss point).

    python experiments/bench_element_tangent.py [--mesh 300x3] [--element ans] [--rounds 15]

Times, on the Nine's mesh at a plastic state (random nodal displacements of 0.03 mm from the virgin
state), the forces and tangents of all elements, one ``vmap`` jitted alone, the variants alternated
in one process, and the geometric term alone both ways. Process CPU time (``time.process_time``), so
that another process on the same core does not enter the figures; pin it with ``taskset -c N`` and one
XLA thread (``XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"``). Writes
``experiments/results/bench_element_tangent.csv`` (one row per variant, element and mesh: median and
fastest call, the median per-round ratios to the AD variant and to the library's tangent, and how closely
the tangents agree).
"""

from __future__ import annotations

import argparse
import csv
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxfric import scenes
from jaxfric.fem import element as el
from jaxfric.fem.element import element_geometry
from jaxfric.fem.material import piola_and_tangent_ad
from jaxfric.io.batch import write_csv
from jaxfric.loadpath.model import initial_state

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "bench_element_tangent.csv")


def tangent_with_ad_geometric_term(material, formulation, dN_dX, dN_dX_center, weight, u_e, states):
    """:func:`jaxfric.fem.element.element_force_and_tangent` for ``fbar``/``ans`` with dF_bar/du by
    forward mode and the geometric term as the forward-over-reverse Hessian of the kinematics."""
    def kinematics(v):
        return el._kinematics(formulation, dN_dX, dN_dX_center, weight, v.reshape(4, 2), jnp.zeros(0))

    v = u_e.ravel()
    Fb, _, dF_dv = el._value_and_jacfwd(kinematics, v)
    dP_dF, (P, _, _) = jax.vmap(lambda F, s: piola_and_tangent_ad(material, F, s))(Fb, states)
    wP = weight[:, None, None] * P
    f_e = jnp.einsum("gij,gija->a", wP, dF_dv)
    K_e = jnp.einsum("g,gija,gijkl,gklb->ab", weight, dF_dv, dP_dF, dF_dv)
    K_e = K_e + jax.jacfwd(jax.grad(lambda w: jnp.sum(jax.lax.stop_gradient(wP) * kinematics(w)[0])))(v)
    return f_e.reshape(4, 2), K_e


def tangent_with_ad_material(*args):
    """:func:`jaxfric.fem.element.element_force_and_tangent` with dP/dF by ``jacfwd`` of the point law."""
    closed = el.piola_and_tangent
    el.piola_and_tangent = piola_and_tangent_ad   # while the call is traced
    try:
        return el.element_force_and_tangent(*args)
    finally:
        el.piola_and_tangent = closed


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", default="300x3")
    parser.add_argument("--element", default="ans", choices=("ans", "fbar"))
    parser.add_argument("--rounds", type=int, default=15)
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    model = scenes.make("nine", "mu017", "lcp_ssn", {"mesh": args.mesh, "element": args.element}).model
    mesh, material, formulation = model.mesh, model.material, args.element
    geo = element_geometry(mesh.nodes[mesh.elements], model.thickness_points)
    states = initial_state(model).material
    u_e = jnp.asarray(np.random.default_rng(0).normal(scale=0.03, size=mesh.nodes.shape))[mesh.elements]
    dN, dN0, w = geo.gradients(formulation), geo.dN_dX_center, geo.weight
    S = jnp.asarray(np.random.default_rng(1).normal(size=(mesh.n_elements, dN.shape[1], 2, 2)))

    def batched(fn):
        return jax.jit(lambda u, s: jax.vmap(lambda *a: fn(material, formulation, *a))(dN, dN0, w, u, s))

    def ad_term(S_e, dN_e, dN0_e, w_e, u):
        def term(v):
            return jnp.sum(S_e * el._kinematics(formulation, dN_e, dN0_e, w_e, v.reshape(4, 2), jnp.zeros(0))[0])
        return jax.jacfwd(jax.grad(term))(u.ravel())

    def axis_last(u, s):
        moved = jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, 0, -1), (dN, dN0, w, u, s))
        f, K, _ = jax.vmap(lambda *a: el.element_force_and_tangent(material, formulation, *a),
                           in_axes=-1, out_axes=-1)(*moved)
        return jnp.moveaxis(f, -1, 0), jnp.moveaxis(K, -1, 0)

    F_points = jax.vmap(lambda *a: el._kinematics(formulation, *a, jnp.zeros(0))[0])(dN, dN0, w, u_e)
    point_law = jax.jit(jax.vmap(jax.vmap(lambda F, s: el.piola_and_tangent(material, F, s))))

    calls = {
        "tangent_closed_form": (batched(el.element_force_and_tangent), (u_e, states)),
        "tangent_element_axis_last": (jax.jit(axis_last), (u_e, states)),
        "point_law": (point_law, (F_points, states)),
        "tangent_material_ad": (batched(tangent_with_ad_material), (u_e, states)),
        "tangent_ad": (batched(tangent_with_ad_geometric_term), (u_e, states)),
        "geometric_term_closed_form": (jax.jit(jax.vmap(
            lambda S_e, d, d0, u: el._fbar_geometric_term(S_e, el._fbar_parts(d, d0, u), d))), (S, dN, dN0, u_e)),
        "geometric_term_ad": (jax.jit(jax.vmap(ad_term)), (S, dN, dN0, w, u_e)),
    }
    out = {name: jax.block_until_ready(fn(*a)) for name, (fn, a) in calls.items()}
    K_ad = out["tangent_ad"][1]
    agree = max(float(jnp.max(jnp.abs(out[name][1] - K_ad)) / jnp.max(jnp.abs(K_ad)))
                for name in ("tangent_closed_form", "tangent_material_ad", "tangent_element_axis_last"))
    plastic = float(jnp.mean(jax.vmap(lambda *a: el.element_force(material, formulation, *a)[1][0].eqps)(
        dN, dN0, w, u_e, states) > 0))
    times: dict[str, list] = {name: [] for name in calls}
    for _ in range(args.rounds):
        for name, (fn, a) in calls.items():
            t0 = time.process_time()
            jax.block_until_ready(fn(*a))
            times[name].append(time.process_time() - t0)
    rows = []
    for name, t in times.items():
        ref = times["geometric_term_ad" if name.startswith("geometric") else "tangent_ad"]
        rows.append({"variant": name, "element": formulation, "mesh": args.mesh, "plastic_points": plastic,
                     "median_ms": round(1e3 * float(np.median(t)), 3), "fastest_ms": round(1e3 * min(t), 3),
                     "ratio_to_ad": round(float(np.median(np.array(t) / np.array(ref))), 3),
                     "ratio_to_library": round(float(np.median(np.array(t) / np.array(
                         times["tangent_closed_form"]))), 3),
                     "tangents_agree_to": agree})
        print(f"{name:28s} median {1e3 * np.median(t):7.2f} ms  fastest {1e3 * min(t):7.2f} ms  "
              f"ratio to AD {rows[-1]['ratio_to_ad']:.3f}  to the library's {rows[-1]['ratio_to_library']:.3f}")
    print(f"tangents agree to {agree:.1e} (relative); plastic points {plastic:.0%}")
    if os.path.exists(OUT):  # keep the other elements' and meshes' rows
        with open(OUT, newline="") as fh:
            rows = [r for r in csv.DictReader(fh)
                    if (r["element"], r["mesh"]) != (formulation, args.mesh)] + rows
    write_csv(OUT, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
