"""Trajectories (sampled states and inputs) and their validation, reading and writing.

A :class:`Trajectory` is the one container for data in symsbl, simulated or measured: a uniform time
grid, the states on it and the inputs on it, with names. It is validated once, where data enters
(:func:`validate`), so everything downstream may assume a clean, uniformly sampled record.

Files are read and written by :mod:`symsbl._data.io`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .._base.checks import number
from .._base.errors import DataError, expected
from .excitation import noise_std, period

__all__ = ["Trajectory", "validate", "check_magnitude", "noise_levels", "TIME_RTOL", "MAX_MAGNITUDE"]

#: Largest relative deviation of a time step from the mean step accepted as "uniform".
#: Real loggers jitter (the EMPS record deviates by 2.4e-5); a dropped sample deviates by 1.
TIME_RTOL = 1e-3

#: Largest magnitude accepted in a state or input column: the squares and cubes of a dictionary
#: overflow double precision beyond about 1e100 (1e300 data would "diverge" at once).
MAX_MAGNITUDE = 1e100

_NOISE_CHANNELS = ("states", "inputs", "all")


def _as_matrix(values, n_cols: int, what: str) -> np.ndarray:
    """Return ``values`` as a float64 ``(n_samples, n_cols)`` array (1-D allowed when ``n_cols == 1``)."""
    try:
        arr = np.array(values, dtype=float)
    except (TypeError, ValueError):
        raise DataError(expected(what, "numbers", type(values).__name__, raw=True)) from None
    if arr.ndim == 1 and n_cols == 1:
        arr = arr[:, None]
    if arr.ndim == 1 and n_cols == 0 and arr.size == 0:
        arr = arr.reshape(0, 0)
    if arr.ndim != 2 or arr.shape[1] != n_cols:
        raise DataError(
            expected(what, f"shape (n_samples, {n_cols}), one column per name", f"shape {arr.shape}", raw=True)
        )
    return arr


def _check_names(names: Sequence[str], what: str) -> tuple[str, ...]:
    names = tuple(names)
    for name in names:
        if not isinstance(name, str) or not name:
            raise DataError(expected(what, "non-empty strings", name))
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise DataError(expected(what, "distinct names", list(names), f"rename the repeated {dupes}"))
    return names


def _check_values(pre: str, names, columns) -> None:
    for name, col in zip(names, columns):
        bad = np.flatnonzero(~np.isfinite(col))
        if bad.size:
            raise DataError(
                expected(
                    f"{pre}column {name!r}",
                    "finite values",
                    f"{col[bad[0]]} at row {bad[0]} ({bad.size} non-finite in total)",
                    "remove or repair those rows",
                    raw=True,
                )
            )


def check_magnitude(traj: Trajectory, source: str = "") -> None:
    """Refuse states or inputs beyond :data:`MAX_MAGNITUDE` where data enter an identification or a
    validation (a diverged simulation may hold such values; measured data may not)."""
    pre = f"{source}: " if source else ""
    for name, col in zip(traj.state_names + traj.input_names, (*traj.states.T, *traj.inputs.T)):
        big = np.flatnonzero(np.abs(col) > MAX_MAGNITUDE)
        if big.size:
            raise DataError(
                expected(
                    f"{pre}column {name!r}",
                    f"magnitudes below {MAX_MAGNITUDE:g}",
                    f"{col[big[0]]:g} at row {big[0]}",
                    "rescale the column (other units)",
                    raw=True,
                )
            )


def _check_time(pre: str, t: np.ndarray, time_rtol: float) -> None:
    steps = np.diff(t)
    bad = np.flatnonzero(steps <= 0)
    if bad.size:
        i = bad[0] + 1
        raise DataError(
            expected(
                f"{pre}time",
                "strictly increasing values",
                f"t = {float(t[i])!r} at row {i} after t = {float(t[i - 1])!r}",
                "sort the rows or pass --fs/fs for a rounded time column",
                raw=True,
            )
        )
    dt = (t[-1] - t[0]) / (t.size - 1)
    dev = np.abs(steps - dt) / dt
    worst = int(np.argmax(dev))
    if dev[worst] > time_rtol:
        raise DataError(
            expected(
                f"{pre}time",
                f"uniform sampling (steps within {time_rtol:g} of the mean step {float(dt)!r})",
                f"a step of {float(steps[worst])!r} before row {worst + 1} (relative deviation {dev[worst]:.3g})",
                "resample onto a uniform grid, or pass --fs/fs when the time column is only rounded",
                raw=True,
            )
        )


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
        raise DataError(
            expected(
                "names",
                "state and input names other than 't' (the time column)",
                list(state_names + input_names),
                "rename that state or input",
            )
        )
    try:
        t = np.array(t, dtype=float)
    except (TypeError, ValueError):
        raise DataError(expected(f"{pre}time", "numbers", type(t).__name__, raw=True)) from None
    if t.ndim != 1:
        raise DataError(expected(f"{pre}time", "shape (n_samples,)", f"shape {t.shape}", raw=True))
    states = _as_matrix(states, len(state_names), pre + "states")
    inputs = _as_matrix(np.empty((t.size, 0)) if inputs is None else inputs, len(input_names), pre + "inputs")
    for what, arr in (("states", states), ("inputs", inputs)):
        if arr.shape[0] != t.size:
            raise DataError(
                expected(pre + what, f"one row per time sample ({t.size})", f"{arr.shape[0]} rows", raw=True)
            )
    if t.size < 2:
        raise DataError(expected(pre + "trajectory", "at least 2 samples", f"{t.size}", raw=True))
    _check_values(pre, ("time",) + state_names + input_names, (t, *states.T, *inputs.T))
    _check_time(pre, t, time_rtol)
    return t, states, inputs


def _frozen(arr: np.ndarray) -> np.ndarray:
    arr = np.ascontiguousarray(arr, dtype=float)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False, repr=False, init=False)
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
        Set by :func:`symsbl.simulate` with ``on_divergence="truncate"`` when the simulation
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
    inputs: np.ndarray
    state_names: tuple[str, ...] = ()
    input_names: tuple[str, ...] = ()
    diverged_at: float | None = field(default=None)

    # Written out because ``inputs`` accepts None but always holds an array once validated.
    def __init__(
        self,
        t: np.ndarray,
        states: np.ndarray,
        inputs: np.ndarray | None = None,
        state_names: Sequence[str] = (),
        input_names: Sequence[str] = (),
        diverged_at: float | None = None,
    ) -> None:
        t, states, inputs = validate(t, states, inputs, state_names, input_names)
        object.__setattr__(self, "t", _frozen(t))
        object.__setattr__(self, "states", _frozen(states))
        object.__setattr__(self, "inputs", _frozen(inputs))
        object.__setattr__(self, "state_names", tuple(state_names))
        object.__setattr__(self, "input_names", tuple(input_names))
        object.__setattr__(self, "diverged_at", diverged_at)

    def __repr__(self) -> str:
        span = f"{self.t[0]:.6g} to {self.t[-1]:.6g} s"
        end = "" if self.diverged_at is None else f", diverged_at={self.diverged_at:.6g}"
        return (
            f"Trajectory({self.n_samples} samples, {span} at {self.fs:.6g} Hz, states={list(self.state_names)}, "
            f"inputs={list(self.input_names)}{end})"
        )

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
        raise DataError(expected("column", f"one of {['t', *self.state_names, *self.input_names]}", name))

    def with_states(self, names: Sequence[str]) -> Trajectory:
        """The record with the states ``names`` (a subset, in that order); the inputs unchanged."""
        missing = [n for n in names if n not in self.state_names]
        if missing or not names:
            raise DataError(expected("names", f"states among {list(self.state_names)}", list(names)))
        if tuple(names) == self.state_names:
            return self
        X = np.column_stack([self.column(n) for n in names])
        return Trajectory(self.t, X, self.inputs, tuple(names), self.input_names)

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
            raise DataError(expected("channels", f"one of {list(_NOISE_CHANNELS)}", channels))
        number("rel_std", rel_std, low=0.0, error=DataError)
        rng = np.random.default_rng(seed)

        def noisy(arr):
            return arr + rel_std * arr.std(axis=0) * rng.standard_normal(arr.shape)

        states = noisy(self.states) if channels in ("states", "all") else self.states
        inputs = noisy(self.inputs) if channels in ("inputs", "all") else self.inputs
        return Trajectory(self.t, states, inputs, self.state_names, self.input_names)


def noise_levels(traj: Trajectory) -> dict[str, float]:
    """White-noise standard deviation of each state and input, told from the excitation.

    Where the inputs repeat, half the variance of the difference of two periods; and in the bands of each
    signal's spectrum that the excitation leaves quiet; the smaller of the two (each an upper bound). Third
    differences (``std(diff(x, 3)) = sqrt(20) sigma``) read a signal sampled near its bandwidth as noise: 12-16
    times the noise on a multisine to 0.35 of the sampling rate, 2-4 times on a 10 Hz sine sampled at 400 Hz;
    the quiet bands are within 20 % on both, and read up to 12 % low on records of 1000 samples (the quietest
    of few bands).

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
    [1.0, 0.99]
    """
    if not isinstance(traj, Trajectory) or traj.n_samples < 4:
        got = f"{traj.n_samples} samples" if isinstance(traj, Trajectory) else type(traj).__name__
        raise DataError(expected("traj", "a Trajectory of at least 4 samples to estimate its noise", got, raw=True))
    length = period(traj.inputs) if traj.inputs.size else None
    return {name: noise_std(traj.column(name), length) for name in list(traj.state_names) + list(traj.input_names)}


def third_difference_std(x: np.ndarray) -> float:
    """White-noise standard deviation of a sampled signal from its third differences (see :func:`noise_levels`):
    ``std(diff(x, 3)) = sqrt(20) sigma``, the standard deviation taken robustly (median absolute deviation)."""
    d3 = np.diff(np.asarray(x, dtype=float), 3)
    return float(1.4826 * np.median(np.abs(d3 - np.median(d3))) / math.sqrt(20.0))
