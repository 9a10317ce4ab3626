"""The package's structure as docs/architecture.md states it: each module imports only from its own layer
and the layers before it; the load loop never asks a contact formulation for its type; each vocabulary
(algorithms, the contact-status thresholds) is defined once."""

import ast
import pathlib
import re

PACKAGE = pathlib.Path(__file__).resolve().parent.parent / "jaxfric"

# The layers of docs/architecture.md, lowest first: the package's subpackages (and its top-level modules).
LAYERS = (
    ("numerics",),
    ("fem",),
    ("contact",),
    ("loadpath",),
    ("scenes", "identification", "io", "cards"),
    ("cli", "__main__", "__init__"),
)
LAYER = {name: k for k, names in enumerate(LAYERS) for name in names}


def _modules():
    """(the module's top-level part: its subpackage, or the module itself at the top; its path)."""
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE)
        yield (rel.parts[0] if len(rel.parts) > 1 else rel.stem), path


def _imported(path: pathlib.Path) -> set:
    """The top-level parts of the package that ``path`` imports (relative imports resolved)."""
    package = path.relative_to(PACKAGE).parts[:-1]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            target = list(package[: len(package) - (node.level - 1)]) + (node.module.split(".") if node.module
                                                                         else [])
            if target:
                out.add(target[0])
            else:
                out.update(alias.name for alias in node.names)
    return out


def test_every_module_lies_in_a_layer():
    assert {name for name, _ in _modules()} <= set(LAYER)
    assert not [path.name for path in PACKAGE.glob("*.py") if path.stem not in LAYER]


def test_modules_import_only_from_their_layer_and_the_layers_before():
    wrong = [f"{path.relative_to(PACKAGE)} (layer {LAYER[name]}) imports {other} (layer {LAYER[other]})"
             for name, path in _modules() for other in _imported(path)
             if other in LAYER and LAYER[other] > LAYER[name]]
    assert not wrong, wrong


def test_only_the_contact_layer_knows_the_formulations_by_name():
    """Outside ``contact/`` nothing imports a concrete formulation class, so the load path cannot ask
    for one (it asks the abstract interface what it declares)."""
    concrete = {"Penalty", "AugmentedLagrangian", "Complementarity"}
    hits = [str(path.relative_to(PACKAGE)) for name, path in _modules()
            if name not in ("contact", "__init__") for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, ast.ImportFrom) and concrete & {alias.name for alias in node.names}]
    assert not hits, hits


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
    # The contract_* modules check run directories against the outputs spec independently of the code,
    # so they state the spec's thresholds themselves.
    status_rules = [path.name for _, path in _modules()
                    if path.name != "status.py" and not path.name.startswith("contract")
                    and thresholds.search(path.read_text())]
    assert status_rules == [], status_rules
