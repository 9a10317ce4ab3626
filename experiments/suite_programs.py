"""Which programs the fast suite compiles, and how many of them differ only by their arrays' sizes: a
pytest plugin that records every XLA compilation with the program's identity, and a summary by structure.

Record (the suite as ``make test`` runs it, with this plugin; each process writes its own file):

    JAXFRIC_TEST_CACHE=fresh PYTHONPATH=experiments .venv/bin/python -m pytest -p suite_programs -m "not slow" -n 2 \\
        --dist loadfile --no-loadscope-reorder tests

Summarise (writes ``experiments/results/suite_programs.csv``, one row per structure, and prints the
totals):

    python experiments/suite_programs.py

Each compilation that reaches XLA (:func:`jax._src.compiler.compile_or_get_cached`: the in-process cache
of JAX answers before it, the persistent cache inside it) is recorded with the test that ran it, its
wall time, its StableHLO operations and two fingerprints of its module, without debug locations:

- ``program``: the module's text. Equal programs compile to equal executables; a second compilation of one
  happens in another process (pytest-xdist's other worker), where the persistent cache answers for the
  programs that took a second or more;
- ``structure``: the text with every number (arrays' dimensions, slice bounds, indices) and every literal
  constant left out. Programs of one structure are one computation on arrays of other sizes (another
  mesh, another number of steps or pairs) or with other constants folded in; tests that used one size
  where their check allows would compile that structure once.

The summary's rows, largest first: per structure its compile seconds in all, the programs (exact
fingerprints) and compilations, the seconds a single program of the structure would have taken (the
largest compilation), what the rest cost (``beyond_one_s``), and the tests.
Command lines that tests start in a new process are not recorded.

The plugin also records each run program that :func:`jaxfric.run` compiles (its start and chunk,
:func:`jaxfric.loadpath.run._compile`) with the model's configuration: the tools, the mesh, the element
formulation, the contact formulation, the material, the snapshot and the Newton and step-control options,
and a digest of the model's structure (its pytree definition, static fields included: the mesh's node
numbers among them, so another mesh is another structure). The summary writes
``experiments/results/suite_programs_runs.csv`` (one row per compilation) and prints how many model
configurations there are and which of them share a model structure, differing only in the options
(those would compile once if the options were data).
"""

from __future__ import annotations

import collections
import csv
import hashlib
import os
import re
import shutil
import time

from suite_compile import read_records, write_records

HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.join(HERE, "results")
RECORDS = os.path.join(RESULTS, "suite_programs_records")
RUN_RECORDS = os.path.join(RESULTS, "suite_programs_runs_records")
OUT = os.path.join(RESULTS, "suite_programs.csv")
RUNS_OUT = os.path.join(RESULTS, "suite_programs_runs.csv")
OPTIONS = ("snapshot", "newton", "control")   # a run program's options besides the model

_DENSE = re.compile(r"dense<[^>]*>")
_NAME = re.compile(r"@[A-Za-z0-9_.$-]+")
_NUMBER = re.compile(r"\d+")   # sizes, slice bounds, indices: in types and attributes alike


def fingerprints(text: str) -> tuple[str, str]:
    """(program, structure) digests of a module's text (see the module's docstring)."""
    structure = _NUMBER.sub("N", _NAME.sub("@f", _DENSE.sub("dense<c>", text)))
    return (hashlib.sha1(text.encode()).hexdigest()[:16], hashlib.sha1(structure.encode()).hexdigest()[:16])


# ---- the plugin --------------------------------------------------------------------------------------

_records: list = []
_current = {"test": None}


def _wrap(compile_or_get_cached):
    def recorded(backend, computation, *args, **kwargs):
        t = time.perf_counter()
        out = compile_or_get_cached(backend, computation, *args, **kwargs)
        seconds = time.perf_counter() - t
        text = computation.operation.get_asm(enable_debug_info=False, large_elements_limit=8)
        program, structure = fingerprints(text)
        name = str(computation.operation.attributes["sym_name"]).strip('"')
        ops = text.count("stablehlo.")
        _records.append((_current["test"], name, program, structure, ops, seconds))
        return out
    return recorded


_run_records: list = []


def describe_run(model, newton, control, snapshot) -> dict:
    """A run program's configuration (module docstring): what tells the suite's run programs apart."""
    import jax

    mesh = model.mesh
    contact = model.contact
    return {"tools": " ".join(t.name for t in model.tools) or "-",
            "mesh": f"{mesh.nx}x{mesh.ny}" + ("" if mesh.order == 1 else f" order {mesh.order}"),
            "formulation": model.formulation,
            "contact": "-" if contact is None else type(contact).__name__ + (
                f" {contact.solver}" if hasattr(contact, "solver") else ""),
            "material": type(model.material).__name__,
            "snapshot": "-" if snapshot is None else type(snapshot).__name__,
            "newton": repr(newton), "control": repr(control),
            "structure": hashlib.sha1(str(jax.tree_util.tree_structure(model)).encode()).hexdigest()[:16]}


def _wrap_run(compile_run):
    def recorded(model, newton, control, observe, snapshot):
        t = time.perf_counter()
        out = compile_run(model, newton, control, observe, snapshot)
        if hasattr(model, "mesh"):   # not a test's stand-in model (tests/test_bad_input.py)
            _run_records.append({"test": _current["test"], "seconds": round(time.perf_counter() - t, 3),
                                 **describe_run(model, newton, control, snapshot)})
        return out
    return recorded


def pytest_configure(config):
    from jax._src import compiler
    from jax._src.interpreters import pxla

    from jaxfric.loadpath import run

    if not hasattr(config, "workerinput"):     # the run's first process: earlier records go
        shutil.rmtree(RECORDS, ignore_errors=True)
        shutil.rmtree(RUN_RECORDS, ignore_errors=True)
    pxla.compiler.compile_or_get_cached = _wrap(compiler.compile_or_get_cached)
    run._compile = _wrap_run(run._compile)


def pytest_runtest_setup(item):
    _current["test"] = item.nodeid


def pytest_unconfigure(config):
    write_records(config, _records, RECORDS)
    write_records(config, _run_records, RUN_RECORDS)


# ---- the summary -------------------------------------------------------------------------------------

def by_structure(records: list) -> list[dict]:
    """One row per structure (see the module's docstring), the costliest first."""
    groups: dict = collections.defaultdict(list)
    for rec in records:
        groups[rec[3]].append(rec)
    rows = []
    for structure, recs in groups.items():
        seconds = [r[5] for r in recs]
        tests = sorted({(r[0] or "(collection)").split("::")[0].removeprefix("tests/") for r in recs})
        rows.append({"structure": structure, "name": collections.Counter(r[1] for r in recs).most_common(1)[0][0],
                     "ops": max(r[4] for r in recs), "compile_s": round(sum(seconds), 2),
                     "programs": len({r[2] for r in recs}), "compilations": len(recs),
                     "one_program_s": round(max(seconds), 2),
                     "beyond_one_s": round(sum(seconds) - max(seconds), 2),
                     "test_files": len(tests), "tests": " ".join(tests)})
    return sorted(rows, key=lambda r: -r["compile_s"])


def shared_structures(runs: list) -> list[dict]:
    """The model structures compiled with more than one set of options: per structure, its configurations'
    compilations, seconds and tests, and the options that differ."""
    groups: dict = collections.defaultdict(list)
    for r in runs:
        groups[r["structure"]].append(r)
    out = []
    for structure, recs in groups.items():
        configurations = {tuple(r[k] for k in OPTIONS) for r in recs}
        if len(configurations) > 1:
            out.append({"structure": structure, "tools": recs[0]["tools"], "mesh": recs[0]["mesh"],
                        "compilations": len(recs), "seconds": round(sum(r["seconds"] for r in recs), 1),
                        "differ": [k for i, k in enumerate(OPTIONS) if len({c[i] for c in configurations}) > 1],
                        "tests": sorted({(r["test"] or "").split("::")[0].removeprefix("tests/") for r in recs})})
    return sorted(out, key=lambda r: -r["seconds"])


def summarise_runs(runs: list) -> None:
    """Writes :data:`RUNS_OUT` and prints the run programs' configurations (module docstring)."""
    fields = ["test", "seconds", "tools", "mesh", "formulation", "contact", "material", *OPTIONS, "structure"]
    with open(RUNS_OUT, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fields)
        writer.writeheader()
        writer.writerows(sorted(runs, key=lambda r: (r["tools"], r["mesh"], r["test"] or "")))
    configurations = {(r["structure"], *(r[k] for k in OPTIONS)) for r in runs}
    print(f"run programs (jaxfric.run's start and chunk): {len(runs)} compilations, "
          f"{sum(r['seconds'] for r in runs):.0f} s (tracing included), {len(configurations)} configurations of "
          f"{len({r['structure'] for r in runs})} model structures")
    for row in shared_structures(runs):
        print(f"  one model structure ({row['tools']}, {row['mesh']}), other {' and '.join(row['differ'])}: "
              f"{row['compilations']} compilations, {row['seconds']} s ({', '.join(row['tests'])})")
    print(f"wrote {RUNS_OUT}")


def main() -> None:
    if os.path.isdir(RUN_RECORDS):
        summarise_runs(read_records(RUN_RECORDS))
    records = read_records(RECORDS)
    rows = by_structure(records)
    with open(OUT, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    total = sum(r["compile_s"] for r in rows)
    big = [r for r in rows if r["ops"] >= 1000]
    print(f"{len(records)} compilations, {total:.0f} s, {len({r[2] for r in records})} programs, "
          f"{len(rows)} structures")
    print(f"  programs of 1000 operations or more: {sum(r['compile_s'] for r in big):.0f} s in "
          f"{sum(r['compilations'] for r in big)} compilations of {len(big)} structures; one program per "
          f"structure would take {sum(r['one_program_s'] for r in big):.0f} s")
    repeated = collections.defaultdict(list)
    for rec in records:
        repeated[rec[2]].append(rec[5])
    again = sum(sum(s) - s[0] for s in repeated.values() if len(s) > 1)
    print(f"  the same program compiled again (another process): {again:.0f} s")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
