"""Regression statistics as a map-reduce over blocks of samples, on Dask.

The statistics of :func:`symsbl.stream_stats` are a sum over blocks of rows, and a block
is independent of the others once it carries its derivative stencil (its *halo*): a weak-form
block ends on a window boundary and shares its end sample with the next one; a pointwise block
reads the few samples either side of its rows. :func:`dask_stats` therefore cuts each record
into such overlapping slices of a ``dask.array``, maps every slice to its
:class:`~symsbl.GramStats` on the workers (the compiled dictionary is built once per worker
process) and adds the parts in a tree. Scheduling, data movement and fault tolerance are
Dask's; this module only plans the slices.

The same rows enter the same sums as in the single-process path; only the grouping of the
partial sums differs, so the model agrees to rounding.

Dask is optional: ``pip install symsbl[dask]``.
"""

from __future__ import annotations

import hashlib
import pickle
from collections.abc import Sequence
from dataclasses import dataclass

import casadi as ca
import numpy as np

from .._base.checks import enough_rows, integer
from .._base.errors import DataError, LibraryError, MissingExtraError, expected
from .._base.rule import SelectionRule
from .._data.trajectory import Trajectory, validate
from .._derivatives.registry import get_differentiator
from .._model import IdentifiedModel
from .._refine.options import RefineOptions
from .._regression.rows import RegressionStats, block_stats, check_variation, library_columns
from .._regression.rvm import RVM
from .._symbolic.evaluator import Evaluator
from .._symbolic.library import Library
from .fitting import model_from_stats
from .stream import RESOLVE_SAMPLES

__all__ = ["dask_stats", "identify_dask", "from_delayed"]

#: Samples per mapped slice, one task each (32 s at 32768 Hz; about 32 MB of four columns). Larger
#: than the streaming block (:data:`~symsbl._scale.records.BLOCK_SAMPLES`): a task has a fixed cost.
SLICE_SAMPLES = 2**20
#: Parts added per reduction task.
FAN_IN = 8


def _dask():
    try:
        import dask
        import dask.array
    except ImportError as err:
        raise MissingExtraError(
            "identify_dask: expected Dask to be installed, received ImportError; install it with "
            "pip install 'dask[distributed]' (or pip install '.[dask]' from a clone of symsbl)"
        ) from err
    return dask


# ---------------------------------------------------------------------------------- the library


@dataclass(frozen=True)
class _PortableLibrary:
    """A Library as bytes (CasADi SX needs a pickle context), rebuilt once per worker process."""

    blob: bytes
    key: str

    @classmethod
    def of(cls, library: Library) -> _PortableLibrary:
        with ca.global_pickle_context():
            blob = pickle.dumps(library)
        return cls(blob, hashlib.sha1(blob).hexdigest())

    def load(self) -> Library:
        if self.key not in _LIBRARIES:
            with ca.global_unpickle_context():
                _LIBRARIES[self.key] = pickle.loads(self.blob)
        return _LIBRARIES[self.key]


_LIBRARIES: dict[str, Library] = {}


# ---------------------------------------------------------------------------------------- tasks


@dataclass(frozen=True)
class _Slice:
    """Samples ``start:stop`` of a record, of which rows ``r0:r1`` (local) are reduced."""

    start: int
    stop: int
    r0: int
    r1: int


def _slice_stats(
    arr,
    plan: _Slice,
    library: _PortableLibrary,
    diff,
    names: tuple[tuple[str, ...], tuple[str, ...]],
    h,
    chunk_size,
    jit,
):
    """Map step: (statistics, per-column minimum, per-column maximum) of one slice."""
    lib = library.load()
    arr = np.asarray(arr, dtype=float)
    ns = len(names[0])
    where = f"samples {plan.start}:{plan.stop}"
    t, X, U = validate(arr[:, 0], arr[:, 1 : 1 + ns], arr[:, 1 + ns :], *names, source=where)
    Z = np.ascontiguousarray(np.column_stack([X, U])[:, library_columns(*names, lib)])
    # Evaluator compares jit by identity; an unpickled "auto" is an equal but distinct string.
    evaluator = Evaluator(lib, chunk_size=chunk_size, jit="auto" if jit == "auto" else jit)
    stats = block_stats(X, Z, plan.r0, plan.r1, diff, evaluator, h, chunk_size)
    XU = np.column_stack([X, U])
    return stats, XU.min(axis=0), XU.max(axis=0)


def _add(parts):
    """Reduce step: sum of statistics, elementwise extremes."""
    stats = parts[0][0]
    lo, hi = parts[0][1], parts[0][2]
    for s, a, b in parts[1:]:
        stats, lo, hi = stats + s, np.minimum(lo, a), np.maximum(hi, b)
    return stats, lo, hi


def _plan(n: int, stencil, block_samples: int) -> list[_Slice]:
    """Overlapping slices of an ``n``-sample record whose rows tile the record's rows once."""
    halo = stencil
    if halo.stride:
        S = halo.stride
        rows = halo.rows(n, True, True)[1]
        per = max(1, block_samples // S)
        cuts = [k * per for k in range(max(1, rows // per))] + [rows]
        out = []
        for a, b in zip(cuts[:-1], cuts[1:]):
            s0, s1 = halo.sample_span(a, b)
            out.append(_Slice(s0, s1, a - s0 // S, b - s0 // S))
        return out
    per = max(block_samples, halo.min_samples)
    cuts = [k * per for k in range(max(1, n // per))] + [n]
    out = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        s0, s1 = max(a - halo.left, 0), min(b + halo.right, n)
        out.append(_Slice(s0, s1, a - s0, b - s0))
    return out


# ---------------------------------------------------------------------------------------- inputs


def _dask_records(records, n_columns: int, names) -> list:
    dask = _dask()
    from dask.delayed import Delayed

    da = dask.array
    items = list(records) if isinstance(records, (list, tuple)) else [records]
    if not items:
        raise DataError(expected("records", "a dask array or a non-empty list of them", "an empty list", raw=True))
    for k, rec in enumerate(items):
        if not isinstance(rec, da.Array):
            hint = "turn a list of delayed chunks into one with symsbl.from_delayed" if isinstance(rec, Delayed) else ""
            raise DataError(
                expected(
                    f"records[{k}]",
                    f"a dask.array.Array of shape (n_samples, {n_columns}) with columns {['t', *names[0], *names[1]]}",
                    type(rec).__name__,
                    hint,
                    raw=True,
                )
            )
        if rec.ndim != 2 or rec.shape[1] != n_columns or np.isnan(rec.shape[0]):
            raise DataError(
                expected(
                    f"records[{k}]",
                    f"shape (n_samples, {n_columns}) with columns {['t', *names[0], *names[1]]} "
                    "and a known number of samples",
                    f"shape {rec.shape}",
                    raw=True,
                )
            )
    return items


def _as_chunk_array(chunk) -> np.ndarray:
    if isinstance(chunk, Trajectory):
        return np.column_stack([chunk.t, chunk.states, chunk.inputs])
    return np.asarray(chunk, dtype=float)


def from_delayed(chunks: Sequence, *, n_columns: int, lengths: Sequence[int] | None = None, scheduler=None):
    """One record from consecutive ``dask.delayed`` chunks, as a ``dask.array``.

    Parameters
    ----------
    chunks : sequence of dask.delayed
        Each evaluates to a :class:`~symsbl.Trajectory` or to an array of shape
        ``(n, n_columns)`` with columns ``t, states..., inputs...``, in time order.
    n_columns : int
        ``1 + n_states + n_inputs``.
    lengths : sequence of int, optional
        Samples per chunk. Without them every chunk is computed once to count its samples
        (one extra pass over the data).
    scheduler : optional
        Passed to ``dask.compute`` for that pass.

    Returns
    -------
    dask.array.Array, shape (n_samples, n_columns)

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> import dask
    >>> pieces = [dask.delayed(train.slice)(0, 4000), dask.delayed(train.slice)(4000, None)]
    >>> record = symsbl.from_delayed(pieces, n_columns=4, scheduler="synchronous")
    >>> record.shape
    (8193, 4)
    """
    dask = _dask()
    parts = [dask.delayed(_as_chunk_array)(c) for c in chunks]
    if not parts:
        raise DataError(expected("chunks", "at least one delayed chunk", "none", raw=True))
    if lengths is None:
        lengths = dask.compute(*[dask.delayed(len)(p) for p in parts], scheduler=scheduler)
    if len(lengths) != len(parts):
        raise DataError(expected("lengths", f"one length per chunk ({len(parts)})", f"{len(lengths)}", raw=True))
    return dask.array.concatenate(
        [dask.array.from_delayed(p, shape=(int(n), n_columns), dtype=float) for p, n in zip(parts, lengths)]
    )


# ------------------------------------------------------------------------------------------ public


def dask_stats(
    records,
    library: Library,
    *,
    states: Sequence[str],
    inputs: Sequence[str] = (),
    derivative="weak",
    block_samples: int = SLICE_SAMPLES,
    chunk_size: int = 4096,
    jit="auto",
    scheduler=None,
) -> RegressionStats:
    """Accumulate the regression statistics of records held in ``dask.array`` s, on Dask.

    Parameters
    ----------
    records : dask.array.Array or list of them
        Each of shape ``(n_samples, 1 + n_states + n_inputs)`` with columns
        ``t, states..., inputs...``: one continuous, uniformly sampled record (rows never
        straddle two records). :func:`from_delayed` builds one from delayed chunks.
    library : Library
    states, inputs : sequence of str
        Names of the state and input columns, in order.
    derivative : str or derivative strategy
        As in :func:`symsbl.stream_stats`; an automatic weak-form window is resolved
        from the first samples of the first record (computed eagerly), as the single-process
        path (:func:`symsbl.identify_stream`) does.
    block_samples : int
        Samples per mapped slice (each slice is one task).
    chunk_size : int
        Samples per dictionary evaluation inside a task.
    jit : {"auto", True, False}
        Compile the dictionary on each worker.
    scheduler : optional
        Passed to ``dask.compute``; by default the active ``dask.distributed.Client`` if any,
        else Dask's default scheduler.

    Returns
    -------
    RegressionStats
        Equal, up to the grouping of partial sums, to :func:`symsbl.stream_stats` on
        the same records.

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> import numpy as np
    >>> import dask.array as da
    >>> record = da.from_array(np.column_stack([train.t, train.states, train.inputs]), chunks=(4096, 4))
    >>> problem = symsbl.dask_stats(record, library, states=["x1", "x2"], inputs=["F"], scheduler="synchronous")
    >>> bool(np.allclose(problem.stats.gram, symsbl.regression_stats(train, library).stats.gram, rtol=1e-12))
    True
    """
    dask = _dask()
    names = (tuple(states), tuple(inputs))
    if not names[0]:
        raise DataError(expected("states", "at least one column name", "an empty list", raw=True))
    if not isinstance(library, Library):
        raise LibraryError(expected("library", "a symsbl Library", type(library).__name__, raw=True))
    integer("block_samples", block_samples, low=2, error=DataError)
    n_columns = 1 + len(names[0]) + len(names[1])
    items = _dask_records(records, n_columns, names)
    head = np.asarray(items[0][: min(RESOLVE_SAMPLES, items[0].shape[0])].compute(scheduler=scheduler), dtype=float)
    t, X, U = validate(
        head[:, 0],
        head[:, 1 : n_columns - len(names[1])],
        head[:, n_columns - len(names[1]) :],
        *names,
        source="records[0]",
    )
    library_columns(*names, library)  # names the missing variables, if any
    h = float(t[1] - t[0])
    diff = get_differentiator(derivative).resolve(np.arange(len(X)) * h, X, n_terms=len(library))
    halo = diff.stencil
    portable = dask.delayed(_PortableLibrary.of(library), pure=True)
    parts, n_rows = [], 0
    for rec in items:
        for plan in _plan(int(rec.shape[0]), halo, block_samples):
            if plan.stop - plan.start < halo.min_samples:
                continue
            n_rows += plan.r1 - plan.r0
            parts.append(
                dask.delayed(_slice_stats, pure=True)(
                    rec[plan.start : plan.stop], plan, portable, diff, names, h, chunk_size, jit
                )
            )
    enough_rows(n_rows, len(library), f"{len(items)} record(s) with {type(diff).__name__}")
    while len(parts) > 1:
        parts = [dask.delayed(_add, pure=True)(parts[k : k + FAN_IN]) for k in range(0, len(parts), FAN_IN)]
    ((stats, lo, hi),) = dask.compute(parts[0], scheduler=scheduler)
    ns = len(names[0])
    check_variation(names[0], lo[:ns], hi[:ns])
    used = [k for k, n in enumerate(names[1]) if n in library.variable_names]
    check_variation([names[1][k] for k in used], lo[ns:][used], hi[ns:][used], "input")
    return RegressionStats(stats, library, names[0], names[1], diff)


def identify_dask(
    records,
    library: Library,
    *,
    states: Sequence[str],
    inputs: Sequence[str] = (),
    derivative="weak",
    rvm: RVM | None = None,
    block_samples: int = SLICE_SAMPLES,
    chunk_size: int = 4096,
    jit="auto",
    scheduler=None,
    equivalence_nats: float | None = None,
    refine: bool | RefineOptions = True,
    refine_options: RefineOptions | dict | None = None,
    selection: SelectionRule | None = None,
    kinematics=None,
) -> IdentifiedModel:
    """Identify one sparse ODE per state from records in ``dask.array`` s.

    :func:`dask_stats` on the cluster, then :func:`symsbl.fit_stats` locally (the
    fit needs only the ``n_terms x n_terms`` statistics) and, by default, the output-error
    refinement locally on at most :attr:`RefineOptions.max_samples <symsbl.RefineOptions>` (2^18 by default)
    samples, as evenly spaced windows fetched from the records (as :func:`symsbl.identify_stream`
    does). Other parameters as in those functions and :func:`symsbl.identify` (``refine``, ``refine_options``,
    ``selection``, ``equivalence_nats``; ``kinematics`` with both members of each pair among ``states``).

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
    >>> import numpy as np
    >>> import dask.array as da
    >>> columns = np.column_stack([train.t, train.states, train.inputs])   # t, x1, x2, F
    >>> record = da.from_array(columns, chunks=(4096, 4))
    >>> model = symsbl.identify_dask(record, library, states=["x1", "x2"], inputs=["F"], scheduler="synchronous")
    >>> model.equation("x2").names
    ['x1', 'x2', 'x1**3', 'F']
    """
    problem = dask_stats(
        records,
        library,
        states=states,
        inputs=inputs,
        derivative=derivative,
        block_samples=block_samples,
        chunk_size=chunk_size,
        jit=jit,
        scheduler=scheduler,
    )
    names = (tuple(states), tuple(inputs))
    items = _dask_records(records, 1 + len(names[0]) + len(names[1]), names)

    def windows(plan):
        ns = len(names[0])
        out = []
        for k, a, b in plan:
            arr = np.asarray(items[k][a:b].compute(scheduler=scheduler), dtype=float)
            out.append(Trajectory(arr[:, 0], arr[:, 1 : 1 + ns], arr[:, 1 + ns :], names[0], names[1]))
        return out

    return model_from_stats(
        problem,
        [int(r.shape[0]) for r in items],
        windows,
        library=library,
        rvm=rvm,
        equivalence_nats=equivalence_nats,
        selection=selection,
        kinematics=kinematics,
        refine=refine,
        refine_options=refine_options,
    )
