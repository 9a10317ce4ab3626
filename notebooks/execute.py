"""Run a notebook's code cells top to bottom and store their outputs, with the standard library only:
``python notebooks/execute.py NOTEBOOK.ipynb [--small] [--no-write]``.

Each code cell runs in one shared namespace, with the notebook's folder as working directory and
matplotlib's Agg backend. Printed text becomes a ``stream`` output; every figure left open at the end
of a cell becomes a PNG ``display_data`` output (then it is closed). ``--small`` sets
``JAXFRIC_NOTEBOOK_SMALL=1``, which the notebooks read to pick a small mesh and a short stroke (the
test suite runs them so); without it they run at the size stated in their first cell. The notebook
file is rewritten with the outputs unless ``--no-write``. An exception stops the run, is stored as an
``error`` output, and the exit status is 1.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import io
import json
import os
import sys
import time
import traceback


def run_notebook(path: str, small: bool = False, write: bool = True) -> dict:
    """Execute ``path``; returns the notebook dict with outputs. Raises RuntimeError naming the cell
    that failed (after writing the notebook, when ``write``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with open(path) as f:
        nb = json.load(f)
    if small:
        os.environ["JAXFRIC_NOTEBOOK_SMALL"] = "1"
    else:
        os.environ.pop("JAXFRIC_NOTEBOOK_SMALL", None)
    namespace = {"__name__": "__main__"}
    cwd = os.getcwd()
    os.chdir(os.path.dirname(os.path.abspath(path)))
    failure = None
    try:
        count = 0
        for index, cell in enumerate(nb["cells"]):
            if cell["cell_type"] != "code":
                continue
            count += 1
            source = "".join(cell["source"])
            out = io.StringIO()
            outputs = []
            t0 = time.perf_counter()
            try:
                with contextlib.redirect_stdout(out):
                    exec(compile(source, f"<cell {index}>", "exec"), namespace)
            except Exception as err:  # noqa: BLE001 (any error of a cell is reported as the cell's output)
                failure = (index, err)
                outputs.append({"output_type": "error", "ename": type(err).__name__, "evalue": str(err),
                                "traceback": traceback.format_exc().splitlines()})
            text = out.getvalue()
            if text:
                outputs.insert(0, {"output_type": "stream", "name": "stdout", "text": text.splitlines(True)})
            for num in plt.get_fignums():
                buf = io.BytesIO()
                plt.figure(num).savefig(buf, format="png", dpi=90, bbox_inches="tight")
                outputs.append({"output_type": "display_data", "metadata": {},
                                "data": {"image/png": base64.b64encode(buf.getvalue()).decode("ascii"),
                                         "text/plain": ["<Figure>"]}})
            plt.close("all")
            cell["outputs"] = outputs
            cell["execution_count"] = count
            print(f"cell {index}: {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
            if failure:
                break
    finally:
        os.chdir(cwd)
    if write:
        with open(path, "w") as f:
            json.dump(nb, f, indent=1)
            f.write("\n")
    if failure:
        raise RuntimeError(f"{path}: cell {failure[0]} failed: {type(failure[1]).__name__}: {failure[1]}")
    return nb


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("notebook")
    p.add_argument("--small", action="store_true", help="small mesh and short stroke (as in the tests)")
    p.add_argument("--no-write", action="store_true", help="do not rewrite the notebook with its outputs")
    a = p.parse_args(argv)
    try:
        run_notebook(a.notebook, small=a.small, write=not a.no_write)
    except RuntimeError as err:
        print(err, file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
