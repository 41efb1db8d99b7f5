"""A record of whole periods of a periodic input: its period, its average and the noise of that average.

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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._errors import DataError, expected

__all__ = ["Periods", "Spectra", "split_periods", "raised_cosine", "REPEAT_TOL", "MIN_PERIODS"]

#: Relative RMS difference ``||u(t + T) - u(t)|| / ||u||`` below which the input repeats with period ``T``.
REPEAT_TOL = 1e-3
#: Whole periods needed: the noise of the average is estimated from their scatter.
MIN_PERIODS = 3
#: Excited frequencies needed (each gives two equations for the three skeleton parameters and the law).
MIN_LINES = 8
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
    head = c2[n - lags]                       # sum of x[:-L]^2
    tail = c2[n] - c2[lags]                   # sum of x[L:]^2
    distance = np.maximum(head + tail - 2 * corr[lags], 0.0)
    ok = np.flatnonzero(distance <= REPEAT_TOL ** 2 * 0.5 * (head + tail))
    ok = ok[lags[ok] >= 4]
    return int(lags[ok[0]]) if ok.size else None


def split_periods(t: np.ndarray, u: np.ndarray, y: np.ndarray) -> Periods:
    """Cut a record into the whole periods of its input.

    Parameters
    ----------
    t : ndarray, shape (n_samples,)
        Uniformly sampled times.
    u, y : ndarray, shape (n_samples,)
        The input and the measured position.

    Returns
    -------
    Periods

    Raises
    ------
    DataError
        The time grid is not uniform, the input does not repeat, or fewer than :data:`MIN_PERIODS`
        whole periods are recorded.
    """
    dt = np.diff(t)
    if dt.size < 8 or not np.allclose(dt, dt[0], rtol=1e-6, atol=0.0):
        raise DataError(expected("data", "a uniformly sampled record (a latent state is reconstructed spectrally)",
                                 "non-uniform sample times", raw=True))
    lag = _repeat_lag(np.asarray(u, dtype=float))
    if lag is None:
        raise DataError(expected(
            "data", f"a periodic input recorded over at least {MIN_PERIODS} whole periods (a latent state is "
            "identified from the periodic steady state)", "an input that does not repeat",
            "record several periods of a multisine", raw=True))
    n_periods = u.size // lag
    start = u.size - n_periods * lag
    U = np.asarray(u[start:], dtype=float).reshape(n_periods, lag)
    Y = np.asarray(y[start:], dtype=float).reshape(n_periods, lag)
    dropped = 0
    while Y.shape[0] > MIN_PERIODS and _is_transient(Y):
        U, Y, start, dropped = U[1:], Y[1:], start + lag, dropped + 1
    return Periods(fs=float(1.0 / dt[0]), U=U, Y=Y, start=int(start), dropped=dropped)


def _is_transient(Y: np.ndarray) -> bool:
    """The first period differs from the mean of the others by more than the noise explains."""
    rest = Y[1:]
    noise_var = float(np.mean(rest.var(axis=0, ddof=1)))
    expected_var = noise_var * (1.0 + 1.0 / rest.shape[0])
    return float(np.mean((Y[0] - rest.mean(axis=0)) ** 2)) > TRANSIENT_RATIO ** 2 * expected_var


def raised_cosine(f: np.ndarray, f_pass: float, f_stop: float) -> np.ndarray:
    """A low-pass gain: 1 up to ``f_pass``, a raised cosine down to 0 at ``f_stop``, 0 above."""
    gain = np.ones_like(f)
    mid = (f > f_pass) & (f < f_stop)
    gain[mid] = 0.5 * (1 + np.cos(np.pi * (f[mid] - f_pass) / (f_stop - f_pass)))
    gain[f >= f_stop] = 0.0
    return gain


class Spectra:
    """The period-averaged record, band-limited spectral derivatives and the noise of each.

    Parameters
    ----------
    periods : Periods

    Attributes
    ----------
    u, y, v, a : ndarray, shape (n_per_period,)
        Average input, and band-limited position, velocity and acceleration of the average output.
    f_max : float
        Highest excited frequency of the input (Hz); derivatives keep the band to ``f_max`` and
        taper to zero at ``4/3 f_max`` (or Nyquist).
    noise_var : float
        Variance of the noise of one averaged output sample (from the scatter of the periods).
    """

    def __init__(self, periods: Periods):
        P, N = periods.Y.shape
        self.N, self.fs = N, periods.fs
        self.f = np.fft.rfftfreq(N, 1.0 / periods.fs)
        self.iw = 2j * np.pi * self.f
        self.Uf = np.fft.rfft(periods.U.mean(axis=0))
        self.Yf = np.fft.rfft(periods.Y.mean(axis=0))
        self.bin_var = np.fft.rfft(periods.Y, axis=1).var(axis=0, ddof=1) / P
        amplitude = np.abs(self.Uf)
        self.excited = amplitude > 1e-2 * amplitude.max()
        self.excited[0] = False
        if self.excited.sum() < MIN_LINES:
            raise DataError(expected(
                "data", f"an input exciting at least {MIN_LINES} frequencies (the skeleton and the hidden law need a "
                "broadband periodic input)", f"{int(self.excited.sum())} excited frequencies",
                "use a multisine", raw=True))
        self.f_max = float(self.f[self.excited].max())
        nyquist = periods.fs / 2
        self.band = raised_cosine(self.f, min(self.f_max, 0.9 * nyquist), min(4 / 3 * self.f_max, nyquist))
        self.noise_var = float(np.mean(periods.Y.var(axis=0, ddof=1)) / P)
        self.u = np.fft.irfft(self.Uf, N)
        self.y = self.filtered(self.Yf)
        self.v = self.filtered(self.iw * self.Yf)
        self.a = self.filtered(self.iw ** 2 * self.Yf)

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
