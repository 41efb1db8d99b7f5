"""Benchmark and recovery study of symsbl.RVM.

Problem: x ~ U[-1, 1]^3, all 84 monomials of degree <= 6 (with the constant), five true terms
x, y, xz, x^3, yz^2 with weights 1, -0.5, 2, -1.5, 0.8 and Gaussian noise of 1 % of std(signal).

The speed study times every competitor in turn in one process (best of 5) and prints the ratio
to ``ARDRegression(fit_intercept=False)`` and each time in passes over X, the unit being the
floor: one pass, ``X^T y``. It also measures the alternative ``fit`` does not use, Gram columns
computed on demand for the terms that enter (the sequential algorithm reads no others), in
batches and with the entering set known in advance (that approach's bound).

    python bench/bench_rvm.py               # speed against sklearn ARDRegression, N = 2e5, one BLAS thread
    python bench/bench_rvm.py --threads     # the same with the BLAS libraries' default threads
    python bench/bench_rvm.py --recovery    # false positives over 20 seeds vs prune_nats
    python bench/bench_rvm.py --detection   # smallest detectable term vs prune_nats
"""

from __future__ import annotations

import argparse
import itertools

import numpy as np
from _report import one_blas_thread, table, timed_together, write_page  # noqa: E402  (bench/ is on sys.path when run as a script)

from symsbl import RVM, GramStats
from symsbl._regression.sbl import DenseGram

TRUE_TERMS = {(0,): 1.0, (1,): -0.5, (0, 2): 2.0, (0, 0, 0): -1.5, (1, 2, 2): 0.8}
MONOMIALS = [c for deg in range(7) for c in itertools.combinations_with_replacement(range(3), deg)]
TRUE_SUPPORT = sorted(MONOMIALS.index(k) for k in TRUE_TERMS)


def problem(n, seed, noise=0.01, extra=None):
    """Dictionary (n, 84), noisy target and true weights; ``extra = (monomial, weight)``."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1.0, 1.0, (n, 3))
    D = np.ones((n, len(MONOMIALS)))
    for j, mono in enumerate(MONOMIALS):
        for v in mono:
            D[:, j] *= x[:, v]
    w = np.zeros(len(MONOMIALS))
    for mono, value in TRUE_TERMS.items():
        w[MONOMIALS.index(mono)] = value
    if extra is not None:
        w[MONOMIALS.index(extra[0])] = extra[1]
    signal = D @ w
    y = signal + noise * signal.std() * rng.standard_normal(n)
    return D, y, w


class ColumnsOnDemand:
    """The alternative to the full Gram that ``fit(X, y)`` does *not* use, kept here to measure it.

    A column source for the solver (``symsbl._regression.sbl.DenseGram``'s protocol): one pass over ``D``
    for ``D^T y`` and the column norms, then each Gram column the solver first asks for, with
    the ``batch - 1`` columns it ranks most likely next, in one pass over ``D`` (block by block,
    OpenBLAS's small-matrix kernel). ``first`` is fetched in the first pass (the bound: the
    entering columns known in advance).
    """

    def __init__(self, D, d2, scale, batch=16, first=()):
        self.D, self.scale, self.batch, self.first = D, scale, batch, list(first)
        self.diag = d2 / scale**2
        self.store = np.empty((len(d2), len(d2)))
        self.have = np.zeros(len(d2), dtype=bool)
        self.passes = 0

    def columns(self, idx, priority=None):
        missing = [i for i in idx if not self.have[i]]
        if missing:
            want = list(dict.fromkeys(missing + self.first))
            self.first = []
            if priority is not None:
                extra = [int(i) for i in np.argsort(-priority, kind="stable") if not self.have[i] and i not in want]
                want += extra[: max(self.batch - len(want), 0)]
            self.passes += 1
            block = cross(self.D, np.array(want)) / np.outer(self.scale, self.scale[want])
            self.store[:, want] = block
            self.store[want, want] = self.diag[want]
            self.have[want] = True
        return self.store[:, idx]


def block_rows(M):
    return max(256, (1 << 18) // (8 * M))


def moments(D, y):
    """``D^T y`` and the squared column norms in one pass, block by block."""
    dty, d2, step = np.zeros(D.shape[1]), np.zeros(D.shape[1]), block_rows(D.shape[1])
    for start in range(0, len(D), step):
        block = D[start : start + step]
        dty += y[start : start + step] @ block
        d2 += np.einsum("ij,ij->j", block, block)
    return dty, d2


def cross(D, cols):
    """``D^T D[:, cols]`` in one pass, block by block."""
    out, part, step = np.zeros((D.shape[1], len(cols))), np.empty((D.shape[1], len(cols))), block_rows(D.shape[1])
    for start in range(0, len(D), step):
        block = D[start : start + step]
        np.matmul(block.T, block[:, cols], out=part)
        out += part
    return out


def on_demand(D, y, batch=16, first=()):
    """``RVM().fit(D, y)`` with Gram columns computed on demand; returns the fit and the source."""
    dty, d2 = moments(D, y)
    scale = np.sqrt(d2)
    source = ColumnsOnDemand(D, d2, scale, batch, first)
    rvm = RVM()._fit(source, scale, dty, float(y @ y), float(y.sum()), float(len(y)))
    return rvm, source


class Recorder(DenseGram):
    """A full Gram that records which columns the solver reads."""

    def __init__(self, matrix):
        super().__init__(matrix)
        self.read = []

    def columns(self, idx, priority=None):
        self.read += [int(i) for i in idx if int(i) not in self.read]
        return super().columns(idx, priority)


def entering_columns(D, y):
    """The columns the solver reads (every term that enters at some point), in order."""
    stats = GramStats.from_arrays(D, y)
    scale = np.sqrt(np.diag(stats.gram))
    source = Recorder(stats.gram / np.outer(scale, scale))
    RVM()._fit(source, scale, stats.dty[:, 0], float(stats.yty[0]), float(stats.y_sum[0]), float(len(y)))
    return source.read


def scipy_syrk(D):
    """``D^T D`` by scipy's own BLAS (a second OpenBLAS beside numpy's), symmetrised."""
    from scipy.linalg.blas import dsyrk

    gram = dsyrk(1.0, D.T, trans=0) if D.flags.c_contiguous else dsyrk(1.0, D, trans=1)
    lower = np.tril_indices(len(gram), -1)
    gram[lower] = gram.T[lower]
    return gram


def speed(n=200_000, seed=0, repeats=5):
    from sklearn.linear_model import ARDRegression

    D, y, w = problem(n, seed)
    D_copy = D.copy()
    stats = GramStats.from_arrays(D, y)
    entering = entering_columns(D, y)

    def before():
        return RVM().fit_stats(GramStats(D.T @ D, (D.T @ y)[:, None], np.array([y @ y]), np.array([y.sum()]), n))

    runs = timed_together(
        {
            "one pass over X: X^T y (the floor)": lambda: D.T @ y,
            "Gram, general product (gemm) on a copy of X": lambda: D.T @ D_copy,
            "Gram: numpy D.T @ D (numpy calls dsyrk)": lambda: D.T @ D,
            "Gram: scipy.linalg.blas.dsyrk, symmetrised": lambda: scipy_syrk(D),
            "GramStats.from_arrays (dsyrk + X^T y, one pass)": lambda: GramStats.from_arrays(D, y),
            "solve (default ebic)": lambda: RVM().fit_stats(stats),
            "solve, prune_nats=None": lambda: RVM(prune_nats=None).fit_stats(stats),
            "fit(X, y) end to end as before (D.T @ D, D.T @ y)": before,
            "fit(X, y) end to end": lambda: RVM().fit(D, y),
            "columns on demand, batches of 16 (not used)": lambda: on_demand(D, y)[0],
            "columns on demand, entering set known (its bound)": lambda: on_demand(D, y, first=entering)[0],
            "sklearn ARDRegression(fit_intercept=False)": lambda: ARDRegression(fit_intercept=False).fit(D, y),
        },
        repeats,
    )
    floor = runs["one pass over X: X^T y (the floor)"][1]
    true = np.flatnonzero(w)
    rows = []
    for name, (out, seconds) in runs.items():
        cells = ["", "", "", ""]
        if hasattr(out, "coef_"):
            support = np.flatnonzero(out.coef_)
            cells = [
                len(support),
                len(set(support) - set(true)),
                len(set(true) - set(support)),
                f"{np.max(np.abs(out.coef_ - w)):.2e}",
            ]
        rows.append([name, f"{seconds * 1e3:.1f}", f"{seconds / floor:.1f}"] + cells)
    print(f"N = {n}, M = {D.shape[1]}, 5 true terms, 1 % noise, seed {seed}; best of {repeats}, interleaved")
    table(
        "symsbl.RVM against ARDRegression",
        ["", "time (ms)", "in passes over X", "terms", "FP", "FN", "max|w-w*|"],
        rows,
    )
    t_fit, t_ard = runs["fit(X, y) end to end"][1], runs["sklearn ARDRegression(fit_intercept=False)"][1]
    t_solve = runs["solve (default ebic)"][1]
    _, source = on_demand(D, y)
    print(
        f"\nend to end: {t_ard / t_fit:.1f}x faster than ARDRegression "
        f"(as before: {t_ard / runs['fit(X, y) end to end as before (D.T @ D, D.T @ y)'][1]:.1f}x; "
        f"solve alone: {t_ard / t_solve:.0f}x)"
    )
    print(
        f"one-pass floor {floor * 1e3:.1f} ms: fit(X, y) takes {t_fit / floor:.1f} passes' worth "
        f"(the floor is {100 * floor / t_fit:.0f} % of it); ARD at 10x would need {t_ard / 10 * 1e3:.0f} ms"
    )
    print(
        f"columns that enter the model at some point: {len(entering)} of {D.shape[1]} "
        f"({entering}); on demand in batches of 16: {source.passes} passes + 1 for X^T y"
    )


def recovery(seeds=range(20), sizes=(20_000, 200_000)):
    rules = [None, 3.0, 4.0, "bic", 6.0, "ebic"]
    print("spurious terms per fit (mean) / fits with exact support, 20 seeds")
    print("| N | " + " | ".join(str(r) for r in rules) + " |")
    print("|---|" + "---|" * len(rules))
    for n in sizes:
        fp = {r: [] for r in rules}
        exact = {r: 0 for r in rules}
        for seed in seeds:
            D, y, w = problem(n, seed)
            stats = GramStats.from_arrays(D, y)
            for r in rules:
                model = RVM(prune_nats=r).fit_stats(stats)
                fp[r].append(len(set(model.active_) - set(TRUE_SUPPORT)))
                exact[r] += list(model.active_) == TRUE_SUPPORT
        cells = [f"{np.mean(fp[r]):.2f} / {exact[r]}" for r in rules]
        print(f"| {n} | " + " | ".join(cells) + " |")


def detection(n=30_000, seeds=range(10)):
    """Detection rate of a sixth term x^2 y whose projected SNR z is set, vs prune_nats."""
    mono = (0, 0, 1)
    rules = [None, 3.0, "bic", 6.0, "ebic"]
    print(f"N = {n}: detection rate of an extra term with projected SNR z, 10 seeds")
    print("| z | " + " | ".join(str(r) for r in rules) + " |")
    print("|---|" + "---|" * len(rules))
    D, _, _ = problem(n, 0)
    j = MONOMIALS.index(mono)
    others = D[:, TRUE_SUPPORT]
    resid = D[:, j] - others @ np.linalg.lstsq(others, D[:, j], rcond=None)[0]
    for z in (2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0):
        hits = {r: 0 for r in rules}
        for seed in seeds:
            D, y0, w = problem(n, seed, noise=0.0)
            sigma = 0.01 * y0.std()
            weight = z * sigma / np.linalg.norm(resid)
            rng = np.random.default_rng(1000 + seed)
            y = y0 + weight * D[:, j] + sigma * rng.standard_normal(n)
            stats = GramStats.from_arrays(D, y)
            for r in rules:
                hits[r] += j in RVM(prune_nats=r).fit_stats(stats).active_
        print(f"| {z:g} | " + " | ".join(f"{hits[r] / len(seeds):.1f}" for r in rules) + " |")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recovery", action="store_true")
    parser.add_argument("--detection", action="store_true")
    parser.add_argument("--threads", action="store_true", help="keep the BLAS libraries' default threads")
    args = parser.parse_args()
    if args.recovery:
        recovery()
    elif args.detection:
        detection()
    elif args.threads:
        speed()
    else:
        with one_blas_thread():
            speed()
    write_page(
        "rvm-"
        + (
            "recovery"
            if args.recovery
            else "detection"
            if args.detection
            else "speed-threads"
            if args.threads
            else "speed"
        ),
        __doc__,
    )
