"""Candidate-term libraries: named CasADi SX expressions of declared variables.

A :class:`Library` is an immutable, ordered set of :class:`Term` objects over declared scalar
SX symbols (states, then inputs). Every term's name is printed from its own sympy form, so
the name, the column of the design matrix and the symbolic form cannot disagree.

Builders: :func:`polynomial`, :func:`elementwise`, :func:`inputs`, :func:`custom` and
:func:`paper`, the dictionary of Eq. (21) of Fuentes et al. (2019), "Equation discovery for
nonlinear dynamical systems: a Bayesian viewpoint", MSSP. Libraries combine with ``+``.

De-duplication
--------------
Every library removes terms that are the same function, in two stages:

1. *Names.* The sympy form uses real symbols, so sympy already rewrites ``Abs(x)**2`` as
   ``x**2`` and ``x*Abs(x)**2`` as ``x**3``; terms with equal names are equal.
   Nonzero constants are replaced by ``1``; terms that are identically zero are dropped.
2. *Numbers.* The remaining terms are evaluated at a fixed seeded set of random points
   (both signs, magnitudes from 0.2 to 3). Columns that are equal up to a nonzero factor
   (relative difference below 1e-10 after scaling to unit norm) are the same function up
   to a constant, e.g. ``x*sign(x)`` and ``Abs(x)``, ``x**3*Abs(x)`` and ``x*Abs(x)**3``,
   or ``2*x1`` and ``x1``. Of each group the simplest term (fewest sympy ``count_ops``,
   then the first seen) is kept, at the position of the group's first member.

Terms read from a file (a model file, a library file, an effects file) are bounded in number and in
expression nodes (:data:`MAX_FILE_TERMS`, :data:`MAX_FILE_NODES`, :func:`bound_size`) before any work on them.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import casadi as ca
import numpy as np
import sympy as sp

from .._base.casadi import scalar_symbols
from .._base.errors import LibraryError, SymsblError, expected
from .symbols import casadi_to_sympy, is_smooth, sympy_to_casadi

__all__ = ["Term", "Library", "MAX_FILE_TERMS", "MAX_FILE_NODES", "bound_size", "expression_nodes"]

_N_PROBE = 40
_RTOL_DUPLICATE = 1e-10
#: Most terms, and most expression nodes of their terms, a file may bring (a model file, a library file, an
#: effects file): validating 1000 polynomial terms, 11000 nodes, takes 20 s and 0.7 GB on a 4097-sample record
#: and the work grows in proportion; nested terms grow faster (54 library terms of 12000 nodes: over 5 min).
MAX_FILE_TERMS, MAX_FILE_NODES = 1000, 12_000


def expression_nodes(exprs) -> int:
    """The expression nodes of ``exprs`` in all (``casadi.n_nodes`` of each), as :data:`MAX_FILE_NODES` counts."""
    return sum(ca.n_nodes(e) for e in exprs)


def bound_size(count: int, most: int, what: str, *, where: str, why: str, fix: str, error: type[SymsblError]) -> None:
    """Refuse a file bringing ``count`` ``what`` (terms, expression nodes) beyond ``most``.

    Parameters
    ----------
    count, most : int
    what : str
        What is counted, e.g. ``"terms"``.
    where : str
        The file or field at fault.
    why : str
        The reason for the bound, in the file's terms.
    fix : str
        What to do about it.
    error : SymsblError subclass
        Raised when ``count > most``.
    """
    if count > most:
        raise error(expected(where, f"at most {most} {what} in all ({why})", f"{count}", fix, raw=True))


@dataclass(frozen=True)
class Term:
    """One candidate term: a scalar SX expression and the name printed from it.

    Parameters
    ----------
    expr : ca.SX
        Scalar expression of the library's variables.

    Attributes
    ----------
    name : str
        ``str`` of the sympy form with real symbols, e.g. ``"x1**2*Abs(x2)"``; derived, never given.

    Examples
    --------
    >>> import casadi as ca
    >>> import symsbl
    >>> x1, x2 = symsbl.symbols("x1 x2")
    >>> term = symsbl.Term(x1**2 * ca.fabs(x2))
    >>> term.name, term.sympy
    ('x1**2*Abs(x2)', x1**2*Abs(x2))
    """

    expr: ca.SX = field(compare=False)
    name: str = field(init=False)
    _sympy: sp.Expr = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        expr = ca.SX(self.expr)
        if not expr.is_scalar():
            raise LibraryError(
                expected(
                    "expr",
                    "a scalar casadi.SX expression",
                    f"shape {expr.shape}",
                    "split vector expressions into one term per element",
                    raw=True,
                )
            )
        object.__setattr__(self, "expr", expr)
        if not hasattr(self, "_sympy"):
            object.__setattr__(self, "_sympy", casadi_to_sympy(expr))
        object.__setattr__(self, "name", str(self._sympy))

    @classmethod
    def _from_parts(cls, expr: ca.SX, sym: sp.Expr) -> Term:
        term = cls.__new__(cls)
        object.__setattr__(term, "_sympy", sym)
        object.__setattr__(term, "expr", expr)
        term.__post_init__()
        return term

    @property
    def sympy(self) -> sp.Expr:
        """The sympy form (real symbols named as the SX symbols)."""
        return self._sympy


def _as_variables(variables, argname: str = "variables") -> tuple[ca.SX, ...]:
    return scalar_symbols(variables, argname, LibraryError)


def _probe_points(n_vars: int) -> np.ndarray:
    """Fixed probe points: half with magnitudes in [0.2, 3], half in [1e-5, 0.2] so that terms
    that differ only near zero (``tanh(x/eps)`` against ``sign(x)``) are told apart."""
    rng = np.random.default_rng(20190512)
    half = _N_PROBE // 2
    low = np.full((_N_PROBE, n_vars), np.log10(0.2))
    low[half:] = -5.0
    high = np.full((_N_PROBE, n_vars), np.log10(3.0))
    high[half:] = np.log10(0.2)
    magnitude = 10 ** rng.uniform(low, high)
    return magnitude * rng.choice([-1.0, 1.0], size=(_N_PROBE, n_vars))


def _probe(exprs: list[ca.SX], variables: tuple[ca.SX, ...]) -> np.ndarray:
    """Values of the terms at the probe points, shape (n_probe, n_terms)."""
    f = ca.Function("probe", [ca.vertcat(*variables)], [ca.vertcat(*exprs)])
    return np.asarray(f.map(_N_PROBE)(_probe_points(len(variables)).T)).T


def _canonical_columns(values: np.ndarray) -> np.ndarray:
    """Scale columns to unit norm with a positive first entry; NaN where not finite."""
    finite = np.isfinite(values)
    v = np.where(finite, values, 0.0)
    norm = np.linalg.norm(v, axis=0)
    first = v[np.argmax(v != 0, axis=0), np.arange(v.shape[1])]
    sign = np.where(first < 0, -1.0, 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        v = v / (norm * sign)
    return np.where(finite, v, np.nan)


def _deduplicate(terms: list[Term], variables: tuple[ca.SX, ...]) -> list[Term]:
    # Stage 1: constants and exact names.
    one = None
    by_name: dict[str, Term] = {}
    for t in terms:
        if t.sympy.is_number:
            if t.sympy == 0:
                continue
            one = one or Term._from_parts(ca.SX(1), sp.Integer(1))
            t = one
        by_name.setdefault(t.name, t)
    unique = list(by_name.values())
    if len(unique) < 2:
        return unique
    # Stage 2: equal up to a constant factor at the probe points.
    cols = _canonical_columns(_probe([t.expr for t in unique], variables))
    usable = np.isfinite(cols).any(axis=0) & (np.nan_to_num(cols) != 0).any(axis=0)
    pattern = np.isnan(cols)
    filled = np.nan_to_num(cols)
    close = np.abs(filled.T @ filled) > 1 - 1e-6
    group = list(range(len(unique)))
    for i, j in zip(*np.nonzero(np.triu(close, 1))):
        if not (usable[i] and usable[j]) or group[j] != j or group[i] != i:
            continue
        if np.array_equal(pattern[:, i], pattern[:, j]) and (
            np.max(np.abs(filled[:, i] - filled[:, j])) < _RTOL_DUPLICATE
        ):
            group[j] = i
    members: dict[int, list[int]] = {}
    for k, g in enumerate(group):
        members.setdefault(g, []).append(k)
    out = []
    for idx in members.values():
        best = min(idx, key=lambda k: (sp.count_ops(unique[k].sympy), k))
        out.append(unique[best])
    return out


def _rebind(expr: ca.SX, variables: tuple[ca.SX, ...], where: str) -> ca.SX:
    """Make a term use the library's own SX symbols (matched by name)."""
    by_name = {v.name(): v for v in variables}
    free = ca.symvar(expr)
    unknown = [s.name() for s in free if s.name() not in by_name]
    if unknown:
        raise LibraryError(
            expected(
                where,
                f"an expression of the variables {list(by_name)}",
                f"one that also uses {unknown}",
                "declare them as variables",
                raw=True,
            )
        )
    swap = [(s, by_name[s.name()]) for s in free if not ca.is_equal(s, by_name[s.name()])]
    if swap:
        expr = ca.substitute(expr, ca.vertcat(*(a for a, _ in swap)), ca.vertcat(*(b for _, b in swap)))
    return expr


class Library:
    """An immutable ordered set of candidate terms over declared variables.

    Parameters
    ----------
    terms : sequence of ca.SX, sympy.Expr or Term
        Scalar expressions of ``variables``. sympy expressions are converted by symbol name.
        Duplicate functions are removed (see the module docstring).
    variables : sequence of ca.SX
        Scalar SX symbols with distinct names: states first, then inputs. This is the
        column order of the data an :class:`~symsbl.Evaluator` expects.

    Examples
    --------
    Terms that are the same function are kept once (``2*x2`` is ``x2`` up to its coefficient):

    >>> import casadi as ca
    >>> import symsbl
    >>> x1, x2 = symsbl.symbols("x1 x2")
    >>> lib = symsbl.Library([x1, x2, x1 * ca.fabs(x1), 2 * x2], [x1, x2])
    >>> lib.names
    ['x1', 'x2', 'x1*Abs(x1)']
    >>> (lib + symsbl.elementwise([x1], ["sin"])).drop(["x2"]).names
    ['x1', 'x1*Abs(x1)', 'sin(x1)']
    >>> lib["x1*Abs(x1)"].sympy
    x1*Abs(x1)
    """

    def __init__(self, terms: Sequence[ca.SX | sp.Expr | Term], variables: Sequence[ca.SX]):
        self._variables = _as_variables(variables)
        if not self._variables:
            raise LibraryError("variables: expected at least one scalar casadi.SX symbol, received none")
        if isinstance(terms, (ca.SX, sp.Basic, Term)):
            terms = [terms]
        symbol_map = {v.name(): v for v in self._variables}
        pending: list[tuple[int, Term]] = []
        raw: list[tuple[int, ca.SX]] = []
        for i, t in enumerate(terms):
            where = f"terms[{i}]"
            if isinstance(t, Term):
                pending.append((i, t))
                continue
            if isinstance(t, sp.Basic):
                t = sympy_to_casadi(t, symbol_map)
            elif isinstance(t, (int, float)):
                t = ca.SX(t)
            elif not isinstance(t, ca.SX):
                raise LibraryError(
                    f"{where}: expected a casadi.SX, sympy expression or Term, received {type(t).__name__}"
                )
            if not t.is_scalar():
                raise LibraryError(
                    f"{where}: expected a scalar expression, received shape {t.shape}; pass one term per element"
                )
            raw.append((i, _rebind(t, self._variables, where)))
        converted = casadi_to_sympy([e for _, e in raw]) if raw else []
        made = {i: Term._from_parts(e, s) for (i, e), s in zip(raw, converted)}
        for i, t in pending:
            made[i] = Term._from_parts(_rebind(t.expr, self._variables, f"terms[{i}]"), t.sympy)
        ordered = [made[i] for i in sorted(made)]
        self._terms = tuple(_deduplicate(ordered, self._variables))
        self._index = {t.name: k for k, t in enumerate(self._terms)}

    # --- container protocol -------------------------------------------------------------
    @property
    def terms(self) -> tuple[Term, ...]:
        """The terms, in column order."""
        return self._terms

    @property
    def names(self) -> list[str]:
        """Term names, in column order."""
        return [t.name for t in self._terms]

    @property
    def variables(self) -> tuple[ca.SX, ...]:
        """Declared scalar SX symbols (states, then inputs)."""
        return self._variables

    @property
    def variable_names(self) -> list[str]:
        """Names of the declared variables, in data-column order."""
        return [v.name() for v in self._variables]

    @property
    def exprs(self) -> list[ca.SX]:
        """Term expressions, in column order."""
        return [t.expr for t in self._terms]

    @property
    def is_smooth(self) -> bool:
        """False if any term uses sign, fabs, fmin, fmax, if_else, floor or ceil."""
        return is_smooth(self.exprs) if self._terms else True

    def __len__(self) -> int:
        return len(self._terms)

    def __iter__(self) -> Iterator[Term]:
        return iter(self._terms)

    def __contains__(self, name: object) -> bool:
        return name in self._index

    def __getitem__(self, key: int | str) -> Term:
        if isinstance(key, str):
            return self._terms[self.index(key)]
        return self._terms[key]

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Library):
            return NotImplemented
        return self.names == other.names and self.variable_names == other.variable_names

    def __hash__(self) -> int:
        return hash((tuple(self.names), tuple(self.variable_names)))

    def __repr__(self) -> str:
        shown = ", ".join(self.names[:6]) + (", ..." if len(self) > 6 else "")
        return f"Library({len(self)} terms over {self.variable_names}: {shown})"

    def index(self, name: str) -> int:
        """Column index of the term called ``name``.

        Raises
        ------
        LibraryError
            If no term has that name (the message suggests close names).
        """
        try:
            return self._index[name]
        except (KeyError, TypeError):
            close = difflib.get_close_matches(str(name), self.names, n=5)
            fix = (f"close names: {close}; " if close else "") + "see Library.names"
            raise LibraryError(expected("name", f"a term of this library of {len(self)} terms", name, fix)) from None

    # --- combination ---------------------------------------------------------------------
    def __add__(self, other: Library) -> Library:
        if not isinstance(other, Library):
            return NotImplemented
        mine = set(self.variable_names)
        extra = tuple(v for v in other.variables if v.name() not in mine)
        return Library(self._terms + other.terms, self._variables + extra)

    def select(self, names: Sequence[str]) -> Library:
        """A library of the named terms, in the given order, over the same variables."""
        names = [names] if isinstance(names, str) else list(names)
        return Library([self[n] for n in names], self._variables)

    def drop(self, names: Sequence[str]) -> Library:
        """A library without the named terms, over the same variables."""
        names = [names] if isinstance(names, str) else list(names)
        gone = {self.index(n) for n in names}
        return Library([t for k, t in enumerate(self._terms) if k not in gone], self._variables)

    def to_sympy(self) -> list[sp.Expr]:
        """The sympy form of every term, in column order."""
        return [t.sympy for t in self._terms]

    def function(self, name: str = "dictionary") -> ca.Function:
        """One SX Function ``[z (n_variables x 1)] -> [d (n_terms x 1)]`` for the whole library."""
        return ca.Function(name, [ca.vertcat(*self._variables)], [ca.vertcat(*self.exprs)], ["z"], ["d"])
