"""Chunked evaluation of a library against plain numpy."""

import itertools
from collections import OrderedDict

import numpy as np
import pytest
import sympy as sp
from helpers import exactly
from hypothesis import given, settings
from hypothesis import strategies as st

import symsbl._base.jit as jit_module
import symsbl._symbolic.evaluator as evaluator_module
from symsbl import Evaluator, LibraryError, paper, polynomial, symbols

X1, X2, X3, F = symbols("x1 x2 x3 F")
HAS_COMPILER = jit_module.compiler() is not None


def numpy_reference(library, Z):
    """Each term's sympy form evaluated by numpy, shape (n_samples, n_terms)."""
    syms = [sp.Symbol(n, real=True) for n in library.variable_names]
    cols = [sp.lambdify(syms, s, "numpy")(*Z.T) for s in library.to_sympy()]
    return np.column_stack([np.broadcast_to(np.asarray(c, float), (len(Z),)) for c in cols])


def polynomial_reference(Z, degree):
    """All monomials up to degree in combinations_with_replacement order, by numpy products."""
    cols = [np.ones(len(Z))]
    for d in range(1, degree + 1):
        cols += [np.prod(Z[:, list(c)], axis=1) for c in itertools.combinations_with_replacement(range(Z.shape[1]), d)]
    return np.column_stack(cols)


def samples(n, n_vars, seed=0):
    return np.random.default_rng(seed).uniform(-1.4, 1.4, size=(n, n_vars))


JIT_MODES = [False, pytest.param(True, marks=pytest.mark.skipif(not HAS_COMPILER, reason="no C compiler"))]


@pytest.mark.parametrize("jit", JIT_MODES)
@pytest.mark.parametrize("states", [(X1, X2), (X1, X2, X3)], ids=["2 states", "3 states"])
@pytest.mark.parametrize("n", [1, 37, 64, 200, 257], ids=lambda n: f"N={n}")
def test_eq21_degree3_equals_numpy_on_chunk_boundaries(states, jit, n):
    library = paper(states, (F,), degree=3)
    ev = Evaluator(library, chunk_size=64, jit=jit)
    assert ev.is_compiled is jit and ev.n_terms == len(library)
    Z = samples(n, len(states) + 1, seed=n)
    D = ev.evaluate(Z)
    assert D.shape == (n, len(library)) and D.dtype == np.float64 and D.flags.c_contiguous
    np.testing.assert_allclose(D, numpy_reference(library, Z), rtol=1e-12, atol=0)


@pytest.mark.parametrize("parallel", ["serial", "thread"])
def test_iter_chunks_and_out_agree_with_evaluate(parallel):
    library = paper((X1, X2), (F,), degree=3)
    ev = Evaluator(library, chunk_size=50, jit=False, parallel=parallel)
    Z = samples(173, 3, seed=5)
    expected = numpy_reference(library, Z)
    chunks = list(ev.iter_chunks(Z))
    assert [c[0] for c in chunks] == [slice(0, 50), slice(50, 100), slice(100, 150), slice(150, 173)]
    np.testing.assert_allclose(np.vstack([d for _, d in chunks]), expected, rtol=1e-12, atol=0)
    out = np.full((173, len(library)), np.nan)
    assert ev.evaluate(Z, out=out) is out
    np.testing.assert_allclose(out, expected, rtol=1e-12, atol=0)


def test_empty_and_fortran_or_integer_input():
    library = polynomial((X1, X2), 2)
    ev = Evaluator(library, chunk_size=16, jit=False)
    assert ev.evaluate(np.empty((0, 2))).shape == (0, 6)
    Z = np.asfortranarray(np.arange(40, dtype=np.int64).reshape(20, 2) - 15)
    np.testing.assert_array_equal(ev.evaluate(Z), polynomial_reference(Z.astype(float), 2))


@pytest.mark.skipif(not HAS_COMPILER, reason="no C compiler")
def test_compiled_functions_are_cached_per_library():
    a = Evaluator(paper((X1, X2), (F,), degree=2), chunk_size=32)
    b = Evaluator(paper((X1, X2), (F,), degree=2), chunk_size=32)  # an equal library built again
    assert a.is_compiled and a._mapped is b._mapped


def test_auto_falls_back_without_compiler_and_true_requires_one(monkeypatch):
    monkeypatch.setattr(jit_module, "compiler", lambda: None)
    evaluator_module._compile.cache_clear()
    library = polynomial((X1,), 4)
    ev = Evaluator(library, chunk_size=8)
    assert not ev.is_compiled
    z = samples(19, 1)
    np.testing.assert_allclose(ev.evaluate(z), polynomial_reference(z, 4), rtol=1e-12, atol=0)
    with pytest.raises(
        LibraryError,
        match=r"jit: expected a C compiler \(gcc or cc on PATH\) for jit=True, "
        r"received none found; install gcc or pass jit='auto'",
    ):
        Evaluator(library, jit=True)
    evaluator_module._compile.cache_clear()


@settings(max_examples=25, deadline=None)
@given(
    n_vars=st.integers(1, 3),
    degree=st.integers(0, 4),
    n=st.integers(1, 70),
    chunk=st.integers(1, 32),
    seed=st.integers(0, 2**16),
)
def test_random_polynomials_equal_numpy_products(n_vars, degree, n, chunk, seed):
    variables = (X1, X2, X3)[:n_vars]
    ev = Evaluator(polynomial(variables, degree), chunk_size=chunk, jit=False)
    Z = samples(n, n_vars, seed)
    np.testing.assert_allclose(ev.evaluate(Z), polynomial_reference(Z, degree), rtol=1e-12, atol=1e-300)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(chunk_size=0), exactly("chunk_size: expected an integer >= 1, received 0")),
        (dict(jit="yes"), exactly("jit: expected one of 'auto', True, False, received 'yes'")),
        (dict(parallel="openmp"), exactly("parallel: expected one of 'serial', 'thread', received 'openmp'")),
    ],
)
def test_constructor_errors(kwargs, match):
    with pytest.raises(LibraryError, match=match):
        Evaluator(polynomial((X1,), 1), **kwargs)


def test_library_errors():
    with pytest.raises(LibraryError, match=r"library: expected a symsbl Library, received list"):
        Evaluator([X1])
    with pytest.raises(LibraryError, match=r"library: expected at least one term, received an empty library"):
        Evaluator(polynomial((X1,), 1).drop(["1", "x1"]))


def test_data_shape_errors_name_the_variables():
    ev = Evaluator(paper((X1, X2), (F,), degree=1), chunk_size=8, jit=False)
    with pytest.raises(
        LibraryError,
        match=r"Z: expected shape \(n_samples, 3\) with columns \['x1', 'x2', 'F'\], received shape "
        r"\(10, 2\)",
    ):
        ev.evaluate(np.zeros((10, 2)))
    with pytest.raises(LibraryError, match=r"received shape \(3,\); pass one column per variable"):
        ev.evaluate(np.zeros(3))
    with pytest.raises(LibraryError, match=r"received shape \(2, 2, 3\)"):
        list(ev.iter_chunks(np.zeros((2, 2, 3))))
    with pytest.raises(LibraryError, match=r"Z: expected a numeric array of shape \(n_samples, 3\)"):
        ev.evaluate([["a", "b", "c"]])
    with pytest.raises(
        LibraryError,
        match=r"out: expected a writeable C-contiguous float64 array of shape \(4, 14\), "
        r"received float64 array of shape \(5, 4\)",
    ):
        ev.evaluate(np.zeros((4, 3)), out=np.zeros((5, 4)))
    with pytest.raises(LibraryError, match=r"out: .* received float32 array of shape \(4, 14\)"):
        ev.evaluate(np.zeros((4, 3)), out=np.zeros((4, 14), np.float32))
    single = Evaluator(polynomial((X1,), 2), jit=False)
    with pytest.raises(LibraryError, match=r"reshape a single column with Z.reshape\(-1, 1\)"):
        single.evaluate(np.zeros(5))


def test_compile_failure_falls_back_silently_unless_jit_is_required(monkeypatch):
    monkeypatch.setattr(jit_module, "compiler", lambda: "/nonexistent/compiler")
    monkeypatch.setattr(jit_module, "_MEMORY", OrderedDict())
    evaluator_module._compile.cache_clear()
    library = polynomial((X1, X2), 2)
    ev = Evaluator(library, chunk_size=8)
    assert not ev.is_compiled
    z = samples(11, 2)
    np.testing.assert_allclose(ev.evaluate(z), polynomial_reference(z, 2), rtol=1e-12, atol=0)
    with pytest.raises(
        LibraryError,
        match=r"jit: expected a successful compilation for jit=True, received .+; "
        r"pass jit='auto'",
    ):
        Evaluator(library, jit=True)
    evaluator_module._compile.cache_clear()


def test_thread_chunk_size_is_rounded_to_the_two_workers():
    ev = Evaluator(polynomial((X1,), 3), chunk_size=7, jit=False, parallel="thread")
    assert ev.chunk_size == 8
    z = samples(21, 1)
    assert [rows for rows, _ in ev.iter_chunks(z)] == [slice(0, 8), slice(8, 16), slice(16, 21)]
    np.testing.assert_allclose(ev.evaluate(z), polynomial_reference(z, 3), rtol=1e-12, atol=0)
