"""Regression rows: sampled records x library -> the sufficient statistics of one identification.

The one layer that turns samples into the statistics of the equation-error regression, used by
the in-memory path (:func:`regression_stats`) and, block by block, by the streaming and Dask
paths (:mod:`symsbl._scale`):

1. the derivative strategy (:class:`~symsbl._derivatives.registry.Differentiator`) turns the sampled
   states into targets ``Y`` and declares which samples feed which rows (its stencil);
2. the compiled evaluator builds the dictionary about ``chunk_size`` samples at a time, the
   strategy reduces it to rows (identity for pointwise differences, window integrals for the weak
   form), and :func:`block_stats` accumulates them into one :class:`~symsbl._regression.gram.GramStats`
   shared by every state equation.

The checks on what enters live here too, once: names, variation of states and inputs, enough rows.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from .._base.checks import enough_rows
from .._base.errors import DataError, LibraryError, expected
from .._base.progress import Progress
from .._data.trajectory import Trajectory, check_magnitude
from .._derivatives.registry import Differentiator, get_differentiator
from .._symbolic.evaluator import Evaluator
from .._symbolic.library import Library
from .band import high_passed
from .gram import GramStats

__all__ = [
    "RegressionStats",
    "regression_stats",
    "block_stats",
    "as_trajectories",
    "library_columns",
    "check_variation",
    "check_inputs_vary",
    "check_representable",
]


@dataclass(frozen=True)
class RegressionStats:
    """Sufficient statistics of one identification problem.

    Attributes
    ----------
    stats : GramStats
        ``D^T D``, ``D^T Y`` ... over all regression rows of all trajectories.
    library : Library
        The candidate library (columns of D).
    state_names, input_names : tuple of str
        Targets (one per state) and inputs.
    derivative : Differentiator
        The derivative strategy used (resolved).
    output_names : tuple of str
        Algebraic outputs, regressed as they are on the library: their targets follow the states'.
    derivatives : tuple of (str, str)
        ``(state, column)``: states whose derivative a column measures (an accelerometer), their target.
    band : float
        Cut-off (Hz) of the high-pass on the rows (see :mod:`.band`); 0: none.
    """

    stats: GramStats
    library: Library
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    derivative: Differentiator
    output_names: tuple[str, ...] = ()
    derivatives: tuple = ()
    band: float = 0.0

    @property
    def target_names(self) -> tuple[str, ...]:
        """The targets in order: every state's derivative, then every algebraic output."""
        return self.state_names + self.output_names

    @property
    def targets(self) -> dict:
        """The keywords of :func:`regression_stats` that give the same targets on other records."""
        return {
            "states": self.state_names,
            "derivatives": dict(self.derivatives),
            "outputs": self.output_names,
            "band": self.band,
        }


def as_trajectories(data) -> list[Trajectory]:
    """``data`` (a Trajectory or a non-empty list of them with the same names) as a list."""
    if isinstance(data, Trajectory):
        return [data]
    if isinstance(data, (list, tuple)) and data and all(isinstance(d, Trajectory) for d in data):
        names = {(d.state_names, d.input_names) for d in data}
        if len(names) > 1:
            got = "; ".join(f"states={s}, inputs={i}" for s, i in sorted(names))
            raise DataError(expected("data", "trajectories with the same state and input names", got, raw=True))
        return list(data)
    raise DataError(
        expected(
            "data",
            "a Trajectory or a non-empty list of Trajectories",
            type(data).__name__,
            "read files with symsbl.read_trajectory",
            raw=True,
        )
    )


def library_columns(state_names: Sequence[str], input_names: Sequence[str], library: Library) -> list[int]:
    """Positions of the library's variables among ``states + inputs`` (the data's column order)."""
    available = list(state_names) + list(input_names)
    missing = [n for n in library.variable_names if n not in available]
    if missing:
        raise LibraryError(
            expected(
                "library",
                f"variables named like the data's states {list(state_names)} and inputs {list(input_names)}",
                f"a library that also uses {missing}",
                "declare the library with symbols named like the columns",
                raw=True,
            )
        )
    return [available.index(v) for v in library.variable_names]


def check_variation(names: Sequence[str], low: np.ndarray, high: np.ndarray, what: str = "state") -> None:
    """Refuse a column whose range ``[low, high]`` shows no variation (a constant or dead channel)."""
    for name, lo, hi in zip(names, low, high):
        scale = max(abs(lo), abs(hi), 1e-300)
        if hi - lo <= 1e-12 * scale:
            fix = (
                "remove it from the states or record a response in which it moves"
                if what == "state"
                else "remove it from the inputs (a dead sensor?); a free decay needs no input column"
            )
            raise DataError(expected(f"{what} {name!r}", "a column that varies", f"a constant {lo:.6g}", fix, raw=True))


#: Squared magnitudes a dictionary column may reach, so that its Gram entries stay normal doubles.
SQUARE_RANGE = (1e-290, 1e290)


def check_representable(
    trajectories, columns, library: Library, evaluator: Evaluator, probe: int = 1024, n_states: int | None = None
) -> None:
    """Refuse data in units that put a library column's squares outside :data:`SQUARE_RANGE`: they would
    underflow (x**3 of 1e-60 silently dropped) or overflow in the Gram matrix. Probed on at most ``probe``
    rows of each record (its first ``n_states`` state columns, default all, then its inputs)."""
    for traj, cols in zip(trajectories, columns):
        Z = np.column_stack([traj.states[:, :n_states], traj.inputs])[:, cols]
        rows = Z[np.unique(np.linspace(0, len(Z) - 1, min(probe, len(Z))).astype(int))]
        with np.errstate(over="ignore", under="ignore", invalid="ignore"):
            D = evaluator.evaluate(rows)
            mean_square = np.mean(np.square(D), axis=0)
            top = np.max(np.abs(D), axis=0)
            rms = top * np.sqrt(np.mean(np.square(D / np.where(top > 0, top, 1.0)), axis=0))  # without under/overflow
        bad = np.flatnonzero((top > 0) & ~((mean_square > SQUARE_RANGE[0]) & (mean_square < SQUARE_RANGE[1])))
        if bad.size:
            j = int(bad[0])
            raise DataError(
                expected(
                    f"term {library.names[j]!r}",
                    "values whose squares a double holds (a root mean square between 1e-145 and 1e145)",
                    f"{rms[j]:.3g} on this record",
                    "express the states and inputs in other units, or lower the degree",
                    raw=True,
                )
            )


def check_inputs_vary(traj: Trajectory, library: Library) -> None:
    """Refuse an input the library uses that is constant: its coefficient cannot be identified."""
    used = [n for n in traj.input_names if n in library.variable_names]
    if used:
        cols = np.column_stack([traj.column(n) for n in used])
        check_variation(used, cols.min(axis=0), cols.max(axis=0), "input")


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


def block_stats(
    X: np.ndarray,
    Z: np.ndarray,
    r0: int,
    r1: int,
    diff: Differentiator,
    evaluator: Evaluator,
    h: float,
    chunk_size: int,
    bar: Progress | None = None,
    measured: np.ndarray | None = None,
    replaced: tuple = (),
    band: float = 0.0,
) -> GramStats:
    """Statistics of rows ``r0:r1`` of a block of samples, evaluating about ``chunk_size`` samples at a time.

    Parameters
    ----------
    X : ndarray, shape (n, n_states)
        The block's states (with the halo its rows need).
    Z : ndarray, shape (n, n_variables)
        The block's columns in the library's variable order.
    r0, r1 : int
        The rows of the block to reduce (local to the block).
    diff : Differentiator
        A resolved strategy.
    evaluator : Evaluator
    h : float
        Sample interval.
    chunk_size : int
        Samples per dictionary evaluation.
    bar : Progress, optional
        Counts rows as they are reduced.
    measured : ndarray, shape (n, n_measured), optional
        Columns whose rows are targets as they are: the measured derivatives of the states at ``replaced``
        (their targets replaced), then the algebraic outputs (targets appended).
    replaced : tuple of int
        The states whose targets the first ``len(replaced)`` columns of ``measured`` replace.
    band : float
        Cut-off (Hz) of the high-pass on every column of the rows (see :mod:`.band`); 0: none.
    """
    Y = diff.targets(np.arange(len(X)) * h, X)
    if measured is not None and measured.shape[1]:
        direct = diff.reduce(measured)  # the window averages (or samples) that pair with the dictionary's rows
        Y = np.array(Y, dtype=float)
        Y[:, list(replaced)] = direct[:, : len(replaced)]
        Y = np.column_stack([Y, direct[:, len(replaced) :]])
    stencil = diff.stencil
    step = max(1, chunk_size // stencil.stride) if stencil.stride else chunk_size

    def slabs():
        for a in range(r0, r1, step):
            b = min(a + step, r1)
            s0, s1 = stencil.sample_span(a, b)
            yield diff.reduce(evaluator.evaluate(Z[s0:s1]))[-(b - a) :], Y[a:b]
            if bar is not None:
                bar.update(b - a)

    try:
        return GramStats.from_chunks(
            high_passed(_regroup(slabs(), chunk_size), band, 1.0 / (h * (stencil.stride or 1)))
        )
    except DataError:
        _undefined_term(Z, evaluator, chunk_size)  # the Gram's check names no term: find it where it failed
        raise


def _undefined_term(Z: np.ndarray, evaluator: Evaluator, chunk_size: int) -> None:
    """Refuse, by name, the first library term that is not finite on the samples ``Z`` (a square root of a level
    that noise takes below zero); return where every term is finite."""
    names = evaluator.library.variable_names
    for a in range(0, len(Z), chunk_size):
        with np.errstate(all="ignore"):
            D = evaluator.evaluate(Z[a : a + chunk_size])
        bad = ~np.isfinite(D)
        if bad.any():
            j = int(np.flatnonzero(bad.any(axis=0))[0])
            i = int(np.flatnonzero(bad[:, j])[0])
            where = ", ".join(f"{n} = {v:.6g}" for n, v in zip(names, Z[a + i]))
            raise DataError(
                expected(
                    f"term {evaluator.library.names[j]!r}",
                    "a term defined on every sample",
                    f"{D[i, j]} where {where}",
                    "leave the term out of the library, or clean the record where it is undefined",
                    raw=True,
                )
            )


def regression_stats(
    data,
    library: Library,
    *,
    derivative="weak",
    chunk_size: int = 4096,
    jit="auto",
    states=None,
    derivatives=None,
    outputs=(),
    band: float = 0.0,
) -> RegressionStats:
    """Accumulate the regression statistics of ``data`` over ``library`` chunk by chunk.

    Parameters
    ----------
    data : Trajectory or list of Trajectory
        Sampled states (and inputs); several trajectories add their rows.
    library : Library
        Candidate terms; its variables must be named like the data's states and inputs.
    derivative : str or Differentiator
        ``"weak"`` (default), ``"central"``, ``"point"``, ``"savgol"`` or a strategy instance.
    chunk_size : int
        Samples per chunk: memory is ``O(chunk_size * n_terms + n_terms^2)`` whatever the length.
    jit : {"auto", True, False}
        Compile the dictionary with a C compiler when available.
    states : sequence of str, optional
        The state columns (default: every column that is not named in ``derivatives`` or ``outputs``).
    derivatives : mapping of str to str, optional
        ``{state: column}``: a column that measures the state's derivative (an accelerometer on a velocity) is
        its target, reduced like the dictionary's rows, instead of the derivative the strategy estimates.
    outputs : sequence of str
        Columns regressed as they are on the library (algebraic outputs: a force cell); their targets follow
        the states'.
    band : float
        Cut-off (Hz) of a high-pass on every column of the rows, both sides alike; 0 (default): none. ``identify``
        passes the lower band edge of the accelerations a position or velocity was integrated from (see
        :mod:`.band`).

    Examples
    --------
    >>> import symsbl
    >>> x1, x2, F = symsbl.symbols("x1 x2 F")
    >>> duffing = symsbl.systems.duffing()   # x1'' + 20 x1' + 1e4 x1 + 1e9 x1^3 = F
    >>> train = symsbl.simulate(duffing, symsbl.time_grid(1.0, 8192), inputs=symsbl.Sine(100.0, 10.0))
    >>> train = train.with_noise(0.004, seed=0)  # 0.4 % of each state's standard deviation
    >>> library = symsbl.polynomial([x1, x2], 3) + symsbl.inputs([F])
    >>> problem = symsbl.regression_stats(train, library)
    >>> problem.derivative, problem.stats.n_samples, problem.stats.n_terms
    (WeakForm(window=44, power=4, overlap=1), 186, 11)
    """
    trajectories = as_trajectories(data)
    if not isinstance(library, Library):
        raise LibraryError(expected("library", "a symsbl Library", type(library).__name__, raw=True))
    derivatives = dict(derivatives or {})
    outputs = tuple(outputs)
    names, direct = _target_columns(trajectories[0], states, derivatives, outputs)
    replaced = tuple(names.index(n) for n in names if n in derivatives)
    trajectories = [tr.with_states(list(names) + direct) for tr in trajectories]
    for traj in trajectories:
        check_magnitude(traj)
    longest = max(trajectories, key=lambda tr: tr.n_samples)
    n_states = len(names)
    diff = get_differentiator(derivative).resolve(longest.t, longest.states[:, :n_states], n_terms=len(library))
    columns = []
    for traj in trajectories:  # validate everything before the expensive pass
        check_variation(traj.state_names, traj.states.min(axis=0), traj.states.max(axis=0))
        check_inputs_vary(traj, library)
        columns.append(library_columns(names, traj.input_names, library))
    n_rows = sum(diff.n_rows(traj.n_samples) for traj in trajectories)
    enough_rows(n_rows, len(library), f"{len(trajectories)} record(s) with {type(diff).__name__}")
    evaluator = Evaluator(library, chunk_size=chunk_size, jit=jit)
    check_representable(trajectories, columns, library, evaluator, n_states=n_states)
    with Progress(f"dictionary ({len(library)} terms) and Gram", total=n_rows, unit="rows") as bar:
        total = _accumulate(trajectories, columns, n_states, diff, evaluator, chunk_size, bar, replaced, band)
    return RegressionStats(
        total,
        library,
        names,
        trajectories[0].input_names,
        diff,
        outputs,
        tuple((n, derivatives[n]) for n in names if n in derivatives),
        band,
    )


def _target_columns(first: Trajectory, states, derivatives: dict, outputs: tuple) -> tuple[tuple, list]:
    """The state columns and the columns that are targets as they are (measured derivatives, then outputs)."""
    names = (
        tuple(n for n in first.state_names if n not in set(derivatives.values()) | set(outputs))
        if states is None
        else tuple(states)
    )
    direct = [derivatives[n] for n in names if n in derivatives] + list(outputs)
    absent = [n for n in list(names) + direct if n not in first.state_names]
    if absent or set(derivatives) - set(names):
        raise DataError(
            expected(
                "data",
                f"columns for the states {list(names)}, the derivatives {derivatives} and the outputs {list(outputs)}",
                f"columns {list(first.state_names)}",
                raw=True,
            )
        )
    return names, direct


def _accumulate(
    trajectories,
    columns,
    n_states: int,
    diff: Differentiator,
    evaluator: Evaluator,
    chunk_size: int,
    bar,
    replaced,
    band: float = 0.0,
) -> GramStats:
    """The statistics of every record's rows, summed."""
    total = None
    for traj, cols in zip(trajectories, columns):
        Z = np.ascontiguousarray(np.column_stack([traj.states[:, :n_states], traj.inputs])[:, cols])
        r0, r1 = diff.stencil.rows(traj.n_samples, True, True)
        if r1 <= r0:
            continue
        part = block_stats(
            traj.states[:, :n_states],
            Z,
            r0,
            r1,
            diff,
            evaluator,
            traj.dt,
            chunk_size,
            bar,
            measured=traj.states[:, n_states:],
            replaced=replaced,
            band=band,
        )
        total = part if total is None else total + part
    assert total is not None  # enough_rows() refused records without a row
    return total
