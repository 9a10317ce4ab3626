"""What the pair pre-selection (``jaxfric.contact.preselection``) evaluates and saves.

    python experiments/bench_preselection.py [--mesh 300x3 1200x3 2400x3] [--steps-mesh 300x3]
                                             [--algorithm lcp_ssn] [--out results/bench_preselection.csv]

Three parts, each with the pre-selection on (``preselect=true``) and off (the scenes' default, ``preselect``
None, is off below ``jaxfric.contact.preselection.PAYS_FROM`` left-out pairs):

- ``pairs``: per scene and variant at its spec mesh, the candidate pairs and the pairs a step evaluates
  (the tools' capacities summed);
- ``geometry``: the Nine's pair evaluation of one Newton iterate (exact contact's projections and their
  forward derivatives, or with ``--algorithm penalty`` the penalty law's forces and Jacobians), at each
  ``--mesh``: median time of 200 calls, the two settings alternated in rounds;
- ``step``: the Nine (``mu017``) drawn to U = 2 mm, then ``--steps`` drawing steps from the secant
  predictor timed whole, on each ``--steps-mesh``; the two settings start from the same converged state
  (the run without the pre-selection), take the same Newton iterations and active-set passes (checked),
  and are timed alternately, ten rounds: ms per Newton iteration.

One XLA thread is assumed (``XLA_FLAGS=--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1``,
pinned with ``taskset``). Writes ``results/bench_preselection.csv``.
"""

from __future__ import annotations

import argparse
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from benchutil import write_rows  # noqa: E402
from jaxfric import scenes  # noqa: E402
from jaxfric.contact.exact_iterate import _geometry  # noqa: E402
from jaxfric.contact.rigid import evaluate_pairs  # noqa: E402
from jaxfric.loadpath.model import initial_state, tool_positions  # noqa: E402
from jaxfric.loadpath.simulate import simulate  # noqa: E402
from jaxfric.loadpath.step import StepContext, solve_step, step_args  # noqa: E402
from jaxfric.numerics.newton import NewtonOptions  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
SETTINGS = (True, False)


def pair_counts() -> list[dict]:
    """Candidate and evaluated pairs of every scene variant at its spec mesh (building the scenes only)."""
    rows = []
    for name in scenes.scene_names():
        for variant in scenes.variants(name):
            tools = scenes.make(name, variant, "lcp_ssn").model.tools
            rows.append({"part": "pairs", "case": f"{name} {variant}",
                         "candidates": sum(len(t.candidates) for t in tools),
                         "evaluated": sum(t.capacity or len(t.candidates) for t in tools),
                         "tools": " ".join(f"{t.name}:{t.capacity or len(t.candidates)}/{len(t.candidates)}"
                                           for t in tools)})
    return rows


def _alternated(calls: dict, rounds: int, repeat: int) -> dict:
    """Median time (s) of each of ``calls`` (setting -> function of no argument), the settings alternated
    in ``rounds`` rounds of ``repeat`` calls, after one warm-up call each."""
    for fn in calls.values():
        fn()
    times = {k: [] for k in calls}
    for r in range(rounds):
        for k in (list(calls) if r % 2 == 0 else list(reversed(list(calls)))):
            for _ in range(repeat):
                t0 = time.perf_counter()
                calls[k]()
                times[k].append(time.perf_counter() - t0)
    return {k: float(np.median(v)) for k, v in times.items()}


def geometry(mesh: str, algorithm: str) -> list[dict]:
    """The pairs' evaluation of one iterate of the clamping's first step, with and without the selection."""
    calls, counts = {}, {}
    for on in SETTINGS:
        scene = scenes.make("nine", "mu017", algorithm, {"mesh": mesh, "preselect": on})
        model = scene.model
        state = initial_state(model)
        args, _, _ = step_args(model, state, 0, 0.01, StepContext.build(model))
        u, q = state.u, tool_positions(state)
        if algorithm == "penalty":
            fn = eqx.filter_jit(lambda ar: evaluate_pairs(ar.contact, ar.mesh.nodes, u, q, True))
        else:
            fn = eqx.filter_jit(lambda ar: _geometry(ar.contact, ar.mesh.nodes, u, q))
        calls[on] = (lambda fn=fn, args=args: jax.block_until_ready(fn(args)))
        counts[on] = sum(t.capacity or len(t.candidates) for t in model.tools)
    ms = {k: 1e3 * v for k, v in _alternated(calls, rounds=4, repeat=50).items()}
    return [{"part": "geometry", "case": f"nine mu017 {mesh} {algorithm}", "candidates": counts[False],
             "evaluated": counts[True], "ms_on": round(ms[True], 4), "ms_off": round(ms[False], 4),
             "ratio": round(ms[True] / ms[False], 3)}]


def steps(mesh: str, algorithm: str, n_steps: int, u0: float = 2.0) -> list[dict]:
    """Whole drawing steps from one converged state with and without the selection (module doc)."""
    short = scenes.make("nine", "mu017", algorithm, {"mesh": mesh, "preselect": False, "U_draw": u0})
    sim = eqx.filter_jit(lambda m: simulate(m, control=short.control))(short.model)
    if int(sim.code) != 0:
        raise RuntimeError(f"the run to U = {u0} mm did not converge (code {int(sim.code)})")
    calls, work = {}, {}
    for on in SETTINGS:
        scene = scenes.make("nine", "mu017", algorithm, {"mesh": mesh, "preselect": on})
        model, config = scene.model, scene.config
        state = eqx.tree_at(lambda s: s.time, sim.final, jnp.asarray(1.0 + u0 / config.U_draw))
        ctx, opts, dt = StepContext.build(model), NewtonOptions(), config.dU / config.U_draw
        step = eqx.filter_jit(lambda st, t, g, model=model, ctx=ctx: solve_step(model, st, 1, t, opts, ctx, guess=g))
        sequence, prev, its, passes = [], None, [], []
        for s in range(n_steps + 2):
            t = float(state.time) + dt
            guess = (state.u, state.contact.q) if prev is None else \
                (2 * state.u - prev.u, 2 * state.contact.q - prev.contact.q)
            sol, new = jax.block_until_ready(step(state, t, guess))
            if int(sol.code) != 0:
                raise RuntimeError(f"step {s} did not converge (code {int(sol.code)})")
            if s >= 2:   # the first two: the predictor's start
                sequence.append((state, t, guess))
                its.append(int(sol.iterations))
                passes.append(int(sol.stats[1]))
            prev, state = state, new
        calls[on] = (lambda step=step, sequence=sequence: [jax.block_until_ready(step(*a)) for a in sequence])
        work[on] = (its, passes)
    if work[True] != work[False]:
        raise RuntimeError(f"the two settings took different iterations and passes: {work}")
    iterations = sum(work[True][0])
    ms = {k: 1e3 * v / iterations for k, v in _alternated(calls, rounds=10, repeat=1).items()}
    return [{"part": "step", "case": f"nine mu017 {mesh} {algorithm}", "iterations": iterations,
             "passes": sum(work[True][1]), "ms_on": round(ms[True], 3), "ms_off": round(ms[False], 3),
             "ratio": round(ms[True] / ms[False], 3)}]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", nargs="*", default=["300x3", "1200x3", "2400x3"])
    ap.add_argument("--steps-mesh", nargs="*", default=["300x3"])
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--algorithm", default="lcp_ssn")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "bench_preselection.csv"))
    a = ap.parse_args(argv)
    rows = pair_counts()
    for mesh in a.mesh:
        rows += geometry(mesh, a.algorithm)
    for mesh in a.steps_mesh:
        rows += steps(mesh, a.algorithm, a.steps)
    for r in rows:
        print(r, flush=True)
    fields = ["part", "case", "candidates", "evaluated", "tools", "iterations", "passes", "ms_on", "ms_off", "ratio"]
    write_rows(a.out, [{f: r.get(f, "") for f in fields} for r in rows])


if __name__ == "__main__":
    main()
