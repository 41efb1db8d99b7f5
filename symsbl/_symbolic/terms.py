"""Families of candidate terms: polynomials (with the |x| augmentation), elementwise functions,
inputs, user expressions, and the dictionary of Eq. (21) of Fuentes et al. (2019).

Each builder returns a :class:`~symsbl._symbolic.library.Library`; libraries combine with ``+``. A
builder counts its terms before it builds them and refuses a size that would not fit (see
:data:`MAX_CANDIDATES`): ``degree=100`` fails at once with the number, instead of running for
minutes or exhausting memory.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import casadi as ca
import sympy as sp

from .._base.checks import integer
from .._base.errors import LibraryError, expected
from .library import Library, _as_variables

__all__ = ["polynomial", "elementwise", "inputs", "custom", "paper", "ELEMENTWISE", "MAX_CANDIDATES"]

#: Elementwise functions known to :func:`elementwise`, by name.
ELEMENTWISE = {
    "sin": ca.sin,
    "cos": ca.cos,
    "tan": ca.tan,
    "sign": ca.sign,
    "abs": ca.fabs,
    "exp": ca.exp,
    "tanh": ca.tanh,
    "atan": ca.atan,
    "sqrt": ca.sqrt,  # NaN below zero: a level, a flow through an orifice
}

#: Largest number of candidate terms a builder makes before de-duplication. Building and
#: de-duplicating 846 terms takes about 1 s (sympy canonicalisation dominates) and the Gram of
#: M terms holds 8 M^2 bytes; 5000 terms take about 30 s to build and 200 MB of Gram.
MAX_CANDIDATES = 5000


def _check_size(n_terms: int, what: str) -> None:
    if n_terms > MAX_CANDIDATES:
        gram = 8 * n_terms**2 / 2**30
        raise LibraryError(
            expected(
                "degree",
                f"a library of at most {MAX_CANDIDATES} candidate terms",
                f"{n_terms} terms ({what}; their Gram matrix alone would take {gram:.3g} GiB)",
                "lower the degree or use fewer variables",
                raw=True,
            )
        )


def _monomials(z: Sequence[ca.SX], degree: int, include_bias: bool) -> list[ca.SX]:
    """All monomials of ``z`` up to ``degree``, each built as parent monomial * variable."""
    built: dict[tuple[int, ...], ca.SX] = {(): ca.SX(1)}
    out = [built[()]] if include_bias else []
    for d in range(1, degree + 1):
        for combo in itertools.combinations_with_replacement(range(len(z)), d):
            built[combo] = built[combo[:-1]] * z[combo[-1]]
            out.append(built[combo])
    return out


def _check_degree(degree) -> int:
    return integer("degree", degree, low=0, error=LibraryError)


def _polynomial_terms(variables, degree, include_bias, absolute) -> list[ca.SX]:
    z = list(variables) + ([ca.fabs(v) for v in variables] if absolute else [])
    degree = _check_degree(degree)
    _check_size(math.comb(len(z) + degree, degree), f"degree {degree} in {len(z)} variables")
    return _monomials(z, degree, include_bias)


def _elementwise_terms(variables, functions) -> list[ca.SX]:
    functions = [functions] if isinstance(functions, str) else list(functions)
    unknown = [f for f in functions if f not in ELEMENTWISE]
    if unknown:
        raise LibraryError(expected("functions", f"names among {sorted(ELEMENTWISE)}", unknown))
    return [ELEMENTWISE[f](v) for f in functions for v in variables]


def polynomial(variables, degree: int, *, include_bias: bool = True, absolute: bool = False) -> Library:
    """All monomials of ``variables`` up to total degree ``degree``.

    Monomials are ordered by degree and, within a degree, as
    ``itertools.combinations_with_replacement`` (the order of pysindy/scikit-learn).

    Parameters
    ----------
    variables : sequence of ca.SX
        Scalar symbols.
    degree : int
        Highest total degree, >= 0.
    include_bias : bool, default True
        Include the constant term ``1``.
    absolute : bool, default False
        Expand in ``(x1, ..., xp, |x1|, ..., |xp|)`` instead, the |x| augmentation of
        Fuentes et al. (2019) for hysteresis; duplicate functions are removed.

    Returns
    -------
    Library

    Examples
    --------
    >>> import symsbl
    >>> x1, x2 = symsbl.symbols("x1 x2")
    >>> symsbl.polynomial([x1, x2], 2).names
    ['1', 'x1', 'x2', 'x1**2', 'x1*x2', 'x2**2']

    With the |x| augmentation, ``|x1|**2`` is ``x1**2`` and appears once:

    >>> symsbl.polynomial([x1], 3, absolute=True).names
    ['1', 'x1', 'Abs(x1)', 'x1**2', 'x1*Abs(x1)', 'x1**3', 'x1**2*Abs(x1)']
    """
    variables = _as_variables(variables)
    return Library(_polynomial_terms(variables, degree, include_bias, absolute), variables)


def elementwise(variables, functions: Sequence[str] = ("sin", "cos", "tan", "sign", "abs")) -> Library:
    """Each function applied to each variable (function-major order).

    Parameters
    ----------
    variables : sequence of ca.SX
    functions : sequence of str
        Names from :data:`ELEMENTWISE`.

    Examples
    --------
    >>> import symsbl
    >>> x1, x2 = symsbl.symbols("x1 x2")
    >>> symsbl.elementwise([x1, x2], ["sin", "sign"]).names
    ['sin(x1)', 'sin(x2)', 'sign(x1)', 'sign(x2)']
    """
    variables = _as_variables(variables)
    return Library(_elementwise_terms(variables, functions), variables)


def inputs(variables) -> Library:
    """The linear terms ``u1, ..., um`` of the given (input) symbols.

    Examples
    --------
    >>> import symsbl
    >>> F, G = symsbl.symbols("F G")
    >>> symsbl.inputs([F, G]).names
    ['F', 'G']
    """
    variables = _as_variables(variables)
    return Library(list(variables), variables)


def custom(exprs: Sequence[ca.SX | sp.Expr], variables) -> Library:
    """A library of arbitrary CasADi or sympy expressions of ``variables``.

    Examples
    --------
    Any scalar CasADi expression of the declared variables is a candidate:

    >>> import casadi as ca
    >>> import symsbl
    >>> x1, x2 = symsbl.symbols("x1 x2")
    >>> symsbl.custom([ca.tanh(x2 / 0.2), ca.exp(-x1**2)], [x1, x2]).names
    ['tanh(5.0*x2)', 'exp(-x1**2)']
    """
    return Library(exprs, variables)


def paper(states, inputs: Sequence[ca.SX] = (), degree: int = 6) -> Library:
    """The dictionary of Eq. (21) of Fuentes et al. (2019).

    ``{F, P^1(x), ..., P^n(x), sin(x), cos(x), tan(x), sgn(x)}`` with the polynomial
    expansion taken over the states augmented by their absolute values.

    Parameters
    ----------
    states : sequence of ca.SX
    inputs : sequence of ca.SX, default ()
        Input symbols, entered linearly (first columns).
    degree : int, default 6
        Highest polynomial degree n.

    Returns
    -------
    Library
        Variables are ``states + inputs``.

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> lib = symsbl.paper([x1, x2], [F], degree=3)
    >>> len(lib), lib.names[:4], lib.variable_names
    (34, ['F', '1', 'x1', 'x2'], ['x1', 'x2', 'F'])
    """
    states = _as_variables(states, "states")
    ins = _as_variables(inputs, "inputs")
    terms = (
        list(ins)
        + _polynomial_terms(states, degree, True, True)
        + _elementwise_terms(states, ("sin", "cos", "tan", "sign"))
    )
    return Library(terms, _as_variables(states + ins, "states + inputs"))
