"""Benchmark and recovery study of symsbl.RVM.

Problem: x ~ U[-1, 1]^3, all 84 monomials of degree <= 6 (with the constant), five true terms
x, y, xz, x^3, yz^2 with weights 1, -0.5, 2, -1.5, 0.8 and Gaussian noise of 1 % of std(signal).

    python bench/bench_rvm.py               # speed against sklearn ARDRegression, N = 2e5
    python bench/bench_rvm.py --recovery    # false positives over 20 seeds vs prune_nats
    python bench/bench_rvm.py --detection   # smallest detectable term vs prune_nats
"""

from __future__ import annotations

import argparse
import itertools
import time

import numpy as np

from symsbl import RVM, GramStats

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


def best_of(fn, repeat=5):
    times, out = [], None
    for _ in range(repeat):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return min(times), out


def speed(n=200_000, seed=0):
    from sklearn.linear_model import ARDRegression

    D, y, w = problem(n, seed)
    t_gram, stats = best_of(lambda: GramStats.from_arrays(D, y))
    t_solve, rvm = best_of(lambda: RVM().fit_stats(stats))
    t_total, _ = best_of(lambda: RVM().fit(D, y))
    t_plain, plain = best_of(lambda: RVM(prune_nats=None).fit_stats(stats))
    t_ard, ard = best_of(lambda: ARDRegression(fit_intercept=False).fit(D, y), repeat=3)
    ard_support = np.flatnonzero(ard.coef_)
    true = np.flatnonzero(w)

    def row(name, seconds, support, coef):
        fp = len(set(support) - set(true))
        fn = len(set(true) - set(support))
        err = np.max(np.abs(coef - w))
        print(f"| {name:42s} | {seconds * 1e3:9.1f} | {len(support):5d} | {fp:3d} | {fn:3d} | {err:9.2e} |")

    print(f"N = {n}, M = {D.shape[1]}, 5 true terms, 1 % noise, seed {seed}")
    print(f"| {'method':42s} | time (ms) | terms |  FP |  FN | max|w-w*| |")
    print(f"|{'-' * 44}|-----------|-------|-----|-----|-----------|")
    row("symsbl RVM: Gram build", t_gram, rvm.active_, rvm.coef_)
    row("symsbl RVM: solve (default ebic)", t_solve, rvm.active_, rvm.coef_)
    row("symsbl RVM: fit(X, y) end to end", t_total, rvm.active_, rvm.coef_)
    row("symsbl RVM: solve, prune_nats=None", t_plain, plain.active_, plain.coef_)
    row("sklearn ARDRegression(fit_intercept=False)", t_ard, ard_support, ard.coef_)
    print(f"end-to-end speed-up over ARDRegression: {t_ard / t_total:.1f}x "
          f"(solve alone: {t_ard / t_solve:.0f}x)")


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
    args = parser.parse_args()
    if args.recovery:
        recovery()
    elif args.detection:
        detection()
    else:
        speed()
