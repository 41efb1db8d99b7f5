"""Streaming regression statistics: records longer than memory, read and reduced chunk by chunk.

A *record* is one continuous, uniformly sampled experiment. It may be held in memory
(a :class:`~symsbl.Trajectory`), arrive as consecutive pieces
(:func:`~symsbl.chunked`: a list, a generator or a factory of chunks) or sit in an
``.npz`` file that is memory-mapped (:func:`~symsbl.open_npz`); :mod:`symsbl._scale.records`
reads them, and they are also importable from here. :func:`stream_stats` turns any number of records into the same
:class:`~symsbl.RegressionStats` that :func:`~symsbl.regression_stats` builds
from the concatenated data, holding only one block of samples (``block_samples``) and one slab
of the dictionary (about ``chunk_size`` samples by ``n_terms``) at a time: memory depends on
the number of terms, not on the record's length.

Chunk boundaries
----------------
Samples are gathered into blocks. Every regression row needs a few neighbouring samples
(its *halo*), so each block starts with the samples the previous one could not finish:

- :class:`~symsbl.WeakForm` rows are windows of ``window`` sample intervals
  aligned with the start of the record; a block ends at a window boundary and the samples from
  the last boundary on (the shared end sample and any incomplete window) are carried over.
- pointwise strategies (point, central, Savitzky-Golay) emit only the rows whose stencil lies
  inside the block, carry the stencil's width over, and use their one-sided end formulas only
  at the true start and end of the record.

Rows are therefore the rows of the whole record, computed in the same arithmetic, and the
statistics equal those of :func:`~symsbl.regression_stats` up to the order in which
partial sums are added. A :class:`~symsbl.WeakForm` without a window is resolved
once, from the first block of the first record (at most :data:`RESOLVE_SAMPLES` samples; the
whole record when it is shorter), and then stays fixed for every record.

Blocks are independent once their halo is attached, so ``n_jobs=2`` reduces two blocks at once
on two threads: the compiled dictionary evaluation and numpy's reductions release the GIL.
"""

from __future__ import annotations

from collections import deque
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .._base.checks import enough_rows, integer
from .._base.errors import DataError, LibraryError, expected
from .._base.progress import Progress
from .._base.rule import SelectionRule
from .._data.trajectory import Trajectory
from .._derivatives.registry import get_differentiator
from .._model import IdentifiedModel
from .._refine.options import RefineOptions
from .._regression.rows import RegressionStats, block_stats, check_variation, library_columns
from .._regression.rvm import RVM
from .._symbolic.evaluator import Evaluator
from .._symbolic.library import Library
from .fitting import model_from_stats
from .records import BLOCK_SAMPLES, RecordReader, as_records, blocks, read_windows

__all__ = ["stream_stats", "identify_stream", "RESOLVE_SAMPLES"]

#: An automatic weak-form window is resolved from at most this many samples at the start of
#: the first record (shared with the Dask path, so both resolve the same window).
RESOLVE_SAMPLES = 2**18


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
    return _stream_stats(
        records,
        library,
        derivative=derivative,
        chunk_size=chunk_size,
        block_samples=block_samples,
        jit=jit,
        n_jobs=n_jobs,
    )[0]


def _stream_stats(records, library, *, derivative, chunk_size, block_samples, jit, n_jobs):
    """:func:`stream_stats`, and the number of samples of every record."""
    records = as_records(records)
    if not isinstance(library, Library):
        raise LibraryError(expected("library", "a symsbl Library", type(library).__name__, raw=True))
    for name, value, least in (
        ("chunk_size", chunk_size, 1),
        ("block_samples", block_samples, 2),
        ("n_jobs", n_jobs, 1),
    ):
        integer(name, value, low=least, error=DataError)
    diff = get_differentiator(derivative)
    evaluator = Evaluator(library, chunk_size=chunk_size, jit=jit)
    pool = ThreadPoolExecutor(n_jobs) if n_jobs > 1 else None
    total, n_rows, names, counts = None, 0, None, []
    lengths = [r.n_samples if isinstance(r, Trajectory) else None for r in records]
    bar = Progress(
        f"dictionary ({len(library)} terms) and Gram, streamed",
        unit="samples",
        total=None if None in lengths else sum(lengths),
    )
    try:
        with bar:
            for index, record in enumerate(records):
                reader = RecordReader(record, index)
                part, rows, diff, count = _record_stats(
                    reader, library, diff, evaluator, chunk_size, block_samples, pool, n_jobs, bar
                )
                counts.append(count)
                if names is None:
                    names = reader.names
                elif reader.names != names:
                    raise DataError(
                        expected(
                            f"records[{index}]",
                            f"the states {names[0]} and inputs {names[1]} of records[0]",
                            f"states {reader.names[0]}, inputs {reader.names[1]}",
                            raw=True,
                        )
                    )
                n_rows += rows
                if part is not None:
                    total = part if total is None else total + part
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
    enough_rows(n_rows, len(library), f"{len(records)} record(s) with {type(diff).__name__}")
    return RegressionStats(total, library, names[0], names[1], diff), counts


def _record_stats(reader, library, diff, evaluator, chunk_size, block_samples, pool, n_jobs, bar):
    """Statistics, row count and (possibly just resolved) strategy of one record."""
    stencil = columns = None
    carry, first = None, True
    lo = hi = None
    pending: deque = deque()
    total, n_rows = None, 0
    read = 0  # samples read since the last block was reduced, counted when their block is done
    count = 0

    def collect(result, samples):
        nonlocal total
        total = result if total is None else total + result
        bar.update(samples)

    for t, X, U, last in blocks(reader, block_samples):
        read += len(t)
        count += len(t)
        if columns is None:
            columns = library_columns(*reader.names, library)
            head = X[:RESOLVE_SAMPLES]
            diff = diff.resolve(np.arange(len(head)) * (reader.h or 1.0), head, n_terms=len(library))
            stencil = diff.stencil
        if carry is not None:
            X = np.concatenate([carry[0], X])
            U = np.concatenate([carry[1], U])
        XU = np.column_stack([X, U])
        lo = XU.min(axis=0) if lo is None else np.minimum(lo, XU.min(axis=0))
        hi = XU.max(axis=0) if hi is None else np.maximum(hi, XU.max(axis=0))
        n = len(X)
        if n < stencil.min_block and not last:
            carry = (X, U)
            continue
        r0, r1 = stencil.rows(n, first, last)
        if r1 <= r0 and last:
            if first:  # the whole record is too short: the strategy's own error says so
                diff.targets(np.arange(n) * (reader.h or 1.0), X)
            break  # an incomplete last window, dropped as in the in-memory path
        first = False
        cut = stencil.carry_from(r1)
        carry = (X[cut:], U[cut:])
        if r1 <= r0:
            continue
        n_rows += r1 - r0
        Z = np.ascontiguousarray(np.column_stack([X, U])[:, columns])
        samples, read = read, 0
        args = (X, Z, r0, r1, diff, evaluator, reader.h, chunk_size)
        if pool is None:
            collect(block_stats(*args), samples)
            continue
        pending.append((pool.submit(block_stats, *args), samples))
        while len(pending) > n_jobs:
            future, samples = pending.popleft()
            collect(future.result(), samples)
    while pending:
        future, samples = pending.popleft()
        collect(future.result(), samples)
    bar.update(read)  # samples that completed no row (a last incomplete window)
    _check_extremes(reader, library, lo, hi)
    return total, n_rows, diff, count


def _check_extremes(reader, library, lo, hi) -> None:
    """The variation checks of states and used inputs, from a record's running extremes."""
    if lo is None:
        raise DataError(expected(reader.label, "a record with samples", "an empty record", raw=True))
    states, inputs = reader.names
    check_variation(states, lo[: len(states)], hi[: len(states)])
    used = [k for k, n in enumerate(inputs) if n in library.variable_names]
    check_variation([inputs[k] for k in used], lo[len(states) :][used], hi[len(states) :][used], "input")


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
    equivalence_nats: float | None = None,
    refine: bool | RefineOptions = True,
    refine_options: RefineOptions | dict | None = None,
    selection: SelectionRule | None = None,
    kinematics=None,
) -> IdentifiedModel:
    """Identify one sparse ODE per state from records read block by block.

    :func:`stream_stats` followed by :func:`symsbl.fit_stats` and, by default, the output-error
    refinement (:func:`symsbl.refine`) on at most :attr:`RefineOptions.max_samples <symsbl.RefineOptions>`
    (2^18 by default) samples: whole records when they fit, else evenly
    spaced windows read again from the records. Peak memory is set by ``block_samples``,
    ``chunk_size``, the number of terms and that sample budget, not by the length of the records.
    The other parameters are those of the functions named and of :func:`symsbl.identify` (``refine``,
    ``refine_options``, ``selection``, ``equivalence_nats``; ``refine=False`` stops at the equation-error
    model); ``kinematics`` declares position-velocity pairs whose members are both columns.

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
    records = as_records(records)
    problem, counts = _stream_stats(
        records,
        library,
        derivative=derivative,
        chunk_size=chunk_size,
        block_samples=block_samples,
        jit=jit,
        n_jobs=n_jobs,
    )
    return model_from_stats(
        problem,
        counts,
        lambda plan: read_windows(records, plan),
        library=library,
        rvm=rvm,
        equivalence_nats=equivalence_nats,
        selection=selection,
        kinematics=kinematics,
        refine=refine,
        refine_options=refine_options,
    )
