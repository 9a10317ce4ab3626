"""Compile time of a scene's run program, split into tracing and XLA's compilation:
``python experiments/bench_compile.py [--scene nine] [--variant mu017] [--algorithms lcp_ssn,penalty,auglag]
[--mesh 300x3]``.

For each algorithm, in a fresh process each (JAX keeps traces and executables for the life of a
process), prints the seconds spent tracing and lowering the program that :func:`jaxfric.run` compiles
(``lower``) and in XLA's compilation (``compile``), and how many times the element tangent was traced
(one per program since ``jaxfric.fem.assembly.shared_trace``; docs/results.md, run time of the Nine test). Writes
nothing.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

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
t = time.perf_counter(); lowered.compile(); compile_s = time.perf_counter() - t
print(json.dumps({"lower_s": lower, "compile_s": compile_s, "tangent_traces": len(traced)}))
"""


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="nine")
    parser.add_argument("--variant", default="mu017")
    parser.add_argument("--algorithms", default="lcp_ssn,penalty,auglag")
    parser.add_argument("--mesh", default="300x3")
    args = parser.parse_args(argv)
    for algorithm in args.algorithms.split(","):
        out = subprocess.run([sys.executable, "-c", _CHILD, args.scene, args.variant, algorithm, args.mesh],
                             capture_output=True, text=True, check=True)
        row = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"{args.scene} {args.variant} {algorithm} {args.mesh}: lower {row['lower_s']:.2f} s, "
              f"XLA compile {row['compile_s']:.2f} s, element tangent traced {row['tangent_traces']}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
