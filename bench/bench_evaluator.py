"""Throughput of the compiled evaluator on the Eq. (21) dictionary against numpy, sympy and pysindy.

Run: ``python bench/bench_evaluator.py`` (symsbl installed, or ``PYTHONPATH=.``; about a minute and a half,
< 4 GB). For each case it prints the median time of a few repeats after one warm-up call, the throughput in samples x
terms per second, the time relative to symsbl (JIT, serial) and relative to ``np.copyto`` of
an array of the output's size (the memory-bandwidth limit). Every method's result is checked
against symsbl's before it is timed.
"""

from __future__ import annotations

import functools
import itertools
import os
import sys
import time

import numpy as np
import sympy as sp

from symsbl import Evaluator, paper, polynomial, symbols

sys.path.insert(0, os.path.dirname(__file__))
from _report import table, timed, write_page  # noqa: E402  (bench/ is on sys.path when run as a script)

N = 1_000_000
REPEATS = 3
CHECK = 20_000  # rows on which every method is compared with symsbl before timing
CASES = [(2, 3), (2, 6), (3, 3)]  # (n_states, degree), with one input F


def median_time(fn, repeats=REPEATS, warmup=True) -> float:
    """Median wall time of ``fn`` (the shared timer; the warm-up run takes page faults of first use)."""
    return timed(fn, repeats, warmup=warmup, statistic="median")[1]


def numpy_eq21(Z: np.ndarray, n_states: int, degree: int) -> np.ndarray:
    """Hand-written numpy for the de-duplicated Eq. (21) columns, in symsbl's order.

    Monomials of (x, |x|) are built recursively (parent column times one variable) into a
    Fortran-ordered array (contiguous columns); x^a |x|^c is skipped when a monomial with the
    same function, i.e. the same (a + c, a mod 2) per state, was already written.
    """
    X, u = Z[:, :n_states], Z[:, n_states]
    aug = np.asfortranarray(np.hstack([X, np.abs(X)]))
    keys: dict[tuple, int] = {}
    combos: list[tuple[int, ...]] = []
    for d in range(degree + 1):
        for combo in itertools.combinations_with_replacement(range(2 * n_states), d):
            key = tuple(
                (k, a % 2 if k else 0)
                for a, k in ((combo.count(i), combo.count(i) + combo.count(i + n_states)) for i in range(n_states))
            )
            if key not in keys:
                keys[key] = len(combos)
                combos.append(combo)
    M = 1 + len(combos) + 4 * n_states
    out = np.empty((len(Z), M), order="F")
    out[:, 0] = u
    index = {}
    for j, combo in enumerate(combos, start=1):
        index[combo] = j
        if not combo:
            out[:, j] = 1.0
        elif len(combo) == 1:
            out[:, j] = aug[:, combo[0]]
        else:
            np.multiply(out[:, index[combo[:-1]]], aug[:, combo[-1]], out=out[:, j])
    j = 1 + len(combos)
    for f in (np.sin, np.cos, np.tan, np.sign):
        for i in range(n_states):
            f(X[:, i], out=out[:, j])
            j += 1
    return out


def lambdified(library):
    syms = [sp.Symbol(n, real=True) for n in library.variable_names]
    f = sp.lambdify(syms, library.to_sympy(), "numpy", cse=True)

    def run(Z):
        cols = f(*Z.T)
        out = np.empty((len(Z), len(cols)))
        for j, c in enumerate(cols):
            out[:, j] = c
        return out

    return run


def pysindy_rows(n_states, degree, Z, rows):
    """pysindy's PolynomialLibrary on (x, |x|) against symsbl's polynomial of the same 2p inputs."""
    try:
        from pysindy import PolynomialLibrary
    except ImportError as err:
        print(f"  (pysindy rows skipped: {err}; pip install pysindy)")
        return
    aug = np.hstack([Z[:, :n_states], np.abs(Z[:, :n_states])])
    a = symbols(" ".join(f"a{i}" for i in range(2 * n_states)))
    ev = Evaluator(polynomial(a, degree), chunk_size=4096)
    lib = PolynomialLibrary(degree=degree).fit(aug)
    np.testing.assert_allclose(lib.transform(aug[:CHECK]), ev.evaluate(aug[:CHECK]), rtol=1e-12)
    out = np.empty((len(aug), len(ev.library)))
    rows.append(
        ("symsbl JIT, polynomial of (x,|x|) only", len(ev.library), median_time(lambda: ev.evaluate(aug, out=out)))
    )
    rows.append(
        (
            "pysindy PolynomialLibrary, same columns",
            len(ev.library),
            median_time(lambda: lib.transform(aug), 2, warmup=False),
        )
    )


def bench_case(n_states: int, degree: int) -> None:
    states = symbols(" ".join(f"x{i + 1}" for i in range(n_states)))
    (F,) = symbols("F")
    library = paper(states, (F,), degree=degree)
    M = len(library)
    Z = np.random.default_rng(0).uniform(-1.2, 1.2, size=(N, n_states + 1))
    t0 = time.perf_counter()
    jit = Evaluator(library, chunk_size=4096, jit="auto")
    compile_time = time.perf_counter() - t0
    out = np.empty((N, M))
    reference = jit.evaluate(Z[:CHECK])
    rows: list[tuple[str, int, float]] = []

    src = np.ones((N, M))
    dst = np.empty((N, M))
    t_copy = median_time(functools.partial(np.copyto, dst, src))  # not a lambda: the names are deleted next
    del src, dst

    t_jit = median_time(lambda: jit.evaluate(Z, out=out))
    rows.append((f"symsbl {'JIT' if jit.is_compiled else 'SX VM (no compiler)'}, serial", M, t_jit))
    thread = Evaluator(library, jit="auto", parallel="thread")
    rows.append(("symsbl JIT, map 'thread' (2)", M, median_time(lambda: thread.evaluate(Z, out=out))))
    vm = Evaluator(library, jit=False)
    rows.append(("symsbl SX virtual machine", M, median_time(lambda: vm.evaluate(Z, out=out))))
    np.testing.assert_allclose(out[:CHECK], reference, rtol=1e-12)

    np.testing.assert_allclose(numpy_eq21(Z[:CHECK], n_states, degree), reference, rtol=1e-12)
    rows.append(("numpy hand-written (F-order out)", M, median_time(lambda: numpy_eq21(Z, n_states, degree))))
    lam = lambdified(library)
    np.testing.assert_allclose(lam(Z[:CHECK]), reference, rtol=1e-12)
    rows.append(("sympy lambdify(numpy, cse=True)", M, median_time(lambda: lam(Z), 2, warmup=False)))
    pysindy_rows(n_states, degree, Z, rows)

    table(
        f"Eq. (21), {n_states} states + F, degree {degree}: M = {M} terms, N = {N:.0e}",
        ["method", "M", "time (ms)", "Gterm/s", "x symsbl", "x copy"],
        [
            [
                name,
                m,
                f"{t * 1e3:.1f}",
                f"{N * m / t / 1e9:.2f}",
                f"{t / t_jit * M / m:.2f}",
                f"{t / t_copy * M / m:.2f}",
            ]
            for name, m, t in rows
        ],
    )
    print(f"JIT compile {compile_time:.2f} s; np.copyto of N x M float64: {t_copy * 1e3:.1f} ms")


def main() -> None:
    print(
        "symsbl evaluator benchmark (median of a few repeats after warm-up). 'x symsbl' and 'x copy' are "
        "time ratios per term: > 1 means slower than symsbl JIT / than copying an output-sized array."
    )
    print(f"load average at start: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    for n_states, degree in CASES:
        bench_case(n_states, degree)
    write_page("evaluator", __doc__)


if __name__ == "__main__":
    main()
