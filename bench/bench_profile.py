"""Where the time of ``identify`` goes, from 1e4 to 1e7 samples.

Data: the Duffing oscillator of :func:`symsbl.systems.duffing` (x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F)
driven by a random-phase multisine (60 N rms, 2-30 Hz), simulated by RK4 at 32768 Hz in pieces of
2^20 samples (the state carried over), 1 % noise, written once to an uncompressed ``.npz``. Library:
the paper's Eq. 21 of degree 3 (34 terms). Each size runs the default identification of a record
on disk, ``identify_stream(open_npz(path, stop=N), library)`` (weak form, RVM, support search,
output-error refinement on at most 2^18 samples as evenly spaced windows), once after a warm-up
that compiles the dictionary and the refinement passes.

Stages are timed by wrapping the functions that do them (wall time, inclusive):

- reading and derivatives: the rest of the statistics pass (memory-mapped reads, weak-form
  reduction of the targets and the dictionary);
- dictionary: :meth:`symsbl.Evaluator.evaluate` (the compiled candidate terms);
- Gram: the symmetric rank-k update of the regression rows (``symsbl._regression.gram._products``);
- RVM: the first sparse Bayesian fit of each equation;
- support search: the evidence-guided local search and parsimony after it;
- refinement: reading the windows and :func:`symsbl.refine` with its term selection.

Run: ``PYTHONPATH=. python bench/bench_profile.py [--sizes 1e4,1e5,1e6,1e7]``.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import tempfile
import time
from pathlib import Path

import numpy as np
from _report import one_blas_thread, table, write_page  # noqa: E402  (bench/ is on sys.path when run as a script)

import symsbl
from symsbl import Multisine, identify_stream, open_npz, paper, simulate, symbols, systems
from symsbl._regression import fit as _fit
from symsbl._regression import gram as _gram
from symsbl._scale import stream
from symsbl._symbolic import evaluator as _evaluator

FS = 32768
PIECE = 2**20
X1, X2, F = symbols("x1 x2 F")
LIB = paper([X1, X2], [F], degree=3)
NAMES = dict(states=("x1", "x2"), inputs=("F",))


def write_record(directory: Path, n: int) -> Path:
    """``n`` samples of the noisy Duffing, simulated piece by piece, as columns t, x1, x2, F."""
    rng = np.random.default_rng(0)
    signal = Multisine(rms=60.0, f_min=2.0, f_max=30.0, seed=1)
    t_all = np.arange(n) / FS
    x0 = np.zeros(2)
    states, forces = [], []
    for a in range(0, n, PIECE):
        t = t_all[a : min(n, a + PIECE + 1)]
        piece = simulate(systems.duffing(), t, inputs=signal, x0=x0, method="rk4")
        x0 = piece.states[-1]
        keep = slice(0, min(PIECE, n - a))
        states.append(piece.states[keep])
        forces.append(piece.inputs[keep, 0])
    X = np.concatenate(states)
    X = X + 0.01 * X.std(axis=0) * rng.standard_normal(X.shape)
    path = directory / "duffing.npz"
    np.savez(path, t=t_all, x1=X[:, 0], x2=X[:, 1], F=np.concatenate(forces))
    return path


class Clock:
    """Inclusive wall time spent in wrapped functions, by stage."""

    def __init__(self):
        self.seconds = {}

    def wrap(self, owner, name, stage):
        original = getattr(owner, name)

        @functools.wraps(original)
        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                self.seconds[stage] = self.seconds.get(stage, 0.0) + time.perf_counter() - t0

        setattr(owner, name, timed)
        return original


@contextlib.contextmanager
def instrumented(clock: Clock):
    targets = [
        (_evaluator.Evaluator, "evaluate", "dictionary"),
        (_gram, "_products", "Gram"),
        (_fit, "fit_rvm", "RVM"),
        (_fit, "search_support", "support search"),
        (stream, "_stream_stats", "statistics"),
        (stream, "refine_or_keep", "refinement"),
    ]
    originals = [(owner, name, clock.wrap(owner, name, stage)) for owner, name, stage in targets]
    try:
        yield
    finally:
        for owner, name, original in originals:
            setattr(owner, name, original)


def profile(path: Path, n: int) -> list:
    clock = Clock()
    with instrumented(clock):
        t0 = time.perf_counter()
        model = identify_stream(open_npz(path, **NAMES, stop=n), LIB)
        total = time.perf_counter() - t0
    s = clock.seconds
    stats = s.get("statistics", 0.0)
    reading = stats - s.get("dictionary", 0.0) - s.get("Gram", 0.0)
    found = ", ".join(model.equation("x2").names)
    cells = [
        reading,
        s.get("dictionary", 0.0),
        s.get("Gram", 0.0),
        s.get("RVM", 0.0),
        s.get("support search", 0.0),
        s.get("refinement", 0.0),
    ]
    return [f"{n:.0e}"] + [f"{c:.2f}" for c in cells] + [f"{total:.2f}", model.fit.value, found]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="1e4,1e5,1e6,1e7")
    args = parser.parse_args()
    sizes = [int(float(s)) for s in args.sizes.split(",")]
    symsbl.set_progress(False)
    with tempfile.TemporaryDirectory() as tmp, one_blas_thread():
        path = write_record(Path(tmp), max(sizes))
        identify_stream(open_npz(path, **NAMES, stop=min(sizes)), LIB)  # warm-up: compile
        rows = [profile(path, n) for n in sizes]
    table(
        "identify_stream end to end: seconds per stage (Duffing, 32768 Hz, Eq. 21 degree 3, 34 terms)",
        [
            "N",
            "reading + derivatives",
            "dictionary",
            "Gram",
            "RVM",
            "support search",
            "refinement",
            "total",
            "fit",
            "x2' terms",
        ],
        rows,
    )
    write_page("profile", __doc__)


if __name__ == "__main__":
    main()
