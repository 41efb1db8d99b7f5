"""Trajectories (sampled states and inputs) and their validation, reading and writing.

A :class:`Trajectory` is the one container for data in symsbl, simulated or measured: a uniform time
grid, the states on it and the inputs on it, with names. It is validated once, where data enters
(:func:`validate`), so everything downstream may assume a clean, uniformly sampled record.

Files: CSV with a header row, NumPy ``.npz`` and MATLAB ``.mat`` (via :mod:`scipy.io`), one named
column per signal. Input files are only ever opened for reading.
"""

from __future__ import annotations

import csv
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from symsbl.errors import DataError

__all__ = ["Trajectory", "validate", "noise_levels", "read_trajectory", "write_trajectory"]

#: Largest relative deviation of a time step from the mean step accepted as "uniform".
#: Real loggers jitter (the EMPS record deviates by 2.4e-5); a dropped sample deviates by 1.
TIME_RTOL = 1e-3

_NOISE_CHANNELS = ("states", "inputs", "all")
_MATLAB_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,62}$")


def _as_matrix(values, n_cols: int, what: str) -> np.ndarray:
    """Return ``values`` as a float64 ``(n_samples, n_cols)`` array (1-D allowed when ``n_cols == 1``)."""
    arr = np.array(values, dtype=float)
    if arr.ndim == 1 and n_cols == 1:
        arr = arr[:, None]
    if arr.ndim == 1 and n_cols == 0 and arr.size == 0:
        arr = arr.reshape(0, 0)
    if arr.ndim != 2 or arr.shape[1] != n_cols:
        raise DataError(
            f"{what} must have shape (n_samples, {n_cols}) to match its {n_cols} names; "
            f"received shape {arr.shape}. Pass one column per name."
        )
    return arr


def _check_names(names: Sequence[str], what: str) -> tuple[str, ...]:
    names = tuple(names)
    for name in names:
        if not isinstance(name, str) or not name:
            raise DataError(f"{what} must be non-empty strings; received {name!r}.")
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise DataError(f"{what} must be unique; {dupes} appear more than once. Rename the columns.")
    return names


def validate(
    t,
    states,
    inputs=None,
    state_names: Sequence[str] = (),
    input_names: Sequence[str] = (),
    *,
    time_rtol: float = TIME_RTOL,
    source: str = "",
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Check and normalise the arrays of a trajectory.

    Parameters
    ----------
    t : array_like, shape (n_samples,)
        Sample times, strictly increasing and uniform to within ``time_rtol`` of the mean step.
    states : array_like, shape (n_samples, n_states)
    inputs : array_like, shape (n_samples, n_inputs), optional
        ``None`` means no inputs (``n_inputs == 0``).
    state_names, input_names : sequence of str
        One unique name per column; names may not repeat across states and inputs.
    time_rtol : float
        Largest accepted ``|t[i+1] - t[i] - dt| / dt`` with ``dt`` the mean step.
    source : str
        Prefix for error messages (e.g. a file name).

    Returns
    -------
    t, states, inputs : ndarray
        Float64 copies with shapes ``(n_samples,)``, ``(n_samples, n_states)``, ``(n_samples, n_inputs)``.

    Raises
    ------
    DataError
        Naming the offending column and row: wrong shape, mismatched lengths, fewer than 2 samples,
        non-finite values, time not strictly increasing or not uniform.
    """
    pre = f"{source}: " if source else ""
    state_names = _check_names(state_names, "state names")
    input_names = _check_names(input_names, "input names")
    _check_names(state_names + input_names, "state and input names together")
    if "t" in state_names + input_names:
        raise DataError("'t' is reserved for the time column; rename that state or input.")
    t = np.array(t, dtype=float)
    if t.ndim != 1:
        raise DataError(f"{pre}time must be 1-D with shape (n_samples,); received shape {t.shape}.")
    states = _as_matrix(states, len(state_names), pre + "states")
    inputs = _as_matrix(np.empty((t.size, 0)) if inputs is None else inputs, len(input_names), pre + "inputs")
    for what, arr in (("states", states), ("inputs", inputs)):
        if arr.shape[0] != t.size:
            raise DataError(
                f"{pre}{what} has {arr.shape[0]} rows but time has {t.size} samples; "
                "every column must have one value per time sample."
            )
    if t.size < 2:
        raise DataError(f"{pre}a trajectory needs at least 2 samples; received {t.size}.")
    for name, col in zip(("time",) + state_names + input_names, (t, *states.T, *inputs.T)):
        bad = np.flatnonzero(~np.isfinite(col))
        if bad.size:
            raise DataError(
                f"{pre}column {name!r} has a non-finite value ({col[bad[0]]}) at row {bad[0]} "
                f"({bad.size} non-finite in total); remove or repair those rows."
            )
    steps = np.diff(t)
    bad = np.flatnonzero(steps <= 0)
    if bad.size:
        i = bad[0] + 1
        raise DataError(
            f"{pre}time must be strictly increasing, but at row {i} t = {t[i]!r} follows t = {t[i - 1]!r}."
        )
    dt = (t[-1] - t[0]) / (t.size - 1)
    dev = np.abs(steps - dt) / dt
    worst = int(np.argmax(dev))
    if dev[worst] > time_rtol:
        raise DataError(
            f"{pre}time must be uniformly sampled, but the step before row {worst + 1} is {steps[worst]!r} "
            f"against a mean step of {dt!r} (relative deviation {dev[worst]:.3g} > {time_rtol:g}); "
            "resample onto a uniform grid first."
        )
    return t, states, inputs


def _frozen(arr: np.ndarray) -> np.ndarray:
    arr = np.ascontiguousarray(arr, dtype=float)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False, repr=False)
class Trajectory:
    """Uniformly sampled states and inputs of one experiment (simulated or measured).

    Parameters
    ----------
    t : ndarray, shape (n_samples,)
        Sample times, strictly increasing and uniform.
    states : ndarray, shape (n_samples, n_states)
    inputs : ndarray, shape (n_samples, n_inputs)
        ``n_inputs`` may be 0; ``None`` is accepted and stored as an empty ``(n_samples, 0)`` array.
    state_names, input_names : tuple of str
    diverged_at : float or None
        Set by :func:`symsbl.simulate.simulate` with ``on_divergence="truncate"`` when the simulation
        diverged: the first time at which the state was no longer finite (or the integrator failed).
        The trajectory then ends at the last good sample before it. ``None`` otherwise.

    Notes
    -----
    The arrays are validated by :func:`validate` and stored as read-only float64 copies.

    Examples
    --------
    >>> import numpy as np
    >>> import symsbl
    >>> t = symsbl.time_grid(1.0, 100)
    >>> record = symsbl.Trajectory(t, np.column_stack([np.sin(t), np.cos(t)]), None, ("x1", "x2"))
    >>> record
    Trajectory(101 samples, 0 to 1 s at 100 Hz, states=['x1', 'x2'], inputs=[])
    >>> noisy = record.with_noise(0.01, seed=0)  # 1 % of each state's standard deviation
    >>> np.round(np.std(noisy.states - record.states, axis=0) / np.std(record.states, axis=0), 3)
    array([0.01 , 0.009])
    """

    t: np.ndarray
    states: np.ndarray
    inputs: np.ndarray | None = None
    state_names: tuple[str, ...] = ()
    input_names: tuple[str, ...] = ()
    diverged_at: float | None = field(default=None)

    def __post_init__(self):
        t, states, inputs = validate(self.t, self.states, self.inputs, self.state_names, self.input_names)
        object.__setattr__(self, "t", _frozen(t))
        object.__setattr__(self, "states", _frozen(states))
        object.__setattr__(self, "inputs", _frozen(inputs))
        object.__setattr__(self, "state_names", tuple(self.state_names))
        object.__setattr__(self, "input_names", tuple(self.input_names))

    def __repr__(self) -> str:
        span = f"{self.t[0]:.6g} to {self.t[-1]:.6g} s"
        end = "" if self.diverged_at is None else f", diverged_at={self.diverged_at:.6g}"
        return (f"Trajectory({self.n_samples} samples, {span} at {self.fs:.6g} Hz, states={list(self.state_names)}, "
                f"inputs={list(self.input_names)}{end})")

    @property
    def n_samples(self) -> int:
        """Number of samples."""
        return self.t.size

    @property
    def dt(self) -> float:
        """Mean sample step (s)."""
        return float((self.t[-1] - self.t[0]) / (self.t.size - 1))

    @property
    def fs(self) -> float:
        """Sample rate, ``1 / dt`` (Hz)."""
        return 1.0 / self.dt

    def column(self, name: str) -> np.ndarray:
        """Return the column ``name`` (a state, an input or ``"t"``), shape ``(n_samples,)``."""
        if name in self.state_names:
            return self.states[:, self.state_names.index(name)]
        if name in self.input_names:
            return self.inputs[:, self.input_names.index(name)]
        if name == "t":
            return self.t
        raise DataError(
            f"column {name!r} not found; available columns: {['t', *self.state_names, *self.input_names]}."
        )

    def to_dict(self) -> dict[str, np.ndarray]:
        """Return ``{"t": t, state_name: column, ..., input_name: column, ...}`` (insertion-ordered)."""
        out = {"t": self.t}
        out.update({n: self.states[:, i] for i, n in enumerate(self.state_names)})
        out.update({n: self.inputs[:, i] for i, n in enumerate(self.input_names)})
        return out

    def slice(self, start: int | None = None, stop: int | None = None) -> Trajectory:
        """Return samples ``start:stop`` (Python slice semantics on the sample index) as a new Trajectory."""
        s = slice(start, stop)
        return Trajectory(self.t[s], self.states[s], self.inputs[s], self.state_names, self.input_names)

    def with_noise(self, rel_std: float = 0.004, seed: int = 0, channels: str = "states") -> Trajectory:
        """Return a copy with additive white Gaussian measurement noise.

        Each noisy column gets independent noise with standard deviation ``rel_std * std(column)``, as in
        Fuentes et al. (2019), Sec. 3 (0.4 % of each signal's own standard deviation). A constant column
        stays noise-free.

        Parameters
        ----------
        rel_std : float
            Noise standard deviation relative to each column's standard deviation.
        seed : int
            Seed of ``np.random.default_rng``; the same seed gives the same noise.
        channels : {"states", "inputs", "all"}
            Which columns receive noise. Noise is drawn for the states first, then the inputs.

        Returns
        -------
        Trajectory
        """
        if channels not in _NOISE_CHANNELS:
            raise DataError(f"channels must be one of {list(_NOISE_CHANNELS)}; received {channels!r}.")
        if not np.isfinite(rel_std) or rel_std < 0:
            raise DataError(f"rel_std must be a finite number >= 0; received {rel_std!r}.")
        rng = np.random.default_rng(seed)

        def noisy(arr):
            return arr + rel_std * arr.std(axis=0) * rng.standard_normal(arr.shape)

        states = noisy(self.states) if channels in ("states", "all") else self.states
        inputs = noisy(self.inputs) if channels in ("inputs", "all") else self.inputs
        return Trajectory(self.t, states, inputs, self.state_names, self.input_names)


# ---------------------------------------------------------------------------------------------- files


def noise_levels(traj: Trajectory) -> dict[str, float]:
    """White-noise standard deviation of each state and input, estimated from third differences.

    ``std(diff(x, 3)) = sqrt(20) sigma`` for white noise, while a signal sampled well above its
    bandwidth contributes almost nothing to the third difference; a median absolute deviation
    makes the estimate robust to the rare jumps of a discontinuous signal. A signal sampled near
    its bandwidth leaves some of itself in the third difference, so the estimate errs high.

    Parameters
    ----------
    traj : Trajectory
        At least 4 samples.

    Returns
    -------
    dict of str to float
        Per state and input name, the estimated noise standard deviation in the signal's units.

    Examples
    --------
    >>> import symsbl
    >>> clean = symsbl.simulate(symsbl.systems.duffing(), symsbl.time_grid(1.0, 8192),
    ...                         inputs=symsbl.Sine(100.0, 10.0))
    >>> noisy = clean.with_noise(0.01, seed=0)        # 1 % of each state's standard deviation
    >>> levels = symsbl.noise_levels(noisy)
    >>> added = 0.01 * clean.states.std(axis=0)
    >>> [round(float(levels[name] / sigma), 2) for name, sigma in zip(clean.state_names, added)]
    [0.98, 0.99]
    """
    if not isinstance(traj, Trajectory) or traj.n_samples < 4:
        raise DataError(
            "traj: expected a Trajectory of at least 4 samples to estimate its noise; received "
            + (f"{traj.n_samples} samples." if isinstance(traj, Trajectory) else f"{type(traj).__name__}.")
        )
    out = {}
    for name in list(traj.state_names) + list(traj.input_names):
        d3 = np.diff(traj.column(name), 3)
        out[name] = float(1.4826 * np.median(np.abs(d3 - np.median(d3))) / math.sqrt(20.0))
    return out


def _read_csv(path: Path) -> dict[str, np.ndarray]:
    with path.open(newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise DataError(f"{path}: the file is empty; expected a header row of column names.")
    header = [h.strip() for h in rows[0]]
    body = [r for r in rows[1:] if r and any(c.strip() for c in r)]
    columns: dict[str, list[float]] = {h: [] for h in header}
    for lineno, row in enumerate(body, start=2):
        if len(row) != len(header):
            raise DataError(
                f"{path}: line {lineno} has {len(row)} fields but the header has {len(header)}; "
                "every row needs one value per column."
            )
        for name, cell in zip(header, row):
            try:
                columns[name].append(float(cell))
            except ValueError:
                raise DataError(
                    f"{path}: column {name!r} at line {lineno} holds {cell!r}, which is not a number."
                ) from None
    return {name: np.array(vals, dtype=float) for name, vals in columns.items()}


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: np.asarray(z[k]) for k in z.files}


def _read_mat(path: Path) -> dict[str, np.ndarray]:
    from scipy.io import loadmat

    return {k: np.asarray(v) for k, v in loadmat(str(path)).items() if not k.startswith("__")}


def _write_csv(columns: Mapping[str, np.ndarray], path: Path) -> None:
    for name in columns:
        if any(ch in name for ch in ',"\n\r'):
            raise DataError(f"column name {name!r} cannot be written to CSV (contains a comma, quote or newline).")
    table = np.column_stack(list(columns.values()))
    np.savetxt(path, table, fmt="%.17g", delimiter=",", header=",".join(columns), comments="")


def _write_npz(columns: Mapping[str, np.ndarray], path: Path) -> None:
    with path.open("wb") as fh:
        np.savez(fh, **columns)


def _write_mat(columns: Mapping[str, np.ndarray], path: Path) -> None:
    from scipy.io import savemat

    for name in columns:
        if not _MATLAB_NAME.match(name):
            raise DataError(
                f"column name {name!r} is not a valid MATLAB variable name (a letter, then letters, digits or "
                "underscores, at most 63 characters); rename it or write .csv/.npz instead."
            )
    savemat(str(path), {k: np.asarray(v)[:, None] for k, v in columns.items()})


_FORMATS = {".csv": (_read_csv, _write_csv), ".npz": (_read_npz, _write_npz), ".mat": (_read_mat, _write_mat)}


def _format(path: Path):
    try:
        return _FORMATS[path.suffix.lower()]
    except KeyError:
        raise DataError(
            f"unsupported file extension {path.suffix!r} for {path}; valid extensions: {sorted(_FORMATS)}."
        ) from None


def _vector(columns: Mapping[str, np.ndarray], name: str, path: Path) -> np.ndarray:
    if name not in columns:
        raise DataError(f"{path}: column {name!r} not found; available columns: {sorted(columns)}.")
    arr = np.asarray(columns[name])
    if arr.ndim == 2 and 1 in arr.shape:  # MATLAB stores vectors as 1xN or Nx1
        arr = arr.ravel()
    if arr.ndim != 1 or not np.issubdtype(arr.dtype, np.number):
        raise DataError(
            f"{path}: column {name!r} must be a numeric vector (N, 1xN or Nx1); "
            f"received shape {arr.shape} and dtype {arr.dtype}."
        )
    return arr.astype(float)


def read_trajectory(
    path: str | Path,
    *,
    states: Sequence[str],
    inputs: Sequence[str] = (),
    time: str | None = "t",
    fs: float | None = None,
) -> Trajectory:
    """Read a trajectory from a ``.csv`` (header row), ``.npz`` or ``.mat`` file.

    Parameters
    ----------
    path : str or Path
        The file; it is only read.
    states, inputs : sequence of str
        Column (variable) names to use as states and as inputs, in this order.
    time : str or None
        Name of the time column. ``None`` builds ``t = arange(n) / fs`` instead (then ``fs`` is required).
    fs : float, optional
        Sample rate in Hz, only used (and required) when ``time`` is None.

    Returns
    -------
    Trajectory

    Raises
    ------
    DataError
        Unsupported extension, a missing column (the message lists those available), a column that is
        not a vector, columns of different lengths, too few samples, non-finite values or a time column
        that is not strictly increasing and uniform (row named).

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> import symsbl
    >>> t = symsbl.time_grid(1.0, 100)
    >>> record = symsbl.Trajectory(t, np.column_stack([np.sin(t), np.cos(t)]), np.cos(3 * t), ("x1", "x2"), ("F",))
    >>> path = os.path.join(tempfile.mkdtemp(), "record.csv")
    >>> symsbl.write_trajectory(record, path)
    >>> back = symsbl.read_trajectory(path, states=["x1", "x2"], inputs=["F"])
    >>> back.state_names, back.input_names, bool(np.allclose(back.states, record.states))
    (('x1', 'x2'), ('F',), True)
    """
    path = Path(path)
    reader, _ = _format(path)
    if not path.is_file():
        raise DataError(f"file {path} does not exist.")
    columns = reader(path)
    state_names, input_names = tuple(states), tuple(inputs)
    if not state_names:
        raise DataError("states must name at least one column; received an empty list.")
    data = {name: _vector(columns, name, path) for name in state_names + input_names}
    lengths = {name: v.size for name, v in data.items()}
    if len(set(lengths.values())) > 1:
        raise DataError(f"{path}: columns have different lengths {lengths}; all must have one value per sample.")
    n = next(iter(lengths.values()))
    if time is None:
        if fs is None or not np.isfinite(fs) or fs <= 0:
            raise DataError(f"time=None needs a positive sample rate fs in Hz; received fs={fs!r}.")
        t = np.arange(n) / float(fs)
    else:
        t = _vector(columns, time, path)
        if t.size != n:
            raise DataError(
                f"{path}: time column {time!r} has {t.size} samples but the data columns have {n}."
            )
    st = np.column_stack([data[k] for k in state_names])
    ip = np.column_stack([data[k] for k in input_names]) if input_names else np.empty((n, 0))
    t, st, ip = validate(t, st, ip, state_names, input_names, source=str(path))
    return Trajectory(t, st, ip, state_names, input_names)


def write_trajectory(traj: Trajectory, path: str | Path) -> None:
    """Write ``traj`` to ``.csv`` (``%.17g``, exact round trip), ``.npz`` or ``.mat`` (Nx1 columns).

    The columns are ``t``, the states and the inputs, under their names; read them back with
    ``read_trajectory(path, states=traj.state_names, inputs=traj.input_names)``.

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> import symsbl
    >>> t = symsbl.time_grid(1.0, 100)
    >>> record = symsbl.Trajectory(t, np.sin(t)[:, None], None, ("x",))
    >>> path = os.path.join(tempfile.mkdtemp(), "record.npz")
    >>> symsbl.write_trajectory(record, path)
    >>> sorted(np.load(path).files)
    ['t', 'x']
    """
    path = Path(path)
    _, writer = _format(path)
    writer(traj.to_dict(), path)
