"""Where the fast suite's compilation goes: a pytest plugin that records, per test, JAX's tracing, lowering
and XLA compilation of every program, and a summary of the records by kind of program.

Record (the suite as ``make test`` runs it, with this plugin; each process writes its own file):

    JAXFRIC_TEST_CACHE=fresh PYTHONPATH=experiments .venv/bin/python -m pytest -p suite_compile -m "not slow" -n 2 \\
        --dist loadfile --no-loadscope-reorder tests

Summarise (writes ``experiments/results/suite_compile.csv``, one row per test, and
``experiments/results/suite_compile_callers.csv``, the one-primitive programs per function that ran them,
and prints the totals):

    python experiments/suite_compile.py

The records come from JAX's own compile log (``jax_log_compiles``: "Finished tracing ...", "Finished
jaxpr to MLIR module conversion ...", "Finished XLA compilation of ..."). Kinds of program:
- ``op by op``: one primitive each (``jit(add)``, ``jit(broadcast_in_dim)``, ...), what JAX compiles
  when array code runs outside a compiled function (building scenes, tests' own array code);
- ``curve``: the identification's forward-mode replays (:mod:`jaxfric.identification.fit_curve`);
- ``other``: every other program (the runs' start and chunk programs, the tests' compiled functions).
Command lines that tests start in a new process are not recorded. A one-primitive program's caller is the
innermost function of the package on the call stack when XLA compiled it, else that of the tests or the
experiments (``tests/test_mesh.py:test_...``): where array code ran outside a compiled function.
"""

from __future__ import annotations

import collections
import csv
import glob
import json
import logging
import os
import re
import shutil
import traceback

HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.join(HERE, "results")
RECORDS = os.path.join(RESULTS, "suite_compile_records")
OUT = os.path.join(RESULTS, "suite_compile.csv")
CALLERS_OUT = os.path.join(RESULTS, "suite_compile_callers.csv")
ROOT = os.path.dirname(HERE) + os.sep
_THIS_FILE = os.path.abspath(__file__)

_MESSAGE = re.compile(r"Finished (tracing|jaxpr to MLIR module conversion|XLA compilation of) (.*?) "
                      r"(?:for jit )?in ([0-9.e+-]+) sec")
STAGES = {"tracing": "trace", "jaxpr to MLIR module conversion": "lower", "XLA compilation of": "xla"}
# Named programs of the package that are not single primitives, although their names look like one.
_PROGRAMS = {"curve", "one", "while", "scan", "force", "assemble", "stage", "compute", "final_reaction",
             "element_force_and_tangent", "_project_all", "_fn"}


def kind(name: str) -> str:
    """``op by op``, ``curve`` or ``other`` (see the module's docstring) for a program's logged name."""
    inner = name[4:-1] if name.startswith("jit(") and name.endswith(")") else name
    if inner == "curve":
        return "curve"
    if re.fullmatch(r"_?[a-z_]+", inner) and inner not in _PROGRAMS:
        return "op by op"
    return "other"


def parse(message: str):
    """(stage, program name, seconds) of a compile-log message, or None for any other message."""
    found = _MESSAGE.match(message)
    if found is None:
        return None
    return STAGES[found.group(1)], found.group(2), float(found.group(3))


# ---- the plugin --------------------------------------------------------------------------------------

_records: list = []
_current = {"test": None}


def caller(frames) -> str:
    """``path:function`` of the innermost frame of ``frames`` (``traceback.extract_stack()``, outermost
    first) in the package, else in the tests or the experiments; ``-`` where there is none."""
    inside = [None, None]
    for frame in reversed(frames):
        if os.path.abspath(frame.filename) == _THIS_FILE:
            continue   # the recorder's own frames
        path = frame.filename[len(ROOT):] if frame.filename.startswith(ROOT) else ""
        where = 0 if path.startswith("jaxfric" + os.sep) else 1 if path.startswith(("tests", "experiments")) else None
        if where is not None and inside[where] is None:
            inside[where] = f"{path}:{frame.name}"
    return inside[0] or inside[1] or "-"


class _Recorder(logging.Handler):
    def emit(self, record):
        found = parse(record.getMessage())
        if found is not None:
            stage, name, _ = found
            where = caller(traceback.extract_stack()) if stage == "xla" and kind(name) == "op by op" else None
            _records.append((_current["test"], *found, where))


def pytest_configure(config):
    import jax

    if not hasattr(config, "workerinput"):     # the run's first process: earlier records go
        shutil.rmtree(RECORDS, ignore_errors=True)
    jax.config.update("jax_log_compiles", True)
    handler = _Recorder(level=logging.DEBUG)
    for name in ("jax._src.interpreters.pxla", "jax._src.dispatch", "jax._src.compiler", "jax._src.pjit"):
        logger = logging.getLogger(name)
        logger.addHandler(handler)
        logger.setLevel(logging.DEBUG)
        logger.propagate = False   # the log's warnings are records here, not output


def pytest_runtest_setup(item):
    _current["test"] = item.nodeid


def pytest_unconfigure(config):
    write_records(config, _records, RECORDS)


def write_records(config, records: list, folder: str) -> None:
    """A process's ``records`` as ``<worker>.json`` in ``folder`` (pytest-xdist's worker id, or main), if any."""
    worker = getattr(config, "workerinput", {}).get("workerid", "main")
    if not records:
        return
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, f"{worker}.json"), "w") as fh:
        json.dump(records, fh)


def read_records(folder: str) -> list:
    """Every process's records in ``folder``; exits with a message where there are none."""
    records = []
    for path in sorted(glob.glob(os.path.join(folder, "*.json"))):
        with open(path) as fh:
            records += json.load(fh)
    if not records:
        raise SystemExit(f"no records in {folder}: run the suite with the plugin first (see the docstring)")
    return records


# ---- the summary -------------------------------------------------------------------------------------

def summarise(records: list) -> tuple[dict, dict]:
    """Per test: seconds per (kind, stage) and programs per kind; and the totals per (kind, stage)."""
    per_test: dict = collections.defaultdict(collections.Counter)
    totals: dict = collections.Counter()
    for test, stage, name, seconds, *_ in records:
        k = kind(name)
        per_test[test or "(collection)"][(k, stage)] += seconds
        if stage == "xla":
            per_test[test or "(collection)"][(k, "programs")] += 1
        totals[(k, stage)] += seconds
    return per_test, totals


def callers(records: list) -> dict:
    """One-primitive programs per caller (records of the plugin above): (programs, seconds of XLA's
    compilation)."""
    out: dict = collections.defaultdict(lambda: [0, 0.0])
    for _, stage, name, seconds, *rest in records:
        if stage == "xla" and kind(name) == "op by op":
            row = out[(rest[0] if rest else None) or "-"]
            row[0] += 1
            row[1] += seconds
    return dict(out)


def main() -> None:
    records = read_records(RECORDS)
    per_test, totals = summarise(records)
    kinds, stages = ("op by op", "curve", "other"), ("trace", "lower", "xla")
    columns = [f"{k.replace(' ', '_')}_{s}_s" for k in kinds for s in stages] + \
              [f"{k.replace(' ', '_')}_programs" for k in kinds]
    with open(OUT, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["test", "total_s", *columns])
        seconds = {test: sum(v for (_, s), v in c.items() if s != "programs") for test, c in per_test.items()}
        for test in sorted(seconds, key=lambda t: -seconds[t]):
            c = per_test[test]
            writer.writerow([test, f"{seconds[test]:.2f}", *(f"{c[(k, s)]:.2f}" for k in kinds for s in stages),
                             *(int(c[(k, "programs")]) for k in kinds)])
    grand = sum(totals.values())
    print(f"{len(records)} records, {grand:.0f} s of tracing, lowering and XLA compilation")
    for k in kinds:
        part = [totals[(k, s)] for s in stages]
        print(f"  {k:9s}: {sum(part):6.0f} s (trace {part[0]:.0f}, lower {part[1]:.0f}, XLA {part[2]:.0f})")
    ranked = sorted(callers(records).items(), key=lambda item: -item[1][0])
    with open(CALLERS_OUT, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["caller", "programs", "xla_s"])
        for where, (n, seconds) in ranked:
            writer.writerow([where, n, f"{seconds:.2f}"])
    print("one-primitive programs by caller: " + ", ".join(f"{w} {n}" for w, (n, _) in ranked[:8]))
    print(f"wrote {OUT} and {CALLERS_OUT}")


if __name__ == "__main__":
    main()
