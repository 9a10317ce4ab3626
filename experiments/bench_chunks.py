"""What running in chunks costs: the `make run` case (Nine mu017, spec mesh, exact contact) run in
chunks with the command line's partial writes (:func:`jaxfric.run`), against the same load path in one
compiled loop (:func:`jaxfric.simulate`), alternated in one process so that both see the same machine.

    python experiments/bench_chunks.py [--repeats 4] [--mesh 300x3] [--u-draw 70] [--one-step]

Writes ``experiments/results/bench_chunks.csv``: per run, the solve wall time and process CPU time and,
for the chunked runs, the chunks, the time inside the compiled calls, the host's time between them and
the time of the partial writes. Whole runs on a shared machine spread by more than the cost sought; with
``--one-step`` each repeat adds a run in chunks of one step, whose extra time inside the compiled calls
per extra chunk is the cost of a boundary (:func:`boundary_cost`).
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


def chunked(scene, out: str, one_step: bool = False) -> dict:
    """The chunked run; ``one_step``: every chunk after the first holds one step (``CHUNK_SECONDS`` 0), so
    that the cost of a chunk's boundary, multiplied by the chunks, stands out of the machine's noise."""
    from jaxfric import cli
    from jaxfric.io import checkpoint
    from jaxfric.loadpath import run as driver

    timed = _Timed(cli._PartialWriter(scene, out, None, checkpoint.configuration(scene)))
    seconds = driver.CHUNK_SECONDS
    driver.CHUNK_SECONDS = 0.0 if one_step else seconds
    try:
        t, c = time.perf_counter(), time.process_time()
        result = jf.run(scene.model, newton=scene.newton, control=scene.control, observe=scene.observe,
                        snapshot=scene.snapshot, keep_snapshots=InstantRows(scene.name),
                        progress=False, on_chunk=timed)
    finally:
        driver.CHUNK_SECONDS = seconds
    total = time.perf_counter() - t - result.compile_s
    return {"driver": "1-step chunks" if one_step else "chunks", "solve_s": total,
            "cpu_s": time.process_time() - c, "chunk_s": result.wall_s, "host_s": total - result.wall_s,
            "write_s": timed.write_s, "chunks": timed.chunks, "steps": len(result.history["time"]) - 1}


def single(scene, program) -> dict:
    t, c = time.perf_counter(), time.process_time()
    sim = jax.block_until_ready(program(scene.model))
    return {"driver": "one loop", "solve_s": time.perf_counter() - t, "cpu_s": time.process_time() - c,
            "steps": int(sim.history.n_rows) - 1}


def boundary_cost(rows: list[dict]) -> str:
    """What the chunks' boundaries cost, from runs in chunks of one step beside the default chunks: the
    time inside the compiled calls grows by one boundary's cost per extra chunk (the same program, the
    same steps), and the default run pays that for each of its chunks plus its host time between them."""
    def total(driver, key):
        return sum(float(r[key]) for r in rows if r["driver"] == driver)

    per = ((total("1-step chunks", "chunk_s") - total("chunks", "chunk_s"))
           / (total("1-step chunks", "chunks") - total("chunks", "chunks")))
    share = (per * total("chunks", "chunks") + total("chunks", "host_s")) / total("one loop", "solve_s")
    return (f"a chunk's boundary costs {1e3 * per:.1f} ms inside the compiled calls; the default chunks' "
            f"boundaries with the host's time between them {100 * share:.2f} % of the one loop's solve")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=4)
    parser.add_argument("--u-draw", type=float, default=70.0, help="the drawing stroke (mm)")
    parser.add_argument("--mesh", default="300x3")
    parser.add_argument("--variant", default="mu017")
    parser.add_argument("--one-step", action="store_true",
                        help="also the run in chunks of one step: the cost of a chunk's boundary")
    args = parser.parse_args(argv)
    scene = scenes.make("nine", args.variant, "lcp_ssn", {"mesh": args.mesh, "U_draw": args.u_draw})
    program = eqx.filter_jit(lambda m: jf.simulate(m, newton=scene.newton, control=scene.control,
                                                   observe=scene.observe)).lower(scene.model).compile()
    rows = []
    with tempfile.TemporaryDirectory() as out:
        chunked(scene, out)  # compiles the chunked programs
        for k in range(args.repeats):
            drivers = [lambda: chunked(scene, out), lambda: single(scene, program)]
            drivers += [lambda: chunked(scene, out, one_step=True)] if args.one_step else []
            for make in drivers:
                row = make()
                rows.append({"repeat": k, **row})
                print(rows[-1], flush=True)
    os.makedirs(RESULTS, exist_ok=True)
    path = os.path.join(RESULTS, "bench_chunks.csv")
    keys = ["repeat", "driver", "steps", "solve_s", "cpu_s", "chunk_s", "host_s", "write_s", "chunks"]
    one = [r["solve_s"] for r in rows if r["driver"] == "one loop"]
    chunks = [r["solve_s"] for r in rows if r["driver"] == "chunks"]
    host = sum(r["host_s"] for r in rows if r["driver"] == "chunks") / sum(chunks)
    cpu = [sum(r["cpu_s"] for r in rows if r["driver"] == d) for d in ("chunks", "one loop")]
    ones = [r for r in rows if r["driver"] == "1-step chunks"]
    if ones:
        print(boundary_cost(rows))
    print(f"solve: chunks / one loop = {sum(chunks) / sum(one):.4f} (pairs: "
          + ", ".join(f"{c / o:.3f}" for c, o in zip(chunks, one)) + f"); host time between chunks {100 * host:.2f} %;"
          f" process CPU time: chunks / one loop = {cpu[0] / cpu[1]:.4f}")
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=keys)
        writer.writeheader()
        writer.writerows({k: r.get(k, "") for k in keys} for r in rows)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
