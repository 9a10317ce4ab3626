"""What running in chunks costs: the `make run` case (Nine mu017, spec mesh, exact contact) run in
chunks with the command line's partial writes (:func:`jaxfric.run`), against the same load path in one
compiled loop (:func:`jaxfric.simulate`), alternated in one process so that both see the same machine.

    python experiments/bench_chunks.py [--repeats 4] [--mesh 300x3] [--u-draw 70]

Writes ``experiments/results/bench_chunks.csv``: per run, the solve wall time and, for the chunked runs,
the chunks, the host's time between them and the time of the partial writes.
"""

from __future__ import annotations

import argparse
import csv
import os
import tempfile
import time

import equinox as eqx
import jax

import jaxfric as jf
from jaxfric import scenes
from jaxfric.io.instants import InstantRows

RESULTS = os.path.join(os.path.dirname(__file__), "results")


class _Timed:
    """``on_chunk`` wrapper: counts the chunks and times the wrapped writer."""

    def __init__(self, writer):
        self.writer, self.chunks, self.write_s = writer, 0, 0.0

    def __call__(self, partial):
        self.chunks += 1
        t = time.perf_counter()
        self.writer(partial)
        self.write_s += time.perf_counter() - t


def chunked(scene, out: str) -> dict:
    from jaxfric import cli
    from jaxfric.io import checkpoint

    timed = _Timed(cli._PartialWriter(scene, out, None, checkpoint.configuration(scene)))
    t = time.perf_counter()
    result = jf.run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                    snapshot=scene.snapshot, keep_snapshots=InstantRows(scene.name),
                    progress=False, on_chunk=timed)
    total = time.perf_counter() - t - result.compile_s
    return {"driver": "chunks", "solve_s": total, "chunk_s": result.wall_s, "host_s": total - result.wall_s,
            "write_s": timed.write_s, "chunks": timed.chunks, "steps": len(result.history["time"]) - 1}


def single(scene, program) -> dict:
    t = time.perf_counter()
    sim = jax.block_until_ready(program(scene.model))
    return {"driver": "one loop", "solve_s": time.perf_counter() - t, "steps": int(sim.history.n_rows) - 1}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=4)
    parser.add_argument("--u-draw", type=float, default=70.0, help="the drawing stroke (mm)")
    parser.add_argument("--mesh", default="300x3")
    parser.add_argument("--variant", default="mu017")
    args = parser.parse_args(argv)
    scene = scenes.make("nine", args.variant, "lcp_ssn", {"mesh": args.mesh, "U_draw": args.u_draw})
    program = eqx.filter_jit(lambda m: jf.simulate(m, newton=scene.newton, control=scene.control,
                                                   observe=scene.observe)).lower(scene.model).compile()
    rows = []
    with tempfile.TemporaryDirectory() as out:
        chunked(scene, out)  # compiles the chunked programs
        for k in range(args.repeats):
            for row in (chunked(scene, out), single(scene, program)):
                rows.append({"repeat": k, **row})
                print(rows[-1], flush=True)
    os.makedirs(RESULTS, exist_ok=True)
    path = os.path.join(RESULTS, "bench_chunks.csv")
    keys = ["repeat", "driver", "steps", "solve_s", "chunk_s", "host_s", "write_s", "chunks"]
    one = [r["solve_s"] for r in rows if r["driver"] == "one loop"]
    chunks = [r["solve_s"] for r in rows if r["driver"] == "chunks"]
    host = sum(r["host_s"] for r in rows if r["driver"] == "chunks") / sum(chunks)
    print(f"solve: chunks / one loop = {sum(chunks) / sum(one):.4f} (pairs: "
          + ", ".join(f"{c / o:.3f}" for c, o in zip(chunks, one)) + f"); host time between chunks {100 * host:.2f} %")
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=keys)
        writer.writeheader()
        writer.writerows({k: r.get(k, "") for k in keys} for r in rows)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
