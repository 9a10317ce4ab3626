"""The notebooks run top to bottom at their small size (``JAXFRIC_NOTEBOOK_SMALL=1``), executed by
``notebooks/execute.py`` (standard library JSON reader, one namespace per notebook). Their committed
outputs come from the full size: ``python notebooks/execute.py notebooks/NAME.ipynb``.

Running them is ``slow`` (``make test-all``): even small, the three take 3 to 5 minutes on two cores
(each compiles its own simulations), which the 10-minute fast suite cannot hold; the fast suite checks
that they are committed with outputs and without errors."""

import glob
import importlib.util
import json
import os
import shutil

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
NOTEBOOKS = sorted(glob.glob(os.path.join(HERE, "..", "notebooks", "*.ipynb")))


def _executor():
    spec = importlib.util.spec_from_file_location("nb_execute", os.path.join(HERE, "..", "notebooks", "execute.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_there_are_three_notebooks_committed_with_outputs():
    assert len(NOTEBOOKS) == 3
    for path in NOTEBOOKS:
        with open(path) as f:
            cells = [c for c in json.load(f)["cells"] if c["cell_type"] == "code"]
        assert cells and all(c["outputs"] for c in cells), f"{path} lacks outputs"
        assert not any(o["output_type"] == "error" for c in cells for o in c["outputs"]), path


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=os.path.basename)
def test_notebook_runs_top_to_bottom_at_small_size(path, tmp_path):
    copy = tmp_path / os.path.basename(path)
    shutil.copy(path, copy)
    nb = _executor().run_notebook(str(copy), small=True, write=False)
    outputs = [o for c in nb["cells"] if c["cell_type"] == "code" for o in c["outputs"]]
    assert any(o["output_type"] == "display_data" for o in outputs)
