"""Error against run time (issue 5): ``python experiments/accuracy_cost.py [--quick] [--test NAME ...]``.

Runs :func:`jaxfric.identification.accuracy_report.accuracy_cost` (the same as ``jaxfric report accuracy-cost``) into
``experiments/results/accuracy_cost/`` (run directories under ``runs/``, not committed; a run already on
disk is read back, so an interrupted sweep resumes) and writes its section of ``docs/results.md``
(between ``<!-- BEGIN study:accuracy_cost -->`` and ``<!-- END study:accuracy_cost -->``).
"""

from __future__ import annotations

import argparse
import os
import sys

from jaxfric.identification import accuracy, accuracy_report
from studies import write_section

OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "accuracy_cost")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--test", action="append", default=None, help="test name (repeatable); default all")
    p.add_argument("--rerun", action="store_true")
    p.add_argument("--collect", action="store_true",
                   help="run nothing: rewrite the CSV, plots and section from the runs on disk")
    a = p.parse_args(argv)
    out = OUT + ("_quick" if a.quick else "")
    if a.collect:
        accuracy_report.write_report(out, a.quick)
    else:
        accuracy_report.accuracy_cost(out, quick=a.quick, tests=a.test, rerun=a.rerun,
                                      log=lambda m: print(m, flush=True))
    # The section covers every test on disk, not only this invocation's.
    rows = accuracy.collect(out, quick=a.quick)
    # Links relative to docs/results.md, where the section is written.
    rel = os.path.relpath(out, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "docs"))
    figures = "\n".join(f"![{name}]({rel}/pareto_{name}.png)" for name in dict.fromkeys(r["test"] for r in rows))
    write_section("accuracy_cost" + ("_quick" if a.quick else ""),
                  f"### Error against run time{' (quick)' if a.quick else ''}\n\nRegenerate: `python "
                  f"experiments/accuracy_cost.py{' --quick' if a.quick else ''}` (or `jaxfric report "
                  f"accuracy-cost{' --quick' if a.quick else ''}`). Table: `{rel}/accuracy_cost.csv`.\n\n"
                  + accuracy_report.report_markdown(rows, accuracy_report.reference_checks(rows), a.quick)
                  + "\n" + figures,
                  command=f"python experiments/accuracy_cost.py{' --quick' if a.quick else ''}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
