"""Helpers shared by the benchmark scripts: best-of timing and Markdown tables."""

import time

import numpy as np


def timed(fn, repeats=3):
    """Run ``fn`` ``repeats`` times; return its last result and the best wall time (s)."""
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best


def table(title, header, rows):
    """Print ``rows`` as a Markdown table under ``title``."""
    print(f"\n{title}\n")
    print("| " + " | ".join(header) + " |")
    print("|" + "|".join("---" for _ in header) + "|")
    for r in rows:
        print("| " + " | ".join(str(c) for c in r) + " |")
