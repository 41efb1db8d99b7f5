"""Helpers shared by the benchmark scripts: the one timer and Markdown tables.

Every script times through :func:`timed` (one function) or :func:`timed_together` (several
competitors run in turn, so that a change of machine load hits all of them alike; use it for
ratios). The machine these run on is shared: report ratios measured in one process, with the
best of several repeats (``statistic="min"``) unless the spread itself matters.
"""

import contextlib
import statistics
import time

_STATISTICS = {"min": min, "median": statistics.median}


def timed(fn, repeats=3, *, warmup=False, statistic="min"):
    """Run ``fn`` ``repeats`` times; return its last result and the best (or median) wall time (s).

    ``warmup`` runs it once more first, untimed (page faults, JIT compilation, caches)."""
    if warmup:
        fn()
    out, times = None, []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, _STATISTICS[statistic](times)


def timed_together(fns, repeats=5, *, warmup=True, statistic="min"):
    """Time several competitors in turn, round-robin; return ``{name: (last result, seconds)}``.

    ``fns`` maps names to zero-argument callables. Interleaving makes ratios robust to the
    load of a shared machine changing during the run."""
    if warmup:
        for fn in fns.values():
            fn()
    out = {name: None for name in fns}
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            out[name] = fn()
            times[name].append(time.perf_counter() - t0)
    return {name: (out[name], _STATISTICS[statistic](times[name])) for name in fns}


def table(title, header, rows):
    """Print ``rows`` as a Markdown table under ``title``."""
    print(f"\n{title}\n")
    print("| " + " | ".join(header) + " |")
    print("|" + "|".join("---" for _ in header) + "|")
    for r in rows:
        print("| " + " | ".join(str(c) for c in r) + " |")


def one_blas_thread():
    """A context limiting every BLAS library in the process to one thread (the setting of the
    README's figures). numpy and scipy each ship their own OpenBLAS; on a machine with few
    cores, code that alternates between them (pysindy, scikit-learn) can run 50x slower with
    their default threads, as each library's idle threads spin while the other works.
    Without threadpoolctl (installed with scikit-learn) it does nothing."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")

