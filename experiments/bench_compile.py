"""Compile time of a scene's run program, split into tracing and XLA's compilation:
``python experiments/bench_compile.py [--scene nine] [--variant mu017] [--algorithms lcp_ssn,penalty,auglag]
[--mesh 300x3] [--repeats 1] [--scene-build]``.

``--repeats N``: each algorithm's program compiled N times, each in a fresh process (XLA's compile time
of one program varies by 10 to 25 % from process to process on a 2-core machine).

``--xla-flags=A --xla-flags=B ...``: instead, XLA's compile time of the run's chunk program (the program
:func:`jaxfric.loadpath.run.run` repeats, :func:`~jaxfric.loadpath.simulate.advance`) with ``XLA_FLAGS`` set
to each of A, B, ... in turn (``--repeats`` rounds, the settings alternated, a fresh process each), and how
many windowed reductions the compiled program holds; writes ``experiments/results/bench_compile_flags.csv``.

``--scene-build``: instead, the time to build the scene (``jaxfric.scenes.make``) in two fresh processes in
turn that share a new persistent compilation cache (:mod:`jaxfric.io.cache`, as the command lines enable
it): the first compiles the programs of the build, the second reads them.

For each algorithm, in a fresh process each (JAX keeps traces and executables for the life of a
process), prints the seconds spent tracing and lowering the program that :func:`jaxfric.run` compiles
(``lower``), the program's size (``ops``: StableHLO operations), the wall and the process CPU seconds of
XLA's compilation (``compile``; XLA compiles on more than one thread), and how many times the element tangent was traced
(one per program since ``jaxfric.fem.assembly.shared_trace``; docs/results.md, run time of the Nine test). Writes
nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

_CHILD = r"""
import json, sys, time
import equinox as eqx
import jaxfric
from jaxfric.fem import assembly
from jaxfric.contact import exact_iterate, system
from jaxfric import scenes
simulate = sys.modules["jaxfric.loadpath.simulate"].simulate
scene, variant, algorithm, mesh = sys.argv[1:5]
traced = []
original = assembly.internal_force_and_tangent
def counted(*args, **kwargs):
    traced.append(1)
    return original(*args, **kwargs)
exact_iterate.internal_force_and_tangent = system.internal_force_and_tangent = counted
sc = scenes.make(scene, variant, algorithm, {"mesh": mesh})
fn = eqx.filter_jit(lambda m: simulate(m, newton=sc.newton, control=sc.control, observe=sc.observe))
t = time.perf_counter(); lowered = fn.lower(sc.model); lower = time.perf_counter() - t
ops = sum(1 for line in lowered.as_text().splitlines() if "stablehlo." in line)
cpu = time.process_time(); t = time.perf_counter(); lowered.compile()
compile_s, compile_cpu_s = time.perf_counter() - t, time.process_time() - cpu
print(json.dumps({"lower_s": lower, "compile_s": compile_s, "compile_cpu_s": compile_cpu_s, "ops": ops,
                  "tangent_traces": len(traced)}))
"""

_CHUNK = r"""
import dataclasses, json, sys, time
import jax
import jax.numpy as jnp
import equinox as eqx
jax.config.update("jax_enable_x64", True)
from jaxfric import scenes
from jaxfric.loadpath.run import CHUNK_ROWS
from jaxfric.loadpath.simulate import advance, begin
sc = scenes.make(sys.argv[1], sys.argv[2], sys.argv[3], {"mesh": sys.argv[4]})
control = dataclasses.replace(sc.control, max_steps=None)
rows = jnp.array(1, jnp.int32)
path, _ = eqx.filter_jit(lambda m, r: begin(m, control=control, observe=sc.observe, snapshot=sc.snapshot,
                                            max_steps=r))(sc.model, rows)
chunk = eqx.filter_jit(lambda m, p, k, r: advance(m, p, k, size=CHUNK_ROWS, newton=sc.newton, control=control,
                                                  observe=sc.observe, snapshot=sc.snapshot, max_steps=r))
t = time.perf_counter(); lowered = chunk.lower(sc.model, path, jnp.array(1, jnp.int32), rows)
lower = time.perf_counter() - t
cpu = time.process_time(); t = time.perf_counter(); compiled = lowered.compile()
compile_s, compile_cpu_s = time.perf_counter() - t, time.process_time() - cpu
print(json.dumps({"lower_s": lower, "compile_s": compile_s, "compile_cpu_s": compile_cpu_s,
                  "reduce_windows": compiled.compiled.as_text().count(" reduce-window(")}))
"""

_BUILD = r"""
import json, sys, time
import jax
jax.config.update("jax_enable_x64", True)
from jaxfric.io.cache import enable_compilation_cache
enable_compilation_cache(sys.argv[4])
from jaxfric import scenes
t = time.perf_counter()
scenes.make(sys.argv[1], sys.argv[2], "lcp_ssn", {"mesh": sys.argv[3]})
print(json.dumps({"build_s": time.perf_counter() - t}))
"""


def scene_build(scene: str, variant: str, mesh: str) -> list[float]:
    """Seconds to build the scene in two fresh processes sharing a new compilation cache."""
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR",
                                                            "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS")}
    with tempfile.TemporaryDirectory() as folder:
        times = []
        for _ in range(2):
            out = subprocess.run([sys.executable, "-c", _BUILD, scene, variant, mesh, folder], env=env,
                                 capture_output=True, text=True, check=True)
            times.append(json.loads(out.stdout.strip().splitlines()[-1])["build_s"])
    return times


FLAGS_OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "bench_compile_flags.csv")


def chunk_with_flags(args) -> list[dict]:
    """The chunk program compiled with each ``XLA_FLAGS`` setting of ``args.xla_flags`` in turn, a fresh
    process each, ``args.repeats`` rounds."""
    rows = []
    algorithm = args.algorithms.split(",")[0]
    for round_ in range(args.repeats):
        for flags in args.xla_flags:
            env = {**os.environ, "XLA_FLAGS": flags}
            out = subprocess.run([sys.executable, "-c", _CHUNK, args.scene, args.variant, algorithm, args.mesh],
                                 capture_output=True, text=True, check=True, env=env)
            row = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append({"round": round_, "xla_flags": flags, "scene": args.scene, "variant": args.variant,
                         "algorithm": algorithm, "mesh": args.mesh,
                         **{k: round(v, 3) if isinstance(v, float) else v for k, v in row.items()}})
            print(f"[{flags}] trace and lower {row['lower_s']:.2f} s, XLA compile {row['compile_s']:.2f} s "
                  f"({row['compile_cpu_s']:.2f} s CPU), {row['reduce_windows']} windowed reductions", flush=True)
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="nine")
    parser.add_argument("--variant", default="mu017")
    parser.add_argument("--algorithms", default="lcp_ssn,penalty,auglag")
    parser.add_argument("--mesh", default="300x3")
    parser.add_argument("--repeats", type=int, default=1, help="compilations of each program, a process each")
    parser.add_argument("--scene-build", action="store_true", help="time the scene's build, compiled then cached")
    parser.add_argument("--xla-flags", action="append", metavar="FLAGS",
                        help="compile the chunk program with XLA_FLAGS=FLAGS; repeat the option for each setting, "
                             "given as --xla-flags=FLAGS (the settings are taken in turn)")
    args = parser.parse_args(argv)
    if args.xla_flags:
        from benchutil import read_rows
        from jaxfric.io.batch import write_csv
        rows = chunk_with_flags(args)
        case = [rows[0][k] for k in ("scene", "variant", "algorithm", "mesh")]
        # Keep the rows of other scenes, variants, algorithms and meshes.
        kept = [r for r in read_rows(FLAGS_OUT) if [r[k] for k in ("scene", "variant", "algorithm", "mesh")] != case]
        write_csv(FLAGS_OUT, kept + rows)
        return 0
    if args.scene_build:
        first, second = scene_build(args.scene, args.variant, args.mesh)
        print(f"{args.scene} {args.variant} {args.mesh}: scene built in {first:.2f} s compiling, "
              f"{second:.2f} s from the compilation cache")
        return 0
    for _ in range(args.repeats):
        for algorithm in args.algorithms.split(","):
            out = subprocess.run([sys.executable, "-c", _CHILD, args.scene, args.variant, algorithm, args.mesh],
                                 capture_output=True, text=True, check=True)
            row = json.loads(out.stdout.strip().splitlines()[-1])
            print(f"{args.scene} {args.variant} {algorithm} {args.mesh}: lower {row['lower_s']:.2f} s, "
                  f"{row['ops']} ops, XLA compile {row['compile_s']:.2f} s ({row['compile_cpu_s']:.2f} s CPU), "
                  f"element tangent traced {row['tangent_traces']}x", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
