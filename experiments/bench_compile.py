"""Compile time of a scene's run program, split into tracing and XLA's compilation:
``python experiments/bench_compile.py [--scene nine] [--variant mu017] [--algorithms lcp_ssn,penalty,auglag]
[--mesh 300x3] [--repeats 1] [--scene-build]``.

``--repeats N``: each algorithm's program compiled N times, each in a fresh process (XLA's compile time
of one program varies by 10 to 25 % from process to process on a 2-core machine).

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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="nine")
    parser.add_argument("--variant", default="mu017")
    parser.add_argument("--algorithms", default="lcp_ssn,penalty,auglag")
    parser.add_argument("--mesh", default="300x3")
    parser.add_argument("--repeats", type=int, default=1, help="compilations of each program, a process each")
    parser.add_argument("--scene-build", action="store_true", help="time the scene's build, compiled then cached")
    args = parser.parse_args(argv)
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
