"""One error voice: every error a user can trigger is a SymsblError worded "name: expected ..., received ...".

The test walks every ``raise`` statement of the package: the exception raised must be one of the
:mod:`symsbl._base.errors` classes (or a re-raise), and its message must come from
:func:`symsbl._base.errors.expected` or read "...: expected ..., received ...".
"""

import ast
import inspect
from pathlib import Path

import pytest

import symsbl
from symsbl._base import errors as _errors

PACKAGE = Path(symsbl.__file__).parent
ERROR_CLASSES = {
    name
    for name, obj in vars(_errors).items()
    if inspect.isclass(obj) and issubclass(obj, Exception) and not issubclass(obj, Warning)
}
WARNING_CLASSES = {name for name, obj in vars(_errors).items() if inspect.isclass(obj) and issubclass(obj, Warning)}
#: Names that hold one of those classes at run time (a parameter ``error`` of the shared checks, ``type(err)``).
ERROR_VARIABLES = {"error", "type"}


def _raises():
    for path in sorted(PACKAGE.rglob("*.py")):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Raise) and node.exc is not None:
                yield path.relative_to(PACKAGE), node


def _message_ok(call: ast.Call) -> bool:
    if not call.args:
        return False
    arg = call.args[0]
    if isinstance(arg, ast.Call) and getattr(arg.func, "id", None) == "expected":
        return True
    if isinstance(arg, ast.Name):  # a message built once (MATPLOTLIB_MISSING) or passed through (str(err))
        return True
    if "str(err)" in ast.unparse(arg) or "str(exc)" in ast.unparse(arg):  # a symsbl error re-worded
        return True
    text = ast.unparse(arg)
    return "expected" in text and "received" in text


def test_every_raise_is_a_symsbl_error_in_one_wording():
    bad = []
    for path, node in _raises():
        exc = node.exc
        call = exc if isinstance(exc, ast.Call) else None
        func = call.func if call is not None else exc
        name = func.id if isinstance(func, ast.Name) else getattr(func, "attr", None)
        if isinstance(func, ast.Call) and getattr(func.func, "id", None) == "type":
            name = "type"
        if isinstance(func, ast.Attribute) and func.attr == "error" and ast.unparse(func.value) == "self":
            continue  # the parser's error builder writes the voice itself (symsbl._symbolic.parse)
        if name == "KeyboardInterrupt":
            continue  # a Ctrl-C passed on (symsbl._base.casadi.interrupts_kept), not an error
        if name not in ERROR_CLASSES and name not in ERROR_VARIABLES:
            bad.append(f"{path}:{node.lineno}: raises {ast.unparse(exc)[:60]}")
        elif call is not None and not _message_ok(call):
            bad.append(f"{path}:{node.lineno}: message not in the 'name: expected ..., received ...' voice")
    assert not bad, "\n".join(bad)


def test_the_error_classes_are_exported_and_are_value_errors():
    for name in ERROR_CLASSES:
        assert getattr(symsbl, name) is getattr(_errors, name)
        assert issubclass(getattr(symsbl, name), ValueError)
    assert WARNING_CLASSES == {"RefineWarning"}  # a warning a user filters on must be importable from symsbl
    for name in WARNING_CLASSES:
        assert getattr(symsbl, name) is getattr(_errors, name)


@pytest.mark.parametrize("value, text", [(0, "0"), (2.5, "2.5"), ("x" * 100, "'" + "x" * 56 + "...")])
def test_received_values_are_shown_short(value, text):
    assert _errors.expected("degree", "an integer >= 1", value) == f"degree: expected an integer >= 1, received {text}"
