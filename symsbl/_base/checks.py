"""Argument checks shared by every entry point, each raising one wording (:func:`symsbl._base.errors.expected`)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from .errors import DataError, ParameterError, SymsblError, expected

__all__ = ["integer", "number", "flag", "choice", "enough_rows", "Constraint", "check_params"]


def integer(
    name: str, value, *, low: float | None = None, high: float | None = None, error: type[SymsblError] = ParameterError
) -> int:
    """``value`` as an int in ``[low, high]``; bools and floats are refused.

    Examples
    --------
    >>> integer("max_iter", 10, low=1)
    10
    >>> integer("max_iter", 0, low=1)
    Traceback (most recent call last):
    ...
    symsbl.ParameterError: max_iter: expected an integer >= 1, received 0
    """
    ok = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
    ok = ok and (low is None or value >= low) and (high is None or value <= high)
    if not ok:
        raise error(expected(name, "an integer" + _range(low, high), value))
    return int(value)


def number(
    name: str,
    value,
    *,
    low: float | None = None,
    high: float | None = None,
    strict: bool = False,
    error: type[SymsblError] = ParameterError,
) -> float:
    """``value`` as a finite float in the range (``strict``: bounds excluded)."""
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
    ok = ok and math.isfinite(value)
    if ok and low is not None:
        ok = value > low if strict else value >= low
    if ok and high is not None:
        ok = value < high if strict else value <= high
    if not ok:
        raise error(expected(name, "a finite number" + _range(low, high, strict), value))
    return float(value)


def flag(name: str, value, *, error: type[SymsblError] = ParameterError) -> bool:
    """``value`` as a bool (True or False only)."""
    if not isinstance(value, (bool, np.bool_)):
        raise error(expected(name, "True or False", value))
    return bool(value)


def choice(name: str, value, options: Mapping | Sequence, *, error: type[SymsblError] = ParameterError):
    """``value`` if it is one of ``options`` (a registry's keys or a sequence); the message lists them."""
    valid = list(options)
    if isinstance(value, str) and value in valid:
        return value
    if not isinstance(value, str) and any(value is v for v in valid):
        return value
    raise error(expected(name, "one of " + ", ".join(repr(v) for v in valid), value))


def enough_rows(n_rows: int, n_terms: int, what: str = "the data") -> None:
    """Refuse a regression with no more rows than candidate terms."""
    if n_rows <= n_terms:
        raise DataError(
            expected(
                "rows",
                f"more regression rows than candidate terms ({n_terms})",
                f"{n_rows} rows from {what}",
                "use longer records, fewer candidate terms (a lower degree) or a derivative strategy with more rows",
                raw=True,
            )
        )


def _range(low, high, strict: bool = False) -> str:
    lo, hi = (">", "<") if strict else (">=", "<=")
    if low is not None and high is not None:
        return f" in [{low}, {high}]" if not strict else f" in ({low}, {high})"
    if low is not None:
        return f" {lo} {low}"
    if high is not None:
        return f" {hi} {high}"
    return ""


@dataclass(frozen=True)
class Constraint:
    """The accepted values of one estimator parameter, declared as data (scikit-learn's
    ``_parameter_constraints``); :func:`check_params` applies them in ``fit``."""

    kind: str  # "number", "integer", "boolean", "indices" or "choice"
    low: float | None = None
    high: float | None = None
    strict: bool = False
    none: bool = False
    options: tuple = ()

    @classmethod
    def number(cls, *, low=None, high=None, strict=False, none=False, options=()) -> Constraint:
        return cls("number", low, high, strict, none, tuple(options))

    @classmethod
    def integer(cls, *, low=None, high=None, options=()) -> Constraint:
        return cls("integer", low, high, options=tuple(options))

    @classmethod
    def choice(cls, options) -> Constraint:
        """One of ``options`` (strings, or other values compared by identity, such as True and False)."""
        return cls("choice", options=tuple(options))

    @classmethod
    def boolean(cls) -> Constraint:
        return cls("boolean")

    @classmethod
    def indices(cls) -> Constraint:
        return cls("indices")

    def check(self, name: str, value, n_columns: int = 0, error: type[SymsblError] = ParameterError):
        """The validated value, or ``error`` (:class:`ParameterError` by default) naming ``name``."""
        try:
            return self._check(name, value, n_columns)
        except ParameterError as exc:
            if error is ParameterError:
                raise
            raise error(str(exc)) from None

    def _check(self, name: str, value, n_columns: int):
        if value is None and self.none:
            return None
        if self.kind == "choice":
            return choice(name, value, self.options)
        if isinstance(value, str) and self.options:
            return choice(name, value, self.options)
        if self.kind == "boolean":
            return flag(name, value)
        if self.kind == "integer":
            try:
                return integer(name, value, low=self.low, high=self.high)
            except ParameterError:
                if not self.options:
                    raise
                extra = "".join(f" or {o!r}" for o in self.options)
                raise ParameterError(
                    expected(name, "an integer" + _range(self.low, self.high) + extra, value)
                ) from None
        if self.kind == "indices":
            return _indices(name, value, n_columns)
        try:
            return number(name, value, low=self.low, high=self.high, strict=self.strict)
        except ParameterError:
            extra = (", None" if self.none else "") + "".join(f", {o!r}" for o in self.options)
            raise ParameterError(
                expected(name, "a finite number" + _range(self.low, self.high, self.strict) + extra, value)
            ) from None


def check_params(
    params: Mapping,
    constraints: Mapping[str, Constraint],
    n_columns: int = 0,
    error: type[SymsblError] = ParameterError,
) -> dict:
    """Every parameter checked against its constraint (raising ``error``); returns the validated values."""
    return {name: constraints[name].check(name, value, n_columns, error) for name, value in params.items()}


def _indices(name: str, value, n_columns: int) -> list[int]:
    items = [value] if isinstance(value, (int, np.integer)) else value
    try:
        items = list(items)
    except TypeError:
        raise ParameterError(expected(name, "column indices", value)) from None
    out = [integer(name, i, low=0, high=n_columns - 1) for i in items]
    if len(set(out)) != len(out):
        raise ParameterError(expected(name, "distinct column indices", value))
    return sorted(out)
