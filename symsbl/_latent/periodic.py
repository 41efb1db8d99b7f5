"""A record of whole periods of a periodic input (or a transient record): its average, band-limited derivatives
and their noise.

A latent state cannot be regressed; it has to be reconstructed from what is measured, and a
periodic steady state makes that exact: any linear filter commutes with ``d/dt`` on a periodic
signal, so derivatives are spectral (no window, no edge), and the scatter of the periods about
their average measures the noise of every DFT bin *independently of any model*. That noise then
propagates through every linear operator (a derivative, a force balance) by Parseval, and the
output-error branches of :mod:`symsbl._latent` are compared on the same known noise variance.

The period is the smallest lag at which the input repeats itself (relative RMS difference below
:data:`REPEAT_TOL`, found for every lag at once from the autocorrelation); the record is cut to its
last whole periods, and leading periods that differ from the others by more than the noise (a
transient) are dropped.

A record whose input does not repeat (a random input, a sweep, fewer than :data:`MIN_PERIODS`
periods) is taken whole: the line through its end points is removed before the spectral operators
and put back after (a band-limited zero-phase filter leaves a line unchanged), the samples within
:data:`EDGE_CYCLES` cycles of the filters' narrowest transition band from either end are left out
of every regression (there the spectral operators see the record's wrap-around), and the noise is
the white floor of the output's spectrum above the band (third differences when there is no room).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from .._base.errors import DataError, expected
from .._data.trajectory import third_difference_std

__all__ = ["Periods", "Spectra", "split_periods", "whole_record", "raised_cosine", "REPEAT_TOL", "MIN_PERIODS"]

#: Relative RMS difference ``||u(t + T) - u(t)|| / ||u||`` below which the input repeats with period ``T``.
REPEAT_TOL = 1e-3
#: Whole periods needed: the noise of the average is estimated from their scatter.
MIN_PERIODS = 3
#: Excited frequencies needed (each gives two equations for the three skeleton parameters and the law).
MIN_LINES = 8
#: Samples left out at each end of a transient record, in cycles of the narrowest transition band.
EDGE_CYCLES = 10.0
#: A leading period whose distance to the mean of the others exceeds this many times the distance the
#: noise alone explains is a transient, and is dropped.
TRANSIENT_RATIO = 3.0


@dataclass(frozen=True)
class Periods:
    """The whole periods of a record.

    Attributes
    ----------
    fs : float
        Sample rate (Hz).
    U, Y : ndarray, shape (n_periods, n_per_period)
        Input and output, one period per row.
    start : int
        Index in the record of the first sample used.
    dropped : int
        Leading whole periods dropped as a transient.
    """

    fs: float
    U: np.ndarray
    Y: np.ndarray
    start: int
    dropped: int

    @property
    def n_periods(self) -> int:
        return int(self.Y.shape[0])

    @property
    def length(self) -> int:
        """Samples per period."""
        return int(self.Y.shape[1])


def _repeat_lag(u: np.ndarray) -> int | None:
    """The smallest lag ``L`` (at most ``n / MIN_PERIODS``) with ``||u[L:] - u[:-L]|| <= REPEAT_TOL ||u||``."""
    n = u.size
    x = u - u.mean()
    spectrum = np.fft.rfft(x, 2 * n)
    corr = np.fft.irfft(np.abs(spectrum) ** 2, 2 * n)[:n]  # sum_i x[i] x[i + L]
    c2 = np.concatenate([[0.0], np.cumsum(x * x)])
    lags = np.arange(1, n // MIN_PERIODS + 1)
    head = c2[n - lags]  # sum of x[:-L]^2
    tail = c2[n] - c2[lags]  # sum of x[L:]^2
    distance = np.maximum(head + tail - 2 * corr[lags], 0.0)
    ok = np.flatnonzero(distance <= REPEAT_TOL**2 * 0.5 * (head + tail))
    ok = ok[lags[ok] >= 4]
    return int(lags[ok[0]]) if ok.size else None


def split_periods(t: np.ndarray, u: np.ndarray, y: np.ndarray) -> Periods | None:
    """Cut a record into the whole periods of its input.

    Parameters
    ----------
    t : ndarray, shape (n_samples,)
        Uniformly sampled times.
    u, y : ndarray, shape (n_samples,)
        The input and the measured position.

    Returns
    -------
    Periods or None
        None when the input does not repeat over at least :data:`MIN_PERIODS` whole periods.

    Raises
    ------
    DataError
        The time grid is not uniform.
    """
    dt = _uniform_step(t)
    lag = _repeat_lag(np.asarray(u, dtype=float))
    if lag is None:
        return None
    n_periods = u.size // lag
    start = u.size - n_periods * lag
    U = np.asarray(u[start:], dtype=float).reshape(n_periods, lag)
    Y = np.asarray(y[start:], dtype=float).reshape(n_periods, lag)
    dropped = 0
    while Y.shape[0] > MIN_PERIODS and _is_transient(Y):
        U, Y, start, dropped = U[1:], Y[1:], start + lag, dropped + 1
    return Periods(fs=float(1.0 / dt), U=U, Y=Y, start=int(start), dropped=dropped)


def whole_record(t: np.ndarray, u: np.ndarray, y: np.ndarray) -> Periods:
    """A record taken whole, as one 'period' (see :class:`Spectra` with ``periodic=False``)."""
    dt = _uniform_step(t)
    return Periods(
        fs=float(1.0 / dt),
        U=np.asarray(u, dtype=float)[None, :],
        Y=np.asarray(y, dtype=float)[None, :],
        start=0,
        dropped=0,
    )


def _uniform_step(t: np.ndarray) -> float:
    dt = np.diff(t)
    if dt.size < 8 or not np.allclose(dt, dt[0], rtol=1e-6, atol=0.0):
        raise DataError(
            expected(
                "data",
                "a uniformly sampled record (a latent state is reconstructed spectrally)",
                "non-uniform sample times",
                raw=True,
            )
        )
    return float(dt[0])


def _is_transient(Y: np.ndarray) -> bool:
    """The first period differs from the mean of the others by more than the noise explains."""
    rest = Y[1:]
    noise_var = float(np.mean(rest.var(axis=0, ddof=1)))
    expected_var = noise_var * (1.0 + 1.0 / rest.shape[0])
    return float(np.mean((Y[0] - rest.mean(axis=0)) ** 2)) > TRANSIENT_RATIO**2 * expected_var


def raised_cosine(f: np.ndarray, f_pass: float, f_stop: float) -> np.ndarray:
    """A low-pass gain: 1 up to ``f_pass``, a raised cosine down to 0 at ``f_stop``, 0 above."""
    gain = np.ones_like(f)
    mid = (f > f_pass) & (f < f_stop)
    gain[mid] = 0.5 * (1 + np.cos(np.pi * (f[mid] - f_pass) / (f_stop - f_pass)))
    gain[f >= f_stop] = 0.0
    return gain


class Spectra:
    """The period-averaged record (or a transient record), band-limited spectral derivatives and their noise.

    Parameters
    ----------
    periods : Periods
    periodic : bool
        Whole periods of a periodic input (default), or a transient record taken whole (one row).

    Attributes
    ----------
    u, y, v, a : ndarray, shape (n_per_period,)
        Average input, and band-limited position, velocity and acceleration of the average output.
    f_max : float
        Highest frequency of the input (Hz): its highest excited line, or for a transient record the
        frequency below which 99.9 % of its power lies. Derivatives keep the band to ``f_max`` and
        taper to zero at ``4/3 f_max`` (or Nyquist).
    noise_var : float
        Variance of the noise of one averaged output sample (from the scatter of the periods).
    valid : ndarray of bool
        Samples the regressions use (all of them for whole periods).
    """

    def __init__(self, periods: Periods, periodic: bool = True):
        P, N = periods.Y.shape
        self.N, self.fs, self.periodic = N, periods.fs, periodic
        self.f = np.fft.rfftfreq(N, 1.0 / periods.fs)
        self.iw = 2j * np.pi * self.f
        y = periods.Y.mean(axis=0)
        slope = 0.0 if periodic else (y[-1] - y[0]) / ((N - 1) / periods.fs)
        trend = np.zeros(N) if periodic else y[0] + slope * np.arange(N) / periods.fs
        self.Uf = np.fft.rfft(periods.U.mean(axis=0))
        self.Yf = np.fft.rfft(y - trend)
        amplitude = np.abs(self.Uf)
        self.excited = amplitude > 1e-2 * amplitude.max()
        self.excited[0] = False
        if self.excited.sum() < MIN_LINES:
            raise DataError(
                expected(
                    "data",
                    f"an input exciting at least {MIN_LINES} frequencies (the skeleton and the hidden law need a "
                    "broadband input)",
                    f"{int(self.excited.sum())} excited frequencies",
                    "use a multisine",
                    raw=True,
                )
            )
        nyquist = periods.fs / 2
        self.f_max = float(self.f[self.excited].max()) if periodic else _power_band(self.f, amplitude)
        self.band = raised_cosine(self.f, min(self.f_max, 0.9 * nyquist), min(4 / 3 * self.f_max, nyquist))
        if periodic:
            self.bin_var = np.fft.rfft(periods.Y, axis=1).var(axis=0, ddof=1) / P
            self.noise_var = float(np.mean(periods.Y.var(axis=0, ddof=1)) / P)
        else:
            self.noise_var = _noise_floor(self.Yf, self.f, 4 / 3 * self.f_max, y, N)
            self.bin_var = np.full(self.f.size, self.noise_var * N)
        self.u = np.fft.irfft(self.Uf, N)
        self.y = self.filtered(self.Yf) + trend
        self.v = self.filtered(self.iw * self.Yf) + slope
        self.a = self.filtered(self.iw**2 * self.Yf)
        self.valid = np.ones(N, dtype=bool)
        if not periodic:
            edge = int(np.ceil(EDGE_CYCLES * periods.fs / (self.f_max / 4)))
            if N < 4 * edge:
                raise DataError(
                    expected(
                        "data",
                        f"a transient record of at least {4 * edge} samples ({EDGE_CYCLES:g} cycles of "
                        f"f_max / 4 = {self.f_max / 4:.3g} Hz are left out at each end)",
                        f"{N} samples",
                        "record longer, or several whole periods of a periodic input",
                        raw=True,
                    )
                )
            self.valid[:edge] = self.valid[-edge:] = False

    def driven_by(self, u: np.ndarray) -> Spectra:
        """This record with ``u`` (on the same samples) in place of its input: a host's drive (see
        :mod:`.hosts`). The excited lines and the band stay those of the record's input."""
        out = copy.copy(self)
        out.u, out.Uf = np.asarray(u, dtype=float), np.fft.rfft(u)
        return out

    def filtered(self, spectrum: np.ndarray) -> np.ndarray:
        """The band-limited signal of a spectrum of the average."""
        return np.fft.irfft(spectrum * self.band, self.N)

    def sd(self, operator) -> float:
        """Standard deviation (the same at every sample) of ``irfft(operator * band * noise)``."""
        power = np.abs(operator * self.band) ** 2 * self.bin_var
        weight = np.full(power.size, 2.0)
        weight[0] = 1.0
        if self.N % 2 == 0:
            weight[-1] = 1.0
        return float(np.sqrt(np.sum(weight * power)) / self.N)

    def force(self, m: float, c: float, k: float) -> np.ndarray:
        """The hidden force ``u - m y'' - c y' - k y`` of a skeleton ``(m, c, k)``."""
        return self.u - m * self.a - c * self.v - k * self.y


def _power_band(f: np.ndarray, amplitude: np.ndarray, share: float = 0.999) -> float:
    """The frequency below which ``share`` of the (non-DC) power of a spectrum lies."""
    power = amplitude[1:] ** 2
    cumulative = np.cumsum(power) / max(power.sum(), 1e-300)
    return float(f[1:][min(int(np.searchsorted(cumulative, share)), power.size - 1)])


def _noise_floor(Yf: np.ndarray, f: np.ndarray, f_stop: float, y: np.ndarray, n: int) -> float:
    """White-noise variance of a transient record: the median power of its bins above the band, else
    third differences (``std(diff(y, 3)) = sqrt(20) sigma``, an upper bound near the band)."""
    above = f > f_stop
    if above.sum() >= 32:
        return float(np.median(np.abs(Yf[above]) ** 2) / np.log(2) / n)  # |Y|^2 is exponential: median = ln2 mean
    return third_difference_std(y) ** 2
