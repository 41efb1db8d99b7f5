"""The support search: a move's supports fitted in lockstep against one by one.

The equation error's support search (``symsbl/_regression/support.py``) scores every support it tries by
refitting the RVM on that support's columns. Each move tries tens of supports; since they are small, each
refit is numpy's per-call cost many times over. The lockstep solver (``symsbl/_regression/lockstep.py``)
fits all of a move's supports side by side, each along its own path.

The searches are those ``identify`` runs on the demo's five systems (``symsbl demo``'s records,
``refine=False``) and on the chains of 2, 5 and 10 masses of the page *mdof-positions* (positions only,
``bench/bench_mdof.py``). Each is recorded once (its inputs), then replayed in one process with the moves
scored in lockstep and one by one (``SupportSearch.score_all`` switched off), in turn, best of 3 (wall
time), one BLAS thread. The multi-start's first fits, the parsimony phase and the final refit run one by one
in both. Per case: the time of the searches, the ratio, and whether every search ended with the same
support, look-alikes, number of supports scored and final coefficients (bit for bit; the final fit is the
support's own in both).

Run: ``PYTHONPATH=. python bench/bench_search.py [--sizes 2,5,10]``.
"""

from __future__ import annotations

import argparse

import numpy as np
from _report import one_blas_thread, table, timed_together, write_page  # noqa: E402  (bench/ is on sys.path)

import symsbl
import symsbl._regression.fit as _fit
import symsbl._regression.support as _support
from symsbl import _demo


def record(run) -> list[tuple]:
    """The inputs of every support search that ``run()`` makes."""
    calls, original = [], _support.search_support

    def recorder(*args):
        calls.append(args)
        return original(*args)

    _fit.search_support = recorder
    try:
        run()
    finally:
        _fit.search_support = original
    return calls


def demo_searches() -> list[tuple]:
    return record(lambda: [_demo.run_case(name, refine=False) for name in _demo.CASES])


def chain_searches(n: int) -> list[tuple]:
    import bench_mdof

    system, record_, naming, _ = bench_mdof.observed(n, "positions")
    library = symsbl.polynomial(list(system.states), 3) + symsbl.inputs(list(system.inputs))
    return record(lambda: symsbl.identify(record_, library, refine=False, **naming))


def replay(calls, lockstep: bool) -> list[tuple]:
    """Every recorded search run again; its support, look-alikes, kept columns, coefficients and size."""
    lock = _support.SupportSearch.score_all
    if not lockstep:
        _support.SupportSearch.score_all = lambda self, trials: None
    try:
        out = []
        for first, stats, target, keys, template, tol in calls:
            active, alternatives, search = _support.search_support(first, stats, target, keys, template, tol)
            _, kept, fit = search.score(active, own=True)
            out.append((active, alternatives, kept, fit.coef_.copy(), len(search.cache)))
        return out
    finally:
        _support.SupportSearch.score_all = lock


def same(one, other) -> bool:
    return all(a[:3] == b[:3] and np.array_equal(a[3], b[3]) and a[4] == b[4] for a, b in zip(one, other, strict=True))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="2,5,10", help="chain sizes (masses), comma-separated")
    args = parser.parse_args()
    cases = [("demo (5 systems)", demo_searches)]
    cases += [(f"chain of {n} masses, positions", lambda n=int(n): chain_searches(n)) for n in args.sizes.split(",")]
    rows = []
    with one_blas_thread():
        for name, searches in cases:
            calls = searches()
            timed = timed_together(
                {"lockstep": lambda c=calls: replay(c, True), "one by one": lambda c=calls: replay(c, False)},
                repeats=3,
                warmup=False,
            )
            lock_out, t_lock = timed["lockstep"]
            alone_out, t_alone = timed["one by one"]
            scored = sum(r[4] for r in alone_out)
            rows.append(
                (
                    name,
                    len(calls),
                    scored,
                    f"{t_alone:.2f} s",
                    f"{t_lock:.2f} s",
                    f"{t_alone / t_lock:.1f}x",
                    "yes" if same(lock_out, alone_out) else "NO",
                )
            )
            print(f"{name}: {t_alone:.2f} s -> {t_lock:.2f} s", flush=True)
    table(
        "### Support searches, one by one and in lockstep",
        ["case", "searches", "supports scored", "one by one", "lockstep", "ratio", "same outcome"],
        rows,
    )
    write_page("search", __doc__)


if __name__ == "__main__":
    main()
