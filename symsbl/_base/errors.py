"""The errors symsbl raises, and the one wording they share.

Every error a user can trigger is a :class:`SymsblError` (a ``ValueError``) whose message reads
``"name: expected ..., received ...; fix"``: the argument, column or file at fault, what was
expected, what was received, and what to do. :func:`expected` writes that sentence, so the
wording lives in one place.
"""

from __future__ import annotations

__all__ = [
    "SymsblError",
    "DataError",
    "LibraryError",
    "ExpressionError",
    "SimulationError",
    "ParameterError",
    "MissingExtraError",
    "RefineWarning",
    "DivergenceError",
    "expected",
    "describe",
]


class SymsblError(ValueError):
    """Base class of symsbl's user-facing errors (a ``ValueError``)."""


class DataError(SymsblError):
    """Input data is malformed: bad columns, non-uniform time, NaN, too few samples, unreadable files."""


class LibraryError(SymsblError):
    """A candidate library or model structure is malformed or does not fit the data."""


class ExpressionError(LibraryError):
    """Text that should hold a term expression (a model file, ``--base``) is outside the grammar."""


class SimulationError(SymsblError):
    """A simulation could not be set up."""


class DivergenceError(SimulationError):
    """A simulation became non-finite (and could not be truncated); ``diverged_at`` is the time it did."""

    def __init__(self, message: str, diverged_at: float):
        super().__init__(message)
        self.diverged_at = diverged_at


class ParameterError(SymsblError):
    """An estimator or function argument has a value outside its documented range."""


class MissingExtraError(SymsblError, ImportError):
    """An optional dependency is not installed; the message names how to install it."""


class RefineWarning(RuntimeWarning):
    """The output-error refinement could not run on a record; the equation-error model is returned."""


def describe(value, limit: int = 60) -> str:
    """A short description of a received value for an error message."""
    if getattr(value, "ndim", None) == 0 and hasattr(value, "item"):  # a numpy scalar: show its value
        value = value.item()
    text = repr(value)
    if len(text) > limit:
        text = text[: limit - 3] + "..."
    return text


def expected(name: str, what: str, received, fix: str = "", *, raw: bool = False) -> str:
    """The message ``"name: expected what, received received; fix"``.

    Parameters
    ----------
    name : str
        The argument, option, column or file at fault.
    what : str
        What was expected, in words.
    received : object
        What was received; shown with :func:`describe` unless ``raw`` (then as given).
    fix : str
        What to do about it (optional).
    raw : bool
        Use ``received`` as text as it is.

    Examples
    --------
    >>> expected("degree", "an integer >= 1", 0, "use 3 for cubic terms")
    'degree: expected an integer >= 1, received 0; use 3 for cubic terms'
    """
    got = received if raw else describe(received)
    return f"{name}: expected {what}, received {got}" + (f"; {fix}" if fix else "")


# the classes are public names of symsbl: tracebacks and doctests name them so, whatever module defines them
for _cls in (
    SymsblError,
    DataError,
    LibraryError,
    ExpressionError,
    SimulationError,
    ParameterError,
    MissingExtraError,
    RefineWarning,
):
    _cls.__module__ = "symsbl"
del _cls
