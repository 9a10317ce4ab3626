"""The fast suite's time per test file, and the wall time of the two workers under two file orders.

Reads a JUnit XML report of the suite (``pytest -m "not slow" -n 2 --dist loadfile --no-loadscope-reorder
--junitxml=FILE``), writes ``experiments/results/suite_files.csv`` (per file: tests, summed time, its
rank in ``tests/conftest.py``'s ``LONGEST_FIRST``) and prints the makespan of a model of
pytest-xdist's ``loadfile`` schedule (two workers, each taking the next file when it is free) for:
- pytest-xdist's default order (``--loadscope-reorder``: the files with the most tests first), and
- ``make test``'s order (the files of ``LONGEST_FIRST`` first, then the rest as collected).

The model leaves out the workers' start-up and collection; it compares orders on the same measured
file times, which the suite's run-to-run spread on one machine (up to 20 %) would hide.

    python experiments/suite_files.py REPORT.xml
"""

from __future__ import annotations

import argparse
import ast
import collections
import csv
import os
import xml.etree.ElementTree as ET

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "results", "suite_files.csv")


def file_times(report: str) -> tuple[dict, dict]:
    """Summed test time (s) and test count per test file of a JUnit XML report."""
    seconds: dict = collections.Counter()
    count: dict = collections.Counter()
    for case in ET.parse(report).getroot().iter("testcase"):
        name = case.get("classname", "").split(".")[-1] + ".py"
        seconds[name] += float(case.get("time", 0.0))
        count[name] += 1
    return dict(seconds), dict(count)


def makespan(order: list, seconds: dict, workers: int = 2) -> float:
    """Wall time when each of ``workers`` takes the next file of ``order`` as soon as it is free."""
    busy = [0.0] * workers
    for name in order:
        k = busy.index(min(busy))
        busy[k] += seconds[name]
    return max(busy)


def longest_first() -> tuple:
    """``LONGEST_FIRST`` of ``tests/conftest.py``, read without running the file (which starts JAX)."""
    with open(os.path.join(HERE, os.pardir, "tests", "conftest.py")) as fh:
        tree = ast.parse(fh.read())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "LONGEST_FIRST" for t in node.targets):
            return tuple(ast.literal_eval(node.value))
    raise ValueError("tests/conftest.py defines no LONGEST_FIRST")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("report", help="JUnit XML report of the fast suite")
    args = parser.parse_args(argv)
    seconds, count = file_times(args.report)
    first = longest_first()
    names = sorted(seconds)
    default = sorted(names, key=lambda n: -count[n])       # stable: alphabetical among equal counts
    ours = sorted(names, key=lambda n: first.index(n) if n in first else len(first))
    os.makedirs(os.path.dirname(OUT), exist_ok=True)
    with open(OUT, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["file", "tests", "seconds", "longest_first_rank"])
        for name in sorted(names, key=lambda n: -seconds[n]):
            writer.writerow([name, count[name], f"{seconds[name]:.1f}", first.index(name) if name in first else ""])
    total = sum(seconds.values())
    print(f"{len(names)} files, {sum(count.values())} tests, {total:.0f} s of test time "
          f"(a perfect split over two workers: {total / 2:.0f} s)")
    print(f"two workers, xdist's default order (most tests first): {makespan(default, seconds):.0f} s")
    print(f"two workers, make test's order (LONGEST_FIRST first):  {makespan(ours, seconds):.0f} s")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
