"""The package's one public surface: ``symsbl.__init__`` is the map, everything else is private.

Guards what a newcomer relies on: every public name resolves through one path, no public attribute
is a module by accident, every type in a public signature is exported, every ``symsbl.X`` a
docstring, the README or a documentation page names exists, the architecture page lists every
module, and functions stay short enough to read at once (bodies under 60 lines). Modules are split
by concept, not by length; their layers are guarded by ``tests/test_layers.py``.
"""

import ast
import importlib
import inspect
import pkgutil
import re
from pathlib import Path

import pytest

import symsbl

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "symsbl"
DOCS = ROOT / "docs"
PUBLIC_MODULES = {"systems", "plots"}
SUBMODULES = sorted(
    m.name for m in pkgutil.walk_packages(symsbl.__path__, "symsbl.") if not m.name.endswith("__main__")
)


def _import_everything():
    pytest.importorskip("matplotlib")
    for name in SUBMODULES:
        importlib.import_module(name)


def test_all_names_resolve_once_and_are_sorted_by_stage():
    assert len(symsbl.__all__) == len(set(symsbl.__all__))
    for name in symsbl.__all__:
        assert hasattr(symsbl, name), name


def test_no_public_attribute_is_an_accidental_module():
    _import_everything()
    modules = {n for n, v in vars(symsbl).items() if not n.startswith("_") and inspect.ismodule(v)}
    assert modules <= PUBLIC_MODULES, modules - PUBLIC_MODULES
    assert all(
        n.startswith("_") or n in PUBLIC_MODULES or n == "__main__"
        for n in (m.name.split(".")[1] for m in pkgutil.iter_modules(symsbl.__path__, "symsbl."))
    )
    # the functions named like the private subpackages stay functions after those are imported
    assert callable(symsbl.discrepancy) and not inspect.ismodule(symsbl.discrepancy)


_TYPE_NAME = re.compile(r"\b([A-Z][A-Za-z0-9]+)\b")
#: Types from outside symsbl that public signatures may name.
_FOREIGN = {
    "Sequence",
    "Mapping",
    "Iterable",
    "Iterator",
    "Callable",
    "Any",
    "Path",
    "ndarray",
    "SX",
    "Function",
    "Expr",
    "Eq",
    "Figure",
    "Symbol",
    "Array",
    "Trajectory_",
    "None",
    "True",
    "False",
    "Delayed",
}


def _annotations(obj):
    try:
        sig = inspect.signature(obj)
    except (TypeError, ValueError):
        return []
    texts = [str(p.annotation) for p in sig.parameters.values() if p.annotation is not inspect.Parameter.empty]
    if sig.return_annotation is not inspect.Signature.empty:
        texts.append(str(sig.return_annotation))
    return texts


def test_every_type_in_a_public_signature_is_exported():
    missing = set()
    for name in symsbl.__all__:
        obj = getattr(symsbl, name)
        targets = [obj]
        if inspect.isclass(obj):
            targets += [m for n, m in vars(obj).items() if not n.startswith("_") and callable(m)]
        for target in targets:
            for text in _annotations(target):
                for found in _TYPE_NAME.findall(text):
                    if found not in symsbl.__all__ and found not in _FOREIGN:
                        missing.add((name, found))
    assert not missing, sorted(missing)


def _resolve(dotted: str) -> bool:
    obj = symsbl
    parts = dotted.split(".")
    for i, part in enumerate(parts):
        if not hasattr(obj, part):
            try:
                obj = importlib.import_module("symsbl." + ".".join(parts[: i + 1]))
                continue
            except ImportError:
                return False
        obj = getattr(obj, part)
    return True


def test_every_symsbl_name_in_docstrings_the_readme_and_the_docs_resolves():
    _import_everything()
    texts = [(str(p.relative_to(ROOT)), p.read_text()) for p in PACKAGE.rglob("*.py")]
    texts += [(str(p.relative_to(ROOT)), p.read_text()) for p in [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]]
    bad = set()
    for where, text in texts:
        for dotted in re.findall(r"(?<![\w/])symsbl\.([A-Za-z_][\w]*(?:\.[A-Za-z_]\w*)*)", text):
            dotted = dotted.rstrip(".")
            if dotted.split(".")[0].startswith("_") or dotted in {"py", "md"}:
                continue
            if not _resolve(dotted):
                bad.add((where, dotted))
    assert not bad, sorted(bad)


def test_the_architecture_page_names_every_module():
    page = (DOCS / "architecture.md").read_text()
    layers = page[page.index("## The layers") : page.index("## Known debts")]
    for path in PACKAGE.rglob("*.py"):
        if path.name in ("__init__.py", "__main__.py"):
            continue
        assert f"`{path.stem}`" in layers or f"`{path.stem.lstrip('_')}`" in layers, (
            f"{path.relative_to(PACKAGE)} missing from the layers of docs/architecture.md"
        )


def _function_bodies(tree):
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            first = node.body[0]
            doc = (
                isinstance(first, ast.Expr)
                and isinstance(first.value, ast.Constant)
                and isinstance(first.value.value, str)
            )
            start = first.end_lineno + 1 if doc and len(node.body) > 1 else first.lineno
            yield node.name, node.end_lineno - start + 1


@pytest.mark.parametrize("path", sorted(PACKAGE.rglob("*.py")), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_functions_stay_readable(path):
    text = path.read_text()
    long = [(name, n) for name, n in _function_bodies(ast.parse(text)) if n > 60]
    assert not long, f"{path.name}: function bodies over 60 lines: {long}"
