"""Streaming regression statistics: records longer than memory, read and reduced chunk by chunk.

A *record* is one continuous, uniformly sampled experiment. It may be held in memory
(a :class:`~symsbl.data.Trajectory`), arrive as consecutive pieces
(:func:`~symsbl.records.chunked`: a list, a generator or a factory of chunks) or sit in an
``.npz`` file that is memory-mapped (:func:`~symsbl.records.open_npz`); :mod:`symsbl.records`
reads them, and they are also importable from here. :func:`stream_stats` turns any number of records into the same
:class:`~symsbl.identify.RegressionStats` that :func:`~symsbl.identify.regression_stats` builds
from the concatenated data, holding only one block of samples (``block_samples``) and one slab
of the dictionary (about ``chunk_size`` samples by ``n_terms``) at a time: memory depends on
the number of terms, not on the record's length.

Chunk boundaries
----------------
Samples are gathered into blocks. Every regression row needs a few neighbouring samples
(its *halo*), so each block starts with the samples the previous one could not finish:

- :class:`~symsbl.derivatives.WeakForm` rows are windows of ``window`` sample intervals
  aligned with the start of the record; a block ends at a window boundary and the samples from
  the last boundary on (the shared end sample and any incomplete window) are carried over.
- pointwise strategies (point, central, Savitzky-Golay) emit only the rows whose stencil lies
  inside the block, carry the stencil's width over, and use their one-sided end formulas only
  at the true start and end of the record.

Rows are therefore the rows of the whole record, computed in the same arithmetic, and the
statistics equal those of :func:`~symsbl.identify.regression_stats` up to the order in which
partial sums are added. A :class:`~symsbl.derivatives.WeakForm` without a window is resolved
once, from the first block of the first record (at most :data:`RESOLVE_SAMPLES` samples; the
whole record when it is shorter), and then stays fixed for every record.

Blocks are independent once their halo is attached, so ``n_jobs=2`` reduces two blocks at once
on two threads: the compiled dictionary evaluation and numpy's reductions release the GIL.
"""

from __future__ import annotations

from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np

from .data import Trajectory
from .derivatives import CentralDifference, PointDifference, SavitzkyGolay, WeakForm, get_differentiator
from .errors import DataError, LibraryError
from .evaluator import Evaluator
from .identify import RegressionStats, _check_variation, _columns, fit_stats
from .library import Library
from .model import IdentifiedModel
from .progress import Progress
from .records import BLOCK_SAMPLES, ChunkedRecord, _as_records, _blocks, _RecordReader, chunked, open_npz
from .rvm import RVM, GramStats

# ChunkedRecord, chunked and open_npz live in symsbl.records and stay importable from here.
__all__ = ["ChunkedRecord", "chunked", "open_npz", "stream_stats", "identify_stream"]

#: An automatic weak-form window is resolved from at most this many samples at the start of
#: the first record (shared with :mod:`symsbl.distributed`, so both resolve the same window).
RESOLVE_SAMPLES = 2**18


# ------------------------------------------------------------------------------------------- halos


@dataclass(frozen=True)
class _Halo:
    """Which rows a block of samples can produce and which samples carry over to the next block."""

    window: int  # weak form: samples per row step; 0 for pointwise strategies
    left: int
    right: int
    min_samples: int

    def rows(self, n: int, first: bool, last: bool) -> tuple[int, int]:
        if self.window:
            return 0, max((n - 1) // self.window, 0)
        return (0 if first else self.left), (n if last else n - self.right)

    def carry_from(self, row_stop: int) -> int:
        return row_stop * self.window if self.window else row_stop - self.left

    def sample_span(self, r0: int, r1: int) -> tuple[int, int]:
        return (r0 * self.window, r1 * self.window + 1) if self.window else (r0, r1)


#: The stencil of each strategy streaming knows about, by exact type (a subclass may change it).
_HALOS: dict[type, Callable[[object], _Halo]] = {
    WeakForm: lambda d: _Halo(d.window, 0, 0, d.window + 1),
    PointDifference: lambda d: _Halo(0, 0, 1, 2),
    CentralDifference: lambda d: _Halo(0, 1, 1, 3),
    SavitzkyGolay: lambda d: _Halo(0, d.window // 2, d.window // 2, d.window),
}


def _halo(diff) -> _Halo:
    try:
        return _HALOS[type(diff)](diff)
    except KeyError:
        raise DataError(
            "derivative: streaming needs to know the stencil of the strategy; expected one of "
            f"{sorted(t.__name__ for t in _HALOS)}, received {type(diff).__name__}. "
            "Use symsbl.regression_stats for in-memory data with other strategies."
        ) from None


# ------------------------------------------------------------------------------------------- blocks


@dataclass(frozen=True)
class _Block:
    X: np.ndarray  # (n, n_states)
    Z: np.ndarray  # (n, n_variables), library order
    r0: int
    r1: int


def _block_stats(block: _Block, diff, halo: _Halo, evaluator: Evaluator, h: float, chunk_size: int) -> GramStats:
    """Statistics of rows ``r0:r1`` of one block, evaluating about ``chunk_size`` samples at a time."""
    Y = diff.targets(np.arange(len(block.X)) * h, block.X)
    step = max(1, chunk_size // halo.window) if halo.window else chunk_size

    def slabs():
        for r0 in range(block.r0, block.r1, step):
            r1 = min(r0 + step, block.r1)
            s0, s1 = halo.sample_span(r0, r1)
            yield diff.reduce(evaluator.evaluate(block.Z[s0:s1]))[: r1 - r0], Y[r0:r1]

    return GramStats.from_chunks(_regroup(slabs(), chunk_size))


def _regroup(pairs: Iterator, rows: int) -> Iterator:
    """Concatenate small ``(D, Y)`` slabs into slabs of at least ``rows`` rows (fewer Gram updates)."""
    Ds, Ys, n = [], [], 0
    for D, Y in pairs:
        Ds.append(D)
        Ys.append(Y)
        n += len(D)
        if n >= rows:
            yield (Ds[0], Ys[0]) if len(Ds) == 1 else (np.vstack(Ds), np.vstack(Ys))
            Ds, Ys, n = [], [], 0
    if Ds:
        yield (Ds[0], Ys[0]) if len(Ds) == 1 else (np.vstack(Ds), np.vstack(Ys))


# -------------------------------------------------------------------------------------------- stats


def stream_stats(
    records,
    library: Library,
    *,
    derivative="weak",
    chunk_size: int = 4096,
    block_samples: int = BLOCK_SAMPLES,
    jit="auto",
    n_jobs: int = 1,
) -> RegressionStats:
    """Accumulate the regression statistics of one or several records, block by block.

    Parameters
    ----------
    records : Trajectory, ChunkedRecord or list of them
        Independent records (rows never straddle two records). A Trajectory is read in
        slices; a :class:`ChunkedRecord` (:func:`chunked`, :func:`open_npz`) chunk by chunk.
    library : Library
        Candidate terms named like the records' columns.
    derivative : str or derivative strategy
        ``"weak"`` (default), ``"point"``, ``"central"``, ``"savgol"`` or an instance of these.
        An automatic weak-form window is resolved from the first block of the first record.
    chunk_size : int
        Samples evaluated per dictionary call (bounds the dictionary slab to about
        ``chunk_size * n_terms`` values) and rows per Gram update.
    block_samples : int
        Samples gathered before a block is reduced; with ``n_jobs`` blocks in flight, the
        memory for samples is ``O(n_jobs * block_samples * n_columns)``.
    jit : {"auto", True, False}
        Compile the dictionary with a C compiler when available.
    n_jobs : int
        Blocks reduced concurrently on threads (1: in the calling thread).

    Returns
    -------
    RegressionStats
        Equal, up to rounding, to :func:`symsbl.regression_stats` on the concatenated records
        with the same (resolved) derivative strategy.

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> import numpy as np
    >>> streamed = symsbl.stream_stats(symsbl.chunked([train.slice(0, 3000), train.slice(3000, None)]), library)
    >>> in_memory = symsbl.regression_stats(train, library)
    >>> bool(np.allclose(streamed.stats.gram, in_memory.stats.gram, rtol=1e-12))
    True
    """
    records = _as_records(records)
    if not isinstance(library, Library):
        raise LibraryError(f"library must be a symsbl Library; received {type(library).__name__}.")
    for name, value, least in (("chunk_size", chunk_size, 1), ("block_samples", block_samples, 2), ("n_jobs", n_jobs, 1)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
            raise DataError(f"{name}: expected an integer >= {least}, received {value!r}.")
    diff = get_differentiator(derivative)
    evaluator = Evaluator(library, chunk_size=chunk_size, jit=jit)
    pool = ThreadPoolExecutor(n_jobs) if n_jobs > 1 else None
    total, n_rows, names = None, 0, None
    lengths = [r.n_samples if isinstance(r, Trajectory) else None for r in records]
    bar = Progress(f"dictionary ({len(library)} terms) and Gram, streamed", unit="samples",
                   total=None if None in lengths else sum(lengths))
    try:
        with bar:
            for index, record in enumerate(records):
                reader = _RecordReader(record, index)
                part, rows, diff = _record_stats(reader, library, diff, evaluator, chunk_size, block_samples, pool,
                                                 n_jobs, bar)
                if names is None:
                    names = reader.names
                elif reader.names != names:
                    raise DataError(
                        f"all records must have the same state and input names; records[0] has states {names[0]}, "
                        f"inputs {names[1]}; records[{index}] has states {reader.names[0]}, inputs {reader.names[1]}."
                    )
                n_rows += rows
                if part is not None:
                    total = part if total is None else total + part
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
    if n_rows <= len(library):
        raise DataError(
            f"the data give {n_rows} regression rows for {len(library)} candidate terms; "
            "identification needs more rows than terms. Use longer records, a smaller library "
            f"(lower degree) or a derivative with more rows than {type(diff).__name__}."
        )
    return RegressionStats(total, library, names[0], names[1], diff)


def _record_stats(reader, library, diff, evaluator, chunk_size, block_samples, pool, n_jobs, bar):
    """Statistics, row count and (possibly just resolved) strategy of one record."""
    halo = columns = None
    carry, first = None, True
    lo = hi = None
    pending: deque = deque()
    total, n_rows = None, 0
    read = 0  # samples read since the last block was reduced, counted when their block is done

    def collect(result, samples):
        nonlocal total
        total = result if total is None else total + result
        bar.update(samples)

    for t, X, U, last in _blocks(reader, block_samples):
        read += len(t)
        if columns is None:
            names = reader.names
            probe = Trajectory(np.arange(2.0), X[:2] if len(X) >= 2 else np.vstack([X, X]),
                               U[:2] if len(U) >= 2 else np.vstack([U, U]), *names)
            _columns(probe, library)  # names the missing variables, if any
            order = list(names[0]) + list(names[1])
            columns = [order.index(v) for v in library.variable_names]
            head = X[:RESOLVE_SAMPLES]
            diff = diff.resolve(np.arange(len(head)) * (reader.h or 1.0), head, n_terms=len(library))
            halo = _halo(diff)
        if carry is not None:
            X = np.concatenate([carry[0], X])
            U = np.concatenate([carry[1], U])
        lo = X.min(axis=0) if lo is None else np.minimum(lo, X.min(axis=0))
        hi = X.max(axis=0) if hi is None else np.maximum(hi, X.max(axis=0))
        n = len(X)
        if n < halo.min_samples and not last:
            carry = (X, U)
            continue
        if n < halo.min_samples:
            if first:  # the whole record is too short: the strategy's own error says so
                diff.targets(np.arange(n) * (reader.h or 1.0), X)
            break  # an incomplete last window, dropped as in the in-memory path
        r0, r1 = halo.rows(n, first, last)
        first = False
        cut = halo.carry_from(r1)
        carry = (X[cut:], U[cut:])
        if r1 <= r0:
            continue
        n_rows += r1 - r0
        Z = np.ascontiguousarray(np.column_stack([X, U])[:, columns])
        block = _Block(X, Z, r0, r1)
        samples, read = read, 0
        if pool is None:
            collect(_block_stats(block, diff, halo, evaluator, reader.h, chunk_size), samples)
            continue
        pending.append((pool.submit(_block_stats, block, diff, halo, evaluator, reader.h, chunk_size), samples))
        while len(pending) > n_jobs:
            future, samples = pending.popleft()
            collect(future.result(), samples)
    while pending:
        future, samples = pending.popleft()
        collect(future.result(), samples)
    bar.update(read)  # samples that completed no row (a last incomplete window)
    if lo is None:
        raise DataError(f"{reader.label}: the record has no samples.")
    # The running extremes carry everything the variation check looks at (range and magnitude).
    _check_variation(Trajectory(np.arange(2.0), np.vstack([lo, hi]), None, reader.names[0], ()))
    return total, n_rows, diff


def identify_stream(
    records,
    library: Library,
    *,
    derivative="weak",
    rvm: RVM | None = None,
    chunk_size: int = 4096,
    block_samples: int = BLOCK_SAMPLES,
    jit="auto",
    n_jobs: int = 1,
    equivalence_nats: float = 2.0,
) -> IdentifiedModel:
    """Identify one sparse ODE per state from records read block by block.

    :func:`stream_stats` followed by :func:`symsbl.identify.fit_stats`; the parameters are
    those of the two functions. Peak memory is set by ``block_samples``, ``chunk_size`` and the
    number of terms, not by the length of the records.

    Returns
    -------
    IdentifiedModel

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> model = symsbl.identify_stream([train.slice(0, 5000), train.slice(5000, None)], library)
    >>> model.equation("x2").names
    ['x1', 'x2', 'x1**3', 'F']
    """
    problem = stream_stats(
        records, library, derivative=derivative, chunk_size=chunk_size, block_samples=block_samples,
        jit=jit, n_jobs=n_jobs,
    )
    return fit_stats(problem, rvm=rvm, equivalence_nats=equivalence_nats)
