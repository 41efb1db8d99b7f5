"""Records for streaming: one continuous experiment delivered in pieces, read back as validated blocks.

A record is a :class:`~symsbl.Trajectory` held in memory, consecutive chunks declared with
:func:`chunked` (a list, a generator or a factory of chunks), or an ``.npz`` file memory-mapped by
:func:`open_npz`. :mod:`symsbl._scale.stream` reduces records to regression statistics block by block;
this module only delivers their samples: every chunk validated, time continuous across chunk
boundaries, gathered into blocks of ``block_samples``.
"""

from __future__ import annotations

import contextlib
import math
import struct
import zipfile
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._base.checks import integer, number
from .._base.errors import DataError, expected
from .._data.trajectory import TIME_RTOL, Trajectory, validate

__all__ = [
    "ChunkedRecord",
    "chunked",
    "open_npz",
    "as_records",
    "RecordReader",
    "blocks",
    "read_windows",
    "BLOCK_SAMPLES",
]

#: Samples gathered per block when a record arrives in smaller chunks (8 s at 32768 Hz).
BLOCK_SAMPLES = 2**18


# ------------------------------------------------------------------------------------------ sources


@dataclass(frozen=True)
class ChunkedRecord:
    """One continuous record delivered as consecutive chunks of samples.

    Build it with :func:`chunked` or :func:`open_npz` rather than directly.

    Attributes
    ----------
    source : callable
        Returns a fresh iterator of chunks on every call; each chunk is a
        :class:`~symsbl.Trajectory` or an array of shape ``(n, 1 + n_states + n_inputs)``
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
        The pieces of the record in time order: :class:`~symsbl.Trajectory` objects or
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
        used: list[bool] = []

        def source():
            if used:
                raise DataError(
                    expected(
                        "chunks",
                        "a record that can be read again",
                        "an iterator, already read",
                        "pass a list or a function returning a new iterator",
                        raw=True,
                    )
                )
            used.append(True)
            return iter(chunks)
    else:
        raise DataError(
            expected(
                "chunks",
                "a sequence, an iterator or a function returning an iterator of Trajectory or array chunks",
                type(chunks).__name__,
                "pass a single in-memory Trajectory to stream_stats directly",
                raw=True,
            )
        )
    names = None if states is None else tuple(states)
    return ChunkedRecord(source, names, tuple(inputs) if names is not None else None, "chunks")


def _npz_columns(path: Path, names: Sequence[str]) -> tuple[dict, int]:
    """Per column: a callable ``(start, stop) -> ndarray`` reading the member lazily; and the length."""
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as err:
        raise DataError(expected(str(path), "a readable .npz file", f"an unreadable file ({err})", raw=True)) from None
    with zf:
        members = {info.filename[:-4]: info for info in zf.infolist() if info.filename.endswith(".npy")}
        readers: dict[str, tuple[str, Any]] = {}
        lengths: dict[str, int] = {}
        for name in names:
            if name not in members:
                raise DataError(
                    expected(
                        f"{path}: column {name!r}", f"a column among {sorted(members)}", "no such column", raw=True
                    )
                )
            info = members[name]
            with zf.open(info) as fh:
                version = np.lib.format.read_magic(fh)
                read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                shape, _, dtype = read(fh)
                header = fh.tell()
            if len([s for s in shape if s != 1]) > 1 or not np.issubdtype(dtype, np.number):
                raise DataError(
                    expected(
                        f"{path}: column {name!r}",
                        "a numeric vector (N, 1xN or Nx1)",
                        f"shape {shape} and dtype {dtype}",
                        raw=True,
                    )
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
        raise DataError(expected(str(path), "columns of one length", f"lengths {lengths}", raw=True))
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
        raise DataError(expected("states", "at least one column name", "an empty list", raw=True))
    if not path.is_file():
        raise DataError(expected(str(path), "an existing .npz file", "no such file", raw=True))
    integer("chunk_samples", chunk_samples, low=2, error=DataError)
    if time is None:
        number("fs", fs if fs is not None else math.nan, low=0.0, strict=True, error=DataError)
    names = ((time,) if time is not None else ()) + state_names + input_names
    readers, n = _npz_columns(path, names)
    stop = n if stop is None else min(int(stop), n)
    if not (0 <= start < stop):
        raise DataError(
            expected("start, stop", f"0 <= start < stop <= {n} samples", f"start={start}, stop={stop}", raw=True)
        )

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


# ------------------------------------------------------------------------------------------ reading


def as_records(records) -> list:
    if isinstance(records, (Trajectory, ChunkedRecord)):
        return [records]
    if isinstance(records, (str, Path)):
        raise DataError(
            expected(
                "records",
                "a Trajectory, a ChunkedRecord or a list of them",
                f"the path {str(records)!r}",
                "open it with symsbl.open_npz(path, states=..., inputs=...)",
                raw=True,
            )
        )
    if isinstance(records, (list, tuple)) and records:
        return list(records)
    raise DataError(
        expected(
            "records", "a Trajectory, a ChunkedRecord or a non-empty list of them", type(records).__name__, raw=True
        )
    )


class RecordReader:
    """Turn one record's chunks into validated ``(t, X, U)`` arrays with continuous time."""

    def __init__(self, record, index: int):
        self.index = index
        self.names: tuple[tuple[str, ...], tuple[str, ...]] | None
        self._chunks: Callable[[], Iterator]
        if isinstance(record, Trajectory):
            self.label = f"records[{index}]"
            self.names = (record.state_names, record.input_names)
            self._chunks = lambda: (
                record.slice(a, a + BLOCK_SAMPLES) for a in range(0, record.n_samples, BLOCK_SAMPLES)
            )
        elif isinstance(record, ChunkedRecord):
            self.label = f"records[{index}] ({record.label})"
            states, inputs = record.state_names, record.input_names  # both None or both set
            self.names = None if states is None or inputs is None else (states, inputs)
            self._chunks = record.source
        else:
            raise DataError(
                expected(
                    f"records[{index}]",
                    "a Trajectory or a ChunkedRecord (from symsbl.chunked or open_npz)",
                    type(record).__name__,
                    raw=True,
                )
            )
        self.h: float | None = None
        self.t_last: float | None = None

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
                    expected(
                        where,
                        f"states {self.names[0]} and inputs {self.names[1]} like the rest of the record",
                        f"states {names[0]} and inputs {names[1]}",
                        raw=True,
                    )
                )
            return chunk.t, chunk.states, chunk.inputs
        if self.names is None:
            raise DataError(
                expected(
                    where,
                    "column names for array chunks",
                    "none",
                    "pass states=... (and inputs=...) to symsbl.chunked",
                    raw=True,
                )
            )
        arr = np.asarray(chunk, dtype=float)
        ns, ni = len(self.names[0]), len(self.names[1])
        if arr.ndim != 2 or arr.shape[1] != 1 + ns + ni:
            raise DataError(
                expected(
                    where,
                    f"an array of shape (n, {1 + ns + ni}) with columns {['t', *self.names[0], *self.names[1]]}",
                    f"shape {arr.shape}",
                    raw=True,
                )
            )
        if len(arr) == 1:  # a single sample: validate() needs two, so check it by hand
            if not np.all(np.isfinite(arr)):
                raise DataError(expected(where, "finite values", "a non-finite value in its only row", raw=True))
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
                    expected(
                        f"{self.label} chunk {k}",
                        f"a start one sample interval ({self.h!r} s) after the previous chunk",
                        f"t = {t[0]!r}, {gap!r} s after it",
                        "chunks must be consecutive pieces of one record; pass separate records as list entries",
                        raw=True,
                    )
                )
        self.t_last = float(t[-1])


def blocks(reader: RecordReader, block_samples: int) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, bool]]:
    """Gather chunks into arrays of at least ``block_samples`` samples; flag the last one."""
    pending: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    n, previous = 0, None
    for part in reader:
        pending.append(part)
        n += len(part[0])
        if n >= block_samples:
            if previous is not None:
                yield (*previous, False)
            previous = _join(pending)
            pending, n = [], 0
    if pending:
        if previous is not None:
            yield (*previous, False)
        previous = _join(pending)
    if previous is not None:
        yield (*previous, True)


def _join(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``(t, X, U)`` of consecutive parts as one."""
    t, X, U = (np.concatenate(cols) if len(parts) > 1 else cols[0] for cols in zip(*parts))
    return t, X, U


def read_windows(records: Sequence, plan) -> list[Trajectory]:
    """The samples ``start:stop`` of record ``k`` for every ``(k, start, stop)`` of ``plan``, read again."""
    out: dict[int, Trajectory] = {}
    for k in sorted({k for k, _, _ in plan}):
        wanted = [(n, a, b) for n, (j, a, b) in enumerate(plan) if j == k]
        reader = RecordReader(records[k], k)
        parts: dict[int, list] = {n: [] for n, _, _ in wanted}
        position = 0
        for t, X, U in reader:
            for n, a, b in wanted:
                lo, hi = max(a - position, 0), min(b - position, len(t))
                if lo < hi:
                    parts[n].append((t[lo:hi], X[lo:hi], U[lo:hi]))
            position += len(t)
            if position >= max(b for _, _, b in wanted):
                break
        assert reader.names is not None  # known once a chunk has been read
        for n, _, _ in wanted:
            t, X, U = (np.concatenate(cols) for cols in zip(*parts[n]))
            out[n] = Trajectory(t=t, states=X, inputs=U, state_names=reader.names[0], input_names=reader.names[1])
    return [out[n] for n in range(len(plan))]
