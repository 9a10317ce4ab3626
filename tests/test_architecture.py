"""The package's structure as docs/architecture.md states it: each module imports only from its own layer
and the layers before it; the load loop never asks a contact formulation for its type; each vocabulary
(algorithms, the contact-status thresholds) is defined once."""

import ast
import pathlib
import re

PACKAGE = pathlib.Path(__file__).resolve().parent.parent / "jaxfric"

# The layers of docs/architecture.md, lowest first.
LAYERS = (
    ("linalg", "newton", "results", "tensor", "lru", "_checks"),
    ("mesh", "element", "material", "assembly", "loading"),
    ("tools", "status", "contact_laws", "contact", "system", "contact_lcp", "lemke", "complementary_basis",
     "alart_curnier", "exact_iterate", "exact_condensed", "exact_active_set", "exact", "formulations"),
    ("model", "step", "controller", "simulate", "run", "sweep", "progress"),
    ("scenes", "params", "fit", "fit_data", "fit_curve", "fit_global", "fit_result", "accuracy", "batch", "instants",
     "output", "contract", "figures", "plotting"),
    ("cli", "__main__", "__init__"),
)
LAYER = {name: k for k, names in enumerate(LAYERS) for name in names}


def _modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE)
        yield ("scenes" if rel.parts[0] == "scenes" else rel.stem), path


def _imported(path: pathlib.Path) -> set:
    """The package modules ``path`` imports (relative imports resolved to the top-level module)."""
    in_scenes = path.parent.name == "scenes"
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            up = node.level - (1 if in_scenes else 0)
            if in_scenes and up == 0:
                out.add("scenes")
            elif node.module:
                out.add(node.module.split(".")[0])
            else:
                out.update(alias.name for alias in node.names)
    return out


def test_every_module_has_a_layer():
    assert {name for name, _ in _modules()} <= set(LAYER)


def test_modules_import_only_from_their_layer_and_the_layers_before():
    wrong = [f"{name} (layer {LAYER[name]}) imports {other} (layer {LAYER[other]})"
             for name, path in _modules() for other in _imported(path)
             if other in LAYER and LAYER[other] > LAYER[name]]
    assert not wrong, wrong


def test_no_module_asks_a_contact_formulation_for_its_type():
    pattern = re.compile(r"isinstance\([^)]*(Penalty|AugmentedLagrangian|Complementarity)|is_plain_penalty")
    hits = [f"{path.name}:{k + 1}" for _, path in _modules() if path.name != "formulations.py"
            for k, line in enumerate(path.read_text().splitlines()) if pattern.search(line)]
    assert not hits, hits


def test_the_algorithm_list_and_the_status_thresholds_are_defined_once():
    algorithms = re.compile(r"""^\s*\w*ALGORITHMS\s*=\s*\(\s*["']penalty""", re.M)
    thresholds = re.compile(r"(rn|R_N)\s*(>|<=)\s*1e-9|1\.0 - 1e-6")
    defined = [path.name for _, path in _modules() if algorithms.search(path.read_text())]
    assert defined == [], defined   # formulations.ALGORITHMS is derived from its classes
    # contract.py checks run directories against the outputs spec independently of the code, so it
    # states the spec's thresholds itself.
    status_rules = [path.name for _, path in _modules()
                    if path.name not in ("status.py", "contract.py") and thresholds.search(path.read_text())]
    assert status_rules == [], status_rules
