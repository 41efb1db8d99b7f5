"""The examples in the docstrings run and print what they say, and every public entry point has one."""

import dataclasses
import doctest
import enum
import importlib
import inspect
import io
import pkgutil

import pytest

import symsbl

MODULES = sorted(
    m.name.removeprefix("symsbl.")
    for m in pkgutil.walk_packages(symsbl.__path__, "symsbl.")
    if not m.name.endswith("__main__")
)
#: Modules whose examples need an optional extra.
EXTRAS = {"plots": "matplotlib", "_scale.dask": "dask", "_discrepancy.figures": "matplotlib", "_figures": "matplotlib"}
#: Result containers and errors: users receive them, they do not call them.
RESULTS = {
    "ChunkedRecord",
    "DemoResult",
    "DiscrepancyReport",
    "Variant",
    "DiscrepancyStep",
    "Disagreement",
    "EffectScore",
    "Equation",
    "RegressionStats",
    "TermEstimate",
    "TruthComparison",
    "Validation",
}


#: Modules whose examples take tens of seconds (the discrepancy workflow end to end): in the full suite only.
SLOW = {"_discrepancy.workflow"}


@pytest.mark.parametrize("name", [pytest.param(m, marks=pytest.mark.slow) if m in SLOW else m for m in MODULES])
def test_docstring_examples_run(name):
    if name in EXTRAS:
        pytest.importorskip(EXTRAS[name], reason=f"symsbl.{name}'s examples need the {EXTRAS[name]} extra")
    if name == "plots":
        import matplotlib

        matplotlib.use("Agg")
    module = importlib.import_module(f"symsbl.{name}")
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    report = io.StringIO()
    for test in doctest.DocTestFinder(exclude_empty=True).find(module, f"symsbl.{name}"):
        runner.run(test, out=report.write)
    assert runner.failures == 0, report.getvalue()


def _needs_example(obj) -> bool:
    if inspect.ismodule(obj) or not callable(obj):
        return False
    if inspect.isclass(obj) and (issubclass(obj, (Exception, enum.Enum)) or obj.__name__ in RESULTS):
        return False
    return True


def test_every_public_entry_point_has_an_example():
    missing = [
        n
        for n in symsbl.__all__
        if _needs_example(getattr(symsbl, n)) and ">>> " not in (inspect.getdoc(getattr(symsbl, n)) or "")
    ]
    assert missing == [], f"public functions and classes without an Examples section: {missing}"


def test_the_examples_are_numpydoc_sections():
    for name in symsbl.__all__:
        doc = inspect.getdoc(getattr(symsbl, name)) or ""
        if ">>> " in doc:
            assert "\nExamples\n--------\n" in doc, f"{name}: examples outside an 'Examples' section"


def test_result_containers_are_frozen_dataclasses():
    for name in RESULTS:
        cls = getattr(symsbl, name)
        assert dataclasses.is_dataclass(cls) and cls.__dataclass_params__.frozen, name
