"""The package's layers: imports go down the data flow, never up, and no module imports itself back.

Every ``import`` counts, function-local ones included (a local import that breaks a cycle hides a design
problem); only imports under ``if TYPE_CHECKING:`` (annotations, never run) and the command line's lazy
imports (which keep ``symsbl --help`` fast) are exempt from the cycle check, and nothing is exempt from the
layer order.
"""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "symsbl"

#: Bottom to top. A module may import from its own layer's package and from layers below it.
LAYERS = [
    ["_base"],
    ["_symbolic"],
    ["_data"],
    ["_simulation", "systems", "_figures"],
    ["_derivatives"],
    ["_model"],
    ["_regression"],
    ["_refine"],
    ["_validate"],
    ["_latent"],
    ["_identify"],
    ["_discrepancy"],
    ["_scale"],
    ["plots", "_demo", "_outcome", "_cli", "__main__", "__init__"],
]
LAYER_OF = {name: k for k, names in enumerate(LAYERS) for name in names}
#: Modules whose function-local imports are lazy by design (start-up time), not cycle breakers.
LAZY = {"symsbl._cli", "symsbl._demo", "symsbl.plots", "symsbl._figures"}


def _module(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path):
    """``(target module, local, type_checking)`` of every import of a symsbl module in ``path``."""
    tree = ast.parse(path.read_text())
    package = _module(path) if path.name == "__init__.py" else _module(path).rsplit(".", 1)[0]
    guarded = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            guarded |= {id(n) for n in ast.walk(node)}
    local = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            local |= {id(n) for n in ast.walk(node)}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                stem = ".".join(base + ([node.module] if node.module else []))
            else:
                stem = node.module or ""
            if not stem.startswith("symsbl"):
                continue
            targets = [stem] if node.module else [f"{stem}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            targets = [a.name for a in node.names if a.name.startswith("symsbl")]
        else:
            continue
        for target in targets:
            yield target, id(node) in local, id(node) in guarded


def _layer(module: str) -> int | None:
    parts = module.split(".")
    return LAYER_OF.get(parts[1]) if len(parts) > 1 else LAYER_OF["__init__"]


MODULES = sorted(PACKAGE.rglob("*.py"))


def test_every_package_has_a_layer():
    top = {p.relative_to(PACKAGE).parts[0].removesuffix(".py") for p in MODULES}
    assert top <= set(LAYER_OF), f"modules without a layer in LAYERS: {sorted(top - set(LAYER_OF))}"


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_go_down_the_layers(path):
    own = _layer(_module(path))
    up = [target for target, _, _ in _imports(path) if (_layer(target) or 0) > own]
    assert not up, f"{_module(path)} (layer {own}) imports from higher layers: {up}"


def _graph():
    modules = {_module(p): p for p in MODULES}
    graph = {}
    for name, path in modules.items():
        edges = set()
        for target, local, guarded in _imports(path):
            if guarded or (local and name in LAZY):
                continue
            # "from .x import y" may name a submodule y or a name in x: resolve to a module that exists
            while target not in modules and "." in target:
                target = target.rsplit(".", 1)[0]
            if target != name and target in modules:
                edges.add(target)
        graph[name] = edges
    return graph


def test_no_import_cycles():
    graph = _graph()
    # a package's __init__ importing its own submodules is how it re-exports; a submodule importing its
    # package's __init__ would close a cycle through it, so both directions are kept in the graph
    index, low, stack, on, cycles, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            scc = []
            while True:
                w = stack.pop()
                on.discard(w)
                scc.append(w)
                if w == v:
                    break
            if len(scc) > 1:
                cycles.append(sorted(scc))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert not cycles, f"import cycles: {cycles}"
