"""Candidate-term libraries: builders, de-duplication, combination."""

import itertools

import casadi as ca
import numpy as np
import pytest
import sympy as sp
from helpers import exactly

from symsbl import (
    Library,
    LibraryError,
    Term,
    custom,
    elementwise,
    inputs,
    paper,
    polynomial,
    symbols,
)

X1, X2, X3, F = symbols("x1 x2 x3 F")
S1, S2 = sp.symbols("x1 x2", real=True)


def columns(library, Z):
    """Design matrix through the library's own SX Function (no Evaluator), shape (n, M)."""
    return np.array(library.function().map(len(Z))(Z.T)).T


def random_points(n_vars, n=30, seed=11):
    rng = np.random.default_rng(seed)
    return rng.uniform(0.3, 2.0, size=(n, n_vars)) * rng.choice([-1.0, 1.0], size=(n, n_vars))


def distinct_up_to_scale(V):
    """Number of columns of V that differ by more than a constant factor (greedy grouping)."""
    V = V / np.linalg.norm(V, axis=0)
    V = V * np.where(V[0] < 0, -1.0, 1.0)
    seen = np.zeros(V.shape[1], bool)
    groups = 0
    for i in range(V.shape[1]):
        if not seen[i]:
            groups += 1
            seen |= np.max(np.abs(V - V[:, [i]]), axis=0) < 1e-9
    return groups


def eq21_raw_columns(Z, n_states):
    """The paper's Eq. (21) candidates with every duplicate kept, straight in numpy.

    Columns: F, all monomials up to the degree of (x, |x|), sin, cos, tan, sign of x.
    """
    X, u = Z[:, :n_states], Z[:, n_states:]
    aug = np.hstack([X, np.abs(X)])

    def build(degree):
        cols = [u[:, 0]]
        for d in range(degree + 1):
            for combo in itertools.combinations_with_replacement(range(2 * n_states), d):
                cols.append(np.prod(aug[:, list(combo)], axis=1))
        cols += [f(X[:, i]) for f in (np.sin, np.cos, np.tan, np.sign) for i in range(n_states)]
        return np.column_stack(cols)

    return build


# Expected sizes of the Eq. (21) dictionary, derived by hand.
# Raw: 1 input + C(2p + n, n) monomials of the 2p augmented variables (x, |x|) + 4p functions.
# Distinct: as functions, x^a |x|^c = |x|^(a+c) sign(x)^a, so each variable of partial degree
# k >= 1 gives exactly two functions (|x|^k and sign(x)|x|^k; both parities of a occur) and
# k = 0 gives one. The count with total degree <= n is the t^n coefficient of
# ((1+t)/(1-t))^p / (1-t) = (1+t)^p / (1-t)^(p+1), i.e. sum_j C(p, j) C(n - j + p, p):
#   p=2: n=3 -> 10 + 2*6 + 3 = 25,   n=6 -> 28 + 2*21 + 15 = 85    (= 2n(n+1) + 1)
#   p=3: n=3 -> 20 + 3*10 + 3*4 + 1 = 63,   n=6 -> 84 + 3*56 + 3*35 + 20 = 377
# Then distinct = 1 + that + 4p (sin, cos, tan, sign are new functions).
EQ21_SIZES = {
    # (n_states, degree): (raw, distinct)
    (2, 3): (1 + 35 + 8, 1 + 25 + 8),  # 44 -> 34
    (2, 6): (1 + 210 + 8, 1 + 85 + 8),  # 219 -> 94
    (3, 3): (1 + 84 + 12, 1 + 63 + 12),  # 97 -> 76
    (3, 6): (1 + 924 + 12, 1 + 377 + 12),  # 937 -> 390
}


@pytest.mark.parametrize("n_states, degree", sorted(EQ21_SIZES))
def test_eq21_deduplication_removes_exactly_the_duplicate_columns(n_states, degree):
    states = (X1, X2, X3)[:n_states]
    library = paper(states, (F,), degree=degree)
    Z = random_points(n_states + 1)
    raw = eq21_raw_columns(Z, n_states)(degree)
    raw_count, distinct = EQ21_SIZES[(n_states, degree)]
    assert raw.shape[1] == raw_count
    assert distinct_up_to_scale(raw) == distinct
    assert len(library) == distinct
    kept = columns(library, Z)
    assert distinct_up_to_scale(kept) == len(library)  # no duplicates left
    assert distinct_up_to_scale(np.hstack([kept, raw])) == len(library)  # nothing distinct lost
    assert library.variable_names == [s.name() for s in states] + ["F"]
    assert library.names[:2] == ["F", "1"]
    assert library.names[-4 * n_states :] == [f"{f}({s.name()})" for f in ("sin", "cos", "tan", "sign") for s in states]


def test_polynomial_order_matches_combinations_with_replacement():
    lib = polynomial((X1, X2), 3)
    expected = ["1"] + [
        str(sp.Mul(*c)) for d in (1, 2, 3) for c in itertools.combinations_with_replacement((S1, S2), d)
    ]
    assert lib.names == expected
    assert polynomial((X1, X2), 2, include_bias=False).names == expected[1:6]
    assert polynomial((X1,), 0).names == ["1"]


def test_absolute_augmentation_names_and_values():
    lib = polynomial((X1,), 3, absolute=True)
    # |x|^2 -> x^2, x|x| stays, |x|^3 = x^2|x|, x|x|^2 = x^3, x^2|x| already counted.
    assert lib.names == ["1", "x1", "Abs(x1)", "x1**2", "x1*Abs(x1)", "x1**3", "x1**2*Abs(x1)"]
    z = np.linspace(-2, 2, 9)[:, None]
    x = z[:, 0]
    np.testing.assert_allclose(
        columns(lib, z), np.column_stack([np.ones_like(x), x, abs(x), x**2, x * abs(x), x**3, x**2 * abs(x)])
    )


def test_numeric_deduplication_of_equal_and_proportional_functions():
    lib = Library(
        [
            X1 * ca.sign(X1),  # == |x1|
            ca.fabs(X1),
            2 * X2,
            X2,  # 2*x2 and x2 are the same column up to scale; x2 is simpler
            ca.SX(3.0),
            ca.SX(1.0),  # constants appear once, as 1
            X1 - X1,  # identically zero: dropped
            ca.fabs(X1) ** 2,  # named x1**2 through sympy
            X1 * X1,
            ca.sin(X1),
        ],
        (X1, X2),
    )
    assert lib.names == ["Abs(x1)", "x2", "1", "x1**2", "sin(x1)"]
    assert lib["1"].sympy == 1


def test_term_name_comes_from_the_expression():
    t = Term(ca.fabs(X2) * X1 * X1)
    assert t.name == "x1**2*Abs(x2)" and t.sympy == S1**2 * sp.Abs(S2)
    assert Term(X1 * X2) == Term(X2 * X1)
    with pytest.raises(TypeError):
        Term(X1, name="custom")  # names are never typed by hand
    with pytest.raises(LibraryError, match=r"expr: expected a scalar casadi.SX expression, received shape \(2, 1\)"):
        Term(ca.vertcat(X1, X2))


def test_elementwise_inputs_custom_and_sympy_terms():
    assert elementwise((X1, X2), ("sin", "abs")).names == ["sin(x1)", "sin(x2)", "Abs(x1)", "Abs(x2)"]
    assert inputs((F,)).names == ["F"]
    lib = custom([sp.sign(S2) * sp.Abs(S1) ** sp.Rational(1, 2), ca.exp(X1) * X2], (X1, X2))
    assert lib.names == ["sqrt(Abs(x1))*sign(x2)", "x2*exp(x1)"]
    z = random_points(2)
    np.testing.assert_allclose(
        columns(lib, z),
        np.column_stack([np.sign(z[:, 1]) * np.sqrt(abs(z[:, 0])), z[:, 1] * np.exp(z[:, 0])]),
        rtol=1e-14,
    )


def test_add_merges_variables_by_name_and_deduplicates():
    other_x1, u = symbols("x1 u")  # a different SX object named x1
    a = polynomial((X1, X2), 2)
    b = Library([other_x1**2, other_x1 * u, u], (other_x1, u))
    c = a + b
    assert c.variable_names == ["x1", "x2", "u"]
    assert c.names == a.names + ["u*x1", "u"]
    z = random_points(3)
    np.testing.assert_allclose(columns(c, z)[:, -2], z[:, 0] * z[:, 2])
    assert (a + a) == a and hash(a + a) == hash(a)


def test_select_drop_index_and_container_protocol():
    lib = paper((X1, X2), (F,), degree=2)
    assert "x1*Abs(x2)" in lib and "Abs(x1)**2" not in lib
    assert lib[lib.index("sign(x2)")].name == "sign(x2)" == lib["sign(x2)"].name
    assert lib[0].name == "F" and [t.name for t in lib] == lib.names
    sub = lib.select(["x2", "F", "sign(x2)"])
    assert sub.names == ["x2", "F", "sign(x2)"] and sub.variable_names == lib.variable_names
    rest = lib.drop(["F", "1"])
    assert rest.names == lib.names[2:]
    assert lib.to_sympy()[lib.index("x1*Abs(x2)")] == S1 * sp.Abs(S2)
    assert not lib.is_smooth and polynomial((X1, X2), 3).is_smooth
    assert len(lib.exprs) == len(lib)


def test_function_evaluates_the_terms():
    lib = polynomial((X1, X2), 2) + elementwise((X1,), ("cos", "tan"))
    f = lib.function("theta")
    assert f.name() == "theta" and f.name_in() == ["z"] and f.name_out() == ["d"]
    assert f.size1_out(0) == len(lib) and f.size1_in(0) == 2
    z = np.array([[0.5, -1.5]])
    x, y = 0.5, -1.5
    np.testing.assert_allclose(columns(lib, z)[0], [1, x, y, x * x, x * y, y * y, np.cos(x), np.tan(x)])


@pytest.mark.parametrize(
    "build, match",
    [
        (
            lambda: elementwise((X1,), ("sin", "sinc")),
            exactly(
                "functions: expected names among ['abs', 'atan', 'cos', "
                "'exp', 'sign', 'sin', 'sqrt', 'tan', 'tanh'], received "
                "['sinc']"
            ),
        ),
        (lambda: polynomial((X1,), -1), r"degree: expected an integer >= 0, received -1"),
        (lambda: polynomial((X1,), 2.0), r"degree: expected an integer >= 0, received 2.0"),
        (lambda: polynomial("x1 x2", 2), r"variables: expected a sequence of scalar casadi.SX symbols, received str"),
        (lambda: polynomial((X1, X1 * 2), 2), r"variables\[1\]: expected a scalar casadi.SX symbol"),
        (
            lambda: polynomial((X1, symbols("x1")[0]), 2),
            exactly("variables: expected distinct symbol names, received ['x1', 'x1']; rename the repeated ['x1']"),
        ),
        (
            lambda: Library([X1 * X3], (X1, X2)),
            exactly(
                "terms[0]: expected an expression of the variables ['x1', "
                "'x2'], received one that also uses ['x3']; declare them as "
                "variables"
            ),
        ),
        (
            lambda: Library([X1, ca.vertcat(X1, X2)], (X1, X2)),
            r"terms\[1\]: expected a scalar expression, received "
            r"shape \(2, 1\)",
        ),
        (lambda: Library(["x1"], (X1,)), r"terms\[0\]: expected a casadi.SX, sympy expression or Term, received str"),
        (lambda: Library([X1], ()), r"variables: expected at least one scalar casadi.SX symbol"),
        (lambda: paper((X1,), (X1,), 2), r"states \+ inputs: expected distinct symbol names"),
        (
            lambda: paper((X1, X2), (F,), 2).index("x1**2*abs(x2)"),
            exactly(
                "name: expected a term of this library of 22 "
                "terms, received 'x1**2*abs(x2)'; close "
                "names: ['x2*Abs(x2)', 'x1*Abs(x2)', "
                "'x2*Abs(x1)', 'x1*Abs(x1)', "
                "'Abs(x1)*Abs(x2)']; see Library.names"
            ),
        ),
        (
            lambda: paper((X1, X2), (F,), 2).drop(["nope"]),
            exactly("name: expected a term of this library of 22 terms, received 'nope'; see Library.names"),
        ),
    ],
)
def test_errors_name_argument_expected_and_received(build, match):
    with pytest.raises(LibraryError, match=match):
        build()


def test_terms_that_differ_only_near_zero_are_kept_apart():
    # tanh(x/eps) equals sign(x) to machine precision for |x| > 0.04; only small |x| tells them apart
    import casadi as ca

    from symsbl import custom, elementwise, symbols

    (x,) = symbols("x")
    lib = elementwise([x], ("sign",)) + custom([ca.tanh(x / 1e-3)], [x])
    assert lib.names == ["sign(x)", "tanh(1000.0*x)"]
