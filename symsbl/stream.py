"""Streaming regression statistics: records longer than memory, read and reduced chunk by chunk.

A *record* is one continuous, uniformly sampled experiment. It may be held in memory
(a :class:`~symsbl.data.Trajectory`), arrive as consecutive pieces (:func:`chunked`: a list,
a generator or a factory of chunks) or sit in an ``.npz`` file that is memory-mapped
(:func:`open_npz`). :func:`stream_stats` turns any number of records into the same
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

import contextlib
import struct
import zipfile
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np

from .data import TIME_RTOL, Trajectory, validate
from .derivatives import CentralDifference, PointDifference, SavitzkyGolay, WeakForm, get_differentiator
from .errors import DataError, LibraryError
from .evaluator import Evaluator
from .identify import RegressionStats, _check_variation, _columns, fit_stats
from .library import Library
from .model import IdentifiedModel
from .progress import Progress
from .rvm import RVM, GramStats

__all__ = ["ChunkedRecord", "chunked", "open_npz", "stream_stats", "identify_stream"]

#: Samples gathered per block when a record arrives in smaller chunks (8 s at 32768 Hz).
BLOCK_SAMPLES = 2**18
#: An automatic weak-form window is resolved from at most this many samples at the start of
#: the first record (shared with :mod:`symsbl.distributed`, so both resolve the same window).
RESOLVE_SAMPLES = 2**18


# ------------------------------------------------------------------------------------------ records


@dataclass(frozen=True)
class ChunkedRecord:
    """One continuous record delivered as consecutive chunks of samples.

    Build it with :func:`chunked` or :func:`open_npz` rather than directly.

    Attributes
    ----------
    source : callable
        Returns a fresh iterator of chunks on every call; each chunk is a
        :class:`~symsbl.data.Trajectory` or an array of shape ``(n, 1 + n_states + n_inputs)``
        with the columns ``t, states..., inputs...``.
    state_names, input_names : tuple of str or None
        Column names; ``None`` takes them from the first Trajectory chunk.
    label : str
        Where the chunks come from, for error messages.
    """

    source: Callable[[], Iterator]
    state_names: tuple[str, ...] | None
    input_names: tuple[str, ...] | None
    label: str


def chunked(chunks, *, states: Sequence[str] | None = None, inputs: Sequence[str] = ()) -> ChunkedRecord:
    """Declare consecutive chunks as one continuous record.

    Parameters
    ----------
    chunks : sequence, iterator or callable
        The pieces of the record in time order: :class:`~symsbl.data.Trajectory` objects or
        arrays of shape ``(n, 1 + n_states + n_inputs)`` with columns ``t, states..., inputs...``.
        A list can be read any number of times, a generator once; a callable returning a new
        iterator can be read again.
    states, inputs : sequence of str
        Column names. Required for array chunks; for Trajectory chunks they default to the
        first chunk's names.

    Returns
    -------
    ChunkedRecord

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> record = symsbl.chunked([train.slice(0, 4096), train.slice(4096, None)])
    >>> symsbl.identify_stream(record, library).equation("x2").names
    ['x1', 'x2', 'x1**3', 'F']
    """
    if callable(chunks) and not isinstance(chunks, (list, tuple)):
        source = chunks
    elif isinstance(chunks, (list, tuple)):
        source = lambda: iter(chunks)  # noqa: E731
    elif isinstance(chunks, Iterable) and not isinstance(chunks, (np.ndarray, Trajectory, str, bytes)):
        used = []

        def source():
            if used:
                raise DataError(
                    "chunks: this record was built from an iterator, which can be read only once; "
                    "pass a list or a function returning a new iterator to read it again."
                )
            used.append(True)
            return iter(chunks)
    else:
        raise DataError(
            "chunks: expected a sequence, an iterator or a function returning an iterator of "
            f"Trajectory or array chunks; received {type(chunks).__name__}. A single in-memory "
            "Trajectory can be passed to stream_stats directly."
        )
    names = None if states is None else tuple(states)
    return ChunkedRecord(source, names, tuple(inputs) if names is not None else None, "chunks")


def _npz_columns(path: Path, names: Sequence[str]) -> tuple[dict, int]:
    """Per column: a callable ``(start, stop) -> ndarray`` reading the member lazily; and the length."""
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as err:
        raise DataError(f"{path}: not a readable .npz file ({err}).") from None
    with zf:
        members = {info.filename[:-4]: info for info in zf.infolist() if info.filename.endswith(".npy")}
        readers, lengths = {}, {}
        for name in names:
            if name not in members:
                raise DataError(f"{path}: column {name!r} not found; available columns: {sorted(members)}.")
            info = members[name]
            with zf.open(info) as fh:
                version = np.lib.format.read_magic(fh)
                read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                shape, _, dtype = read(fh)
                header = fh.tell()
            if len([s for s in shape if s != 1]) > 1 or not np.issubdtype(dtype, np.number):
                raise DataError(
                    f"{path}: column {name!r} must be a numeric vector (N, 1xN or Nx1); "
                    f"received shape {shape} and dtype {dtype}."
                )
            lengths[name] = int(np.prod(shape))
            if info.compress_type == zipfile.ZIP_STORED:
                with open(path, "rb") as raw:
                    raw.seek(info.header_offset)
                    local = raw.read(30)
                name_len, extra_len = struct.unpack("<HH", local[26:30])
                offset = info.header_offset + 30 + name_len + extra_len + header
                mm = np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=(lengths[name],))
                readers[name] = ("mmap", mm)
            else:
                readers[name] = ("zip", (info.filename, header, dtype))
    if len(set(lengths.values())) > 1:
        raise DataError(f"{path}: columns have different lengths {lengths}; all must have one value per sample.")
    return readers, next(iter(lengths.values()))


def open_npz(
    path,
    *,
    states: Sequence[str],
    inputs: Sequence[str] = (),
    time: str | None = "t",
    fs: float | None = None,
    chunk_samples: int = BLOCK_SAMPLES,
    start: int = 0,
    stop: int | None = None,
) -> ChunkedRecord:
    """A record in an ``.npz`` file (one named vector per column), read chunk by chunk.

    Members saved uncompressed (:func:`numpy.savez`) are memory-mapped, so only the chunk being
    read occupies memory; compressed members (:func:`numpy.savez_compressed`) are decompressed
    as a stream. The file is only read.

    Parameters
    ----------
    path : str or Path
    states, inputs : sequence of str
        Column names to use as states and inputs, in this order.
    time : str or None
        Name of the time column; ``None`` uses ``t = (start + arange(n)) / fs``.
    fs : float, optional
        Sample rate in Hz, required when ``time`` is None.
    chunk_samples : int
        Samples per chunk read.
    start, stop : int
        Sample range to read (Python slice semantics, non-negative).

    Returns
    -------
    ChunkedRecord

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> import os, tempfile
    >>> path = os.path.join(tempfile.mkdtemp(), "train.npz")
    >>> symsbl.write_trajectory(train, path)
    >>> record = symsbl.open_npz(path, states=["x1", "x2"], inputs=["F"])   # memory-mapped, read in blocks
    >>> symsbl.identify_stream(record, library).equation("x2").names
    ['x1', 'x2', 'x1**3', 'F']
    """
    path = Path(path)
    state_names, input_names = tuple(states), tuple(inputs)
    if not state_names:
        raise DataError("states must name at least one column; received an empty list.")
    if not path.is_file():
        raise DataError(f"file {path} does not exist.")
    if isinstance(chunk_samples, bool) or not isinstance(chunk_samples, (int, np.integer)) or chunk_samples < 2:
        raise DataError(f"chunk_samples: expected an integer >= 2, received {chunk_samples!r}.")
    if time is None and (fs is None or not np.isfinite(fs) or fs <= 0):
        raise DataError(f"time=None needs a positive sample rate fs in Hz; received fs={fs!r}.")
    names = ((time,) if time is not None else ()) + state_names + input_names
    readers, n = _npz_columns(path, names)
    stop = n if stop is None else min(int(stop), n)
    if not (0 <= start < stop):
        raise DataError(f"start, stop: expected 0 <= start < stop <= {n} samples; received start={start}, stop={stop}.")

    def source():
        with contextlib.ExitStack() as stack:
            streams = {}
            for name, (kind, how) in readers.items():
                if kind == "mmap":
                    streams[name] = lambda a, b, mm=how: mm[a:b]
                    continue
                member, header, dtype = how  # compressed: decompress in order, skipping to start
                fh = stack.enter_context(stack.enter_context(zipfile.ZipFile(path)).open(member))
                fh.read(header + start * dtype.itemsize)
                streams[name] = lambda a, b, fh=fh, dtype=dtype: np.frombuffer(fh.read((b - a) * dtype.itemsize), dtype)
            for a in range(start, stop, chunk_samples):
                b = min(a + chunk_samples, stop)
                cols = [np.arange(a, b) / float(fs)] if time is None else []
                cols += [np.asarray(streams[name](a, b), dtype=float) for name in names]
                yield np.column_stack(cols)

    return ChunkedRecord(source, state_names, input_names, str(path))


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


class _RecordReader:
    """Turn one record's chunks into validated ``(t, X, U)`` arrays with continuous time."""

    def __init__(self, record, index: int):
        self.index = index
        if isinstance(record, Trajectory):
            self.label = f"records[{index}]"
            self.names = (record.state_names, record.input_names)
            self._chunks = lambda: (record.slice(a, a + BLOCK_SAMPLES) for a in range(0, record.n_samples, BLOCK_SAMPLES))
        elif isinstance(record, ChunkedRecord):
            self.label = f"records[{index}] ({record.label})"
            self.names = None if record.state_names is None else (record.state_names, record.input_names)
            self._chunks = record.source
        else:
            raise DataError(
                f"records[{index}]: expected a Trajectory or a ChunkedRecord (from symsbl.stream.chunked or "
                f"open_npz); received {type(record).__name__}."
            )
        self.h = None
        self.t_last = None

    def __iter__(self) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        for k, chunk in enumerate(self._chunks()):
            t, X, U = self._arrays(chunk, k)
            self._check_time(t, k)
            yield t, X, U

    def _arrays(self, chunk, k: int):
        where = f"{self.label} chunk {k}"
        if isinstance(chunk, Trajectory):
            names = (chunk.state_names, chunk.input_names)
            if self.names is None:
                self.names = names
            if names != self.names:
                raise DataError(
                    f"{where}: has states {names[0]} and inputs {names[1]}; expected states "
                    f"{self.names[0]} and inputs {self.names[1]} like the rest of the record."
                )
            return chunk.t, chunk.states, chunk.inputs
        if self.names is None:
            raise DataError(
                f"{where}: array chunks need column names; pass states=... (and inputs=...) to "
                "symsbl.stream.chunked."
            )
        arr = np.asarray(chunk, dtype=float)
        ns, ni = len(self.names[0]), len(self.names[1])
        if arr.ndim != 2 or arr.shape[1] != 1 + ns + ni:
            raise DataError(
                f"{where}: expected an array of shape (n, {1 + ns + ni}) with columns "
                f"{['t', *self.names[0], *self.names[1]]}; received shape {arr.shape}."
            )
        if len(arr) == 1:  # a single sample: validate() needs two, so check it by hand
            if not np.all(np.isfinite(arr)):
                raise DataError(f"{where}: has a non-finite value in its only row.")
            return arr[:, 0], arr[:, 1 : 1 + ns], arr[:, 1 + ns :]
        return validate(arr[:, 0], arr[:, 1 : 1 + ns], arr[:, 1 + ns :], *self.names, source=where)

    def _check_time(self, t: np.ndarray, k: int) -> None:
        if len(t) == 0:
            return
        if self.h is None and len(t) >= 2:
            self.h = float(t[1] - t[0])
        if self.t_last is not None and self.h is not None:
            gap = float(t[0] - self.t_last)
            if abs(gap - self.h) > TIME_RTOL * self.h:
                raise DataError(
                    f"{self.label} chunk {k}: starts at t = {t[0]!r}, {gap!r} s after the previous chunk "
                    f"ended, but the sample interval is {self.h!r} s; chunks must be consecutive pieces of "
                    "one uniformly sampled record (pass separate records as separate list entries)."
                )
        self.t_last = float(t[-1])


def _blocks(reader: _RecordReader, block_samples: int) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, bool]]:
    """Gather chunks into arrays of at least ``block_samples`` samples; flag the last one."""
    pending, n, previous = [], 0, None
    for part in reader:
        pending.append(part)
        n += len(part[0])
        if n >= block_samples:
            if previous is not None:
                yield (*previous, False)
            previous = tuple(np.concatenate(cols) if len(pending) > 1 else cols[0] for cols in zip(*pending))
            pending, n = [], 0
    if pending:
        if previous is not None:
            yield (*previous, False)
        previous = tuple(np.concatenate(cols) if len(pending) > 1 else cols[0] for cols in zip(*pending))
    if previous is not None:
        yield (*previous, True)


# -------------------------------------------------------------------------------------------- stats


def _as_records(records) -> list:
    if isinstance(records, (Trajectory, ChunkedRecord)):
        return [records]
    if isinstance(records, (str, Path)):
        raise DataError(
            f"records: received the path {str(records)!r}; open it with symsbl.stream.open_npz(path, "
            "states=..., inputs=...) so the columns are named."
        )
    if isinstance(records, (list, tuple)) and records:
        return list(records)
    raise DataError(
        "records: expected a Trajectory, a ChunkedRecord or a non-empty list of them; received "
        f"{type(records).__name__}."
    )


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

    def collect(result):
        nonlocal total
        total = result if total is None else total + result

    for t, X, U, last in _blocks(reader, block_samples):
        bar.update(len(t))
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
        if pool is None:
            collect(_block_stats(block, diff, halo, evaluator, reader.h, chunk_size))
            continue
        pending.append(pool.submit(_block_stats, block, diff, halo, evaluator, reader.h, chunk_size))
        while len(pending) > n_jobs:
            collect(pending.popleft().result())
    while pending:
        collect(pending.popleft().result())
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
