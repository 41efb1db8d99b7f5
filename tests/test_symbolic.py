"""Exact CasADi <-> sympy conversion."""

import casadi as ca
import numpy as np
import pytest
import sympy as sp
from helpers import exactly
from hypothesis import given, settings
from hypothesis import strategies as st

from symsbl import LibraryError, paper
from symsbl._symbolic.symbols import casadi_to_sympy, is_smooth, symbols, sympy_to_casadi

X1, X2, X3, F = symbols("x1 x2 x3 F")
S1, S2, S3, SF = sp.symbols("x1 x2 x3 F", real=True)
SX_BY_NAME = {"x1": X1, "x2": X2, "x3": X3, "F": F}
POINTS = np.random.default_rng(3).uniform(-2.5, 2.5, size=(25, 4))


def values(expr):
    """Evaluate a scalar SX expression of (x1, x2, x3, F) at POINTS."""
    f = ca.Function("f", [ca.vertcat(X1, X2, X3, F)], [expr])
    return np.array(f.map(len(POINTS))(POINTS.T)).ravel()


def sympy_values(expr):
    f = sp.lambdify([S1, S2, S3, SF], expr, "numpy")
    return np.broadcast_to(np.asarray(f(*POINTS.T), dtype=float), (len(POINTS),))


def test_symbols_accepts_spaces_commas_and_sequences():
    a = symbols("a b, c")
    b = symbols(["u", "v"])
    assert [s.name() for s in a + b] == ["a", "b", "c", "u", "v"]
    assert all(s.is_symbolic() and s.is_scalar() for s in a + b)


@pytest.mark.parametrize(
    "names, match",
    [
        ("", r"names: expected identifiers.*no names"),
        ("x 1y", r"invalid: \['1y'\]"),
        ("x x", r"distinct.*\['x', 'x'\]"),
    ],
)
def test_symbols_rejects_bad_names(names, match):
    with pytest.raises(LibraryError, match=match):
        symbols(names)


@pytest.mark.parametrize(
    "expr, expected",
    [
        (X1 * ca.fabs(X1) * ca.fabs(X1), S1**3),  # |x|^2 = x^2 for real x
        (ca.constpow(X1, 3), S1**3),
        (X1**7, S1**7),
        (ca.sign(X2) * X1, S1 * sp.sign(S2)),
        (1 / X1, 1 / S1),
        (X1**-2, S1**-2),
        (ca.sqrt(X1), sp.sqrt(S1)),
        (X1**2.5, S1 ** sp.Rational(5, 2)),
        (ca.fmin(X1, X2), sp.Min(S1, S2)),
        (ca.tan(X1) * ca.exp(X2) - ca.log(X3), sp.tan(S1) * sp.exp(S2) - sp.log(S3)),
        (2.5 * X1 - 3 * X2**3 + 0.1 * ca.sign(X2), 2.5 * S1 - 3 * S2**3 + sp.Float(0.1) * sp.sign(S2)),
        (ca.SX(7.0), sp.Integer(7)),
        (2 * X1, 2 * S1),  # CasADi stores this as OP_TWICE
    ],
)
def test_casadi_to_sympy_is_structurally_exact(expr, expected):
    got = casadi_to_sympy(expr)
    assert got == expected
    assert sympy_to_casadi(got, SX_BY_NAME).is_scalar()


def test_integer_constants_and_powers_stay_integers():
    got = casadi_to_sympy(3 * X1**3 + 2)
    assert got == 3 * S1**3 + 2
    numbers = [a for a in sp.preorder_traversal(got) if a.is_Number]
    assert numbers and all(isinstance(a, sp.Integer) for a in numbers)
    assert "3.0" not in str(got) and "**3" in str(got)


def test_vector_and_list_inputs_give_lists_and_custom_symbols_are_used():
    mine = sp.Symbol("x1", positive=True)
    out = casadi_to_sympy(ca.vertcat(X1 * X2, ca.sin(X1)), {"x1": mine})
    assert out == [mine * S2, sp.sin(mine)]
    assert casadi_to_sympy([X1, X2 + 1]) == [S1, S2 + 1]


def test_if_else_and_logic_round_trip_numerically():
    exprs = [ca.if_else(X1 > 0, X1, X2), ca.logic_and(X1 > 0, X2 < 1) * 3, ca.fmax(X1, ca.fabs(X2))]
    for expr, sym in zip(exprs, casadi_to_sympy(exprs)):
        np.testing.assert_array_equal(values(expr), sympy_values(sym))
        np.testing.assert_array_equal(values(sympy_to_casadi(sym, SX_BY_NAME)), values(expr))


def test_every_term_of_the_paper_dictionary_round_trips_exactly():
    library = paper((X1, X2, X3), (F,), degree=4)
    syms = casadi_to_sympy(library.exprs)
    back = [sympy_to_casadi(s, SX_BY_NAME) for s in syms]
    assert casadi_to_sympy(back) == syms  # structurally identical after a second pass
    for expr, sym, again in zip(library.exprs, syms, back):
        ref = values(expr)
        np.testing.assert_allclose(sympy_values(sym), ref, rtol=1e-13, atol=0)
        np.testing.assert_allclose(values(again), ref, rtol=1e-13, atol=0)


def test_sympy_to_casadi_handles_piecewise_pow_and_constants():
    expr = sp.Piecewise((S1**-3, S1 > 1), (sp.Abs(S2) ** sp.Rational(1, 3), S2 < 0), (sp.pi, True))
    got = values(sympy_to_casadi(expr, SX_BY_NAME))
    np.testing.assert_allclose(got, sympy_values(expr), rtol=1e-14)
    assert float(sympy_to_casadi(S1**0, SX_BY_NAME)) == 1.0


def test_sympy_to_casadi_keeps_sign_exact_where_lambdify_fails():
    expr = S1 * sp.sign(S2) + sp.Abs(S1) * sp.sign(S1)
    np.testing.assert_array_equal(values(sympy_to_casadi(expr, SX_BY_NAME)), sympy_values(expr))
    f = ca.Function("f", [X1], [sympy_to_casadi(sp.sign(S1), SX_BY_NAME)])
    assert float(f(0.0)) == 0.0


def test_sympy_to_casadi_errors_name_the_symbol_and_function():
    with pytest.raises(
        LibraryError,
        match=exactly(
            "expr: expected symbols among the declared variables ['F', 'x1', "
            "'x2', 'x3'], received 'y'; declare it or rename it"
        ),
    ):
        sympy_to_casadi(S1 + sp.Symbol("y"), SX_BY_NAME)
    with pytest.raises(
        LibraryError,
        match=exactly(
            "expr: expected functions with a CasADi counterpart (Add, Mul, Pow, "
            "Piecewise, Abs, And, Equality, GreaterThan, LessThan, Max, Min, "
            "Not, Or, StrictGreaterThan, StrictLessThan, Unequality, acos, "
            "acosh, asin, asinh, atan, atan2, atanh, ceiling, cos, cosh, erf, "
            "exp, floor, log, sign, sin, sinh, tan, tanh), received gamma"
        ),
    ):
        sympy_to_casadi(sp.gamma(S1), SX_BY_NAME)


def test_casadi_to_sympy_errors_name_the_operation():
    with pytest.raises(
        LibraryError,
        match=exactly(
            "expr: expected operations with a sympy counterpart, received the "
            "CasADi operation OP_FMOD; rewrite the term with elementary "
            "functions, powers, sign, fabs, fmin/fmax or if_else"
        ),
    ):
        casadi_to_sympy(ca.fmod(X1, X2))
    with pytest.raises(LibraryError, match=r"expected a casadi.SX expression or a list of them, received dict"):
        casadi_to_sympy({"a": X1})
    with pytest.raises(
        LibraryError,
        match=r"expr\[1\]: expected a scalar casadi.SX expression, received SX of shape "
        r"\(2, 1\)",
    ):
        casadi_to_sympy([X1, ca.vertcat(X1, X2)])


def test_is_smooth():
    assert is_smooth([X1 * X2, ca.sin(X1), ca.exp(X2) / X1])
    for rough in (ca.sign(X1), ca.fabs(X1) * X2, ca.fmin(X1, X2), ca.if_else(X1 > 0, X1, 0), ca.floor(X1)):
        assert not is_smooth([X1, rough])


_UNARY = [ca.sin, ca.cos, ca.sign, ca.fabs, ca.tanh, lambda a: a]
_SP_UNARY = [sp.sin, sp.cos, sp.sign, sp.Abs, sp.tanh, lambda a: a]


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.integers(-5, 5).filter(bool),
            st.integers(0, len(_UNARY) - 1),
            st.lists(st.integers(0, 2), min_size=1, max_size=4),
        ),
        min_size=1,
        max_size=4,
    )
)
def test_round_trip_of_random_expressions(parts):
    """sum_k c_k * g_k(prod of variables): casadi->sympy equals the sympy-built reference."""
    xs, ss = (X1, X2, X3), (S1, S2, S3)
    expr, ref = ca.SX(0), sp.Integer(0)
    for coef, fun, idx in parts:
        mono_x, mono_s = ca.SX(1), sp.Integer(1)
        for i in idx:
            mono_x, mono_s = mono_x * xs[i], mono_s * ss[i]
        expr += coef * _UNARY[fun](mono_x)
        ref += coef * _SP_UNARY[fun](mono_s)
    got = casadi_to_sympy(expr)
    assert sp.simplify(got - ref) == 0
    back = sympy_to_casadi(got, SX_BY_NAME)
    np.testing.assert_allclose(values(back), values(expr), rtol=1e-13, atol=1e-13)
