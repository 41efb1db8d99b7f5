"""Where a record's noise can be told from its excitation: its period and the bands it leaves quiet.

A measured signal is excitation (or the response to it) plus noise, and the two can be told apart only where
the excitation is known not to be. Two places are, in the frequency-domain practice of system identification
(Pintelon and Schoukens, *System Identification: A Frequency Domain Approach*, ch. 2 and 5):

- **between periods**: a periodic excitation repeats exactly, and so does a stable system's steady response;
  what changes from one period to the next is noise (its variance is half that of the difference of two
  periods);
- **in the quiet bands**: a band-limited or multisine excitation leaves bands of the spectrum empty (above its
  highest line, between its lines); there the periodogram holds only noise.

Each is an upper bound of the noise (a leftover of excitation only adds to it), so a signal's noise is the
smaller of the two. A fixed fraction of the sampling rate is neither: a multisine to a third of the sampling
rate puts excitation above a quarter of it.
"""

from __future__ import annotations

import math

import numpy as np

from .residuals import innovations, prewhitening

__all__ = [
    "period",
    "period_noise_std",
    "quiet_band_std",
    "noise_std",
    "relative_noise",
    "aperiodic_part",
    "predicted",
    "BLOCKS",
    "RESOLVED",
]

#: Contiguous bands the periodogram is cut into; the quiet ones are those within :data:`QUIET` of the quietest.
BLOCKS = 16

#: A band is quiet when its median power is within this factor of the quietest band's.
QUIET = 2.0

#: Largest share of a signal's variance the difference of two periods may hold for the signal to be periodic.
REPEAT = 0.01


def _blocks(n_bins: int) -> int:
    """How many bands a periodogram of ``n_bins`` bins is cut into: :data:`BLOCKS`, at least 16 bins each."""
    return max(1, min(BLOCKS, n_bins // 16))


def quiet_band_std(x: np.ndarray) -> float:
    """White-noise standard deviation of a sampled signal from the quiet bands of its spectrum.

    The Hann-windowed periodogram (against the leakage of a record that is not periodic) is cut into
    :data:`BLOCKS` contiguous bands above the lowest; each band's median power estimates ``sigma^2 ln 2 sum w^2``
    where it holds only white noise, robust to a few lines of excitation. The bands within :data:`QUIET` of the
    quietest are taken for noise and their medians averaged: every band when the signal is white noise, the
    bands above the excitation's highest line when it is band-limited. Where the excitation fills every band
    (white excitation to the Nyquist rate) the estimate is the excitation's level: an upper bound.

    Examples
    --------
    Noise of 0.01 on a multisine that fills the lower 30 % of the band (a quarter-rate split would read it as
    noise):

    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> n = 8192
    >>> spectrum = np.zeros(n // 2 + 1, complex)
    >>> spectrum[1 : int(0.3 * n)] = np.exp(2j * np.pi * rng.uniform(size=int(0.3 * n) - 1))
    >>> u = np.fft.irfft(spectrum, n)
    >>> u = u / u.std() + 0.01 * rng.standard_normal(n)
    >>> round(quiet_band_std(u), 3)
    0.01
    """
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    if x.size < 16:
        return 0.0
    w = np.hanning(x.size)
    power = np.abs(np.fft.rfft((x - x.mean()) * w)) ** 2
    bins = power[1:-1]
    k = _blocks(bins.size)
    medians = np.array([np.median(b) for b in np.array_split(bins, k)])
    if k > 1:
        medians = medians[1:]  # the lowest band holds the drift and the slowest excitation
    quiet = medians[medians <= QUIET * medians.min()]
    return float(math.sqrt(float(np.mean(quiet)) / (math.log(2.0) * float(w @ w))))


def period(columns: np.ndarray, min_cycles: int = 2) -> int | None:
    """The period in samples of a record whose columns repeat together at least ``min_cycles`` times, or None.

    The candidate is the lag, past the first zero of the columns' pooled autocorrelation, where the
    autocorrelation (per overlapping sample) is largest, taken at its smallest multiple that comes within 1 %
    of it (at the peak there); the record is periodic when the difference of two periods holds at most
    :data:`REPEAT` of the columns' variance and each column's change between periods is at most :data:`QUIET`
    times the noise of its quiet bands.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(1)
    >>> one = rng.standard_normal(500)
    >>> period(np.tile(one, 4) + 0.01 * rng.standard_normal(2000))
    500
    >>> period(rng.standard_normal(2000)) is None
    True
    >>> t = np.arange(5000)
    >>> period(np.sin(2 * np.pi * t / 100.37) + 0.001 * rng.standard_normal(5000)) is None  # 100.37 samples
    True
    """
    X = np.asarray(columns, dtype=float)
    X = X.reshape(X.shape[0], -1)
    X = X[:, np.std(X, axis=0) > 0]
    n = X.shape[0]
    if X.shape[1] == 0 or n < 2 * min_cycles or not np.all(np.isfinite(X)):
        return None
    X = (X - X.mean(axis=0)) / X.std(axis=0)
    size = 1 << int(2 * n - 1).bit_length()
    F = np.fft.rfft(X, size, axis=0)
    r = np.fft.irfft(np.sum(np.abs(F) ** 2, axis=1), size)[:n] / (X.shape[1] * (n - np.arange(n)))
    last = n // min_cycles
    below = np.flatnonzero(r[1 : last + 1] < 0)
    if below.size == 0:
        return None
    first = int(below[0]) + 1
    lags = np.arange(first, last + 1)
    best = float(r[lags].max())
    if best <= 0:
        return None
    L = int(lags[np.flatnonzero(r[lags] >= best - 0.01)[0]])
    while L < last and r[L + 1] > r[L]:  # a smooth record's neighbours of its period come within 1 % too
        L += 1
    d = X[L:] - X[:-L]
    if float(np.mean(d**2)) / 2.0 > REPEAT:
        return None
    # what changes between periods is noise only if the quiet bands hold as much: a sine of a period between two
    # sample counts repeats nearly, its leftover a sine
    return L if all(period_noise_std(c, L) <= QUIET * quiet_band_std(c) for c in X.T) else None


def period_noise_std(x: np.ndarray, length: int) -> float:
    """White-noise standard deviation of a signal of period ``length`` samples from the difference of successive
    periods, ``var(x_{t+L} - x_t) = 2 sigma^2``, its variance taken robustly (median of the squares over its
    chi-squared median, 0.4549) against a transient in the first period."""
    x = np.asarray(x, dtype=float)
    d = x[length:] - x[:-length]
    d = d[np.isfinite(d)]
    if d.size == 0:
        return math.inf
    return float(math.sqrt(float(np.median(d**2)) / (2.0 * 0.454936)))


def noise_std(x: np.ndarray, length: int | None = None) -> float:
    """White-noise standard deviation of a sampled signal: the smaller of :func:`quiet_band_std` and, when the
    record has a period of ``length`` samples, :func:`period_noise_std` (each an upper bound)."""
    quiet = quiet_band_std(x)
    return min(quiet, period_noise_std(x, length)) if length else quiet


#: A relative noise below this is not told by the record (a 20-bit converter's step over its range is 1e-6): the
#: channel was low-passed or reconstructed (an encoder's position filtered at 100 Hz reads 7e-12 on EMPS), and its
#: noise, band-limited, is unknown rather than zero.
RESOLVED = 1e-6


def relative_noise(values: list[np.ndarray], periods: list[int | None]) -> float:
    """A column's white-noise standard deviation over its spread, pooled over records (``values``, each of
    period ``periods`` samples or None), each record's noise by :func:`noise_std`; non-finite samples left
    out. NaN where the records do not resolve it (below :data:`RESOLVED`, or a constant column).

    Examples
    --------
    >>> import numpy as np
    >>> t = np.arange(20000) / 1000.0
    >>> noisy = np.sin(2 * np.pi * t) + 0.01 * np.random.default_rng(0).standard_normal(t.size)
    >>> round(relative_noise([noisy], [None]), 4), relative_noise([np.sin(2 * np.pi * t)], [None])
    (0.0139, nan)
    """
    finite = [v[np.isfinite(v)] for v in values]
    spread = float(np.std(np.concatenate(finite))) if finite else 0.0
    sizes = np.array([v.size for v in finite], dtype=float)
    levels = np.array([noise_std(v, p) ** 2 if v.size else 0.0 for v, p in zip(values, periods)])
    var = float(np.sum(sizes * levels) / max(sizes.sum(), 1.0))
    level = math.sqrt(var) / spread if spread > 0 else 0.0
    return level if level >= RESOLVED else math.nan


def aperiodic_part(x: np.ndarray, length: int) -> np.ndarray:
    """The part of ``x`` that is not excitation or its steady response: each of its whole periods less their
    average, scaled by ``sqrt(P / (P - 1))`` to the noise's variance, over the first ``P - 1`` of the ``P`` whole
    periods (the last is minus their sum: no new sample), ``(P - 1) * length`` rows.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(2)
    >>> noise = rng.standard_normal(4 * 1000)
    >>> x = np.tile(np.sin(np.arange(1000) / 30.0), 4) + noise
    >>> part = aperiodic_part(x, 1000)
    >>> part.shape, round(float(part.std()), 2)
    ((3000,), 1.0)
    """
    x = np.asarray(x, dtype=float)
    cycles = x.shape[0] // length
    whole = x[: cycles * length].reshape((cycles, length) + x.shape[1:])
    part = (whole[:-1] - whole.mean(axis=0)) * math.sqrt(cycles / max(cycles - 1, 1))
    return part.reshape(((cycles - 1) * length,) + x.shape[1:])


def predicted(x: np.ndarray, tolerance: float) -> bool:
    """Whether the past of the signal ``x`` predicts it within ``tolerance`` of its spread: its innovations under
    its own autoregressive filter (:func:`symsbl._data.residuals.prewhitening`) spread less. A noise-free sine or
    multisine is a function of its past (nothing a loop could feed back into it); a measured input, with its
    converter's noise, is not. A noise-free random signal through a steep low-pass can be too (an 8th-order
    Butterworth at 0.01 of the Nyquist rate: 2.5e-11), and a simulated loop on such a reference goes untested.

    Examples
    --------
    >>> import numpy as np
    >>> t = np.arange(4000) / 1000.0
    >>> sine = np.sin(2 * np.pi * 10 * t)
    >>> predicted(sine, 1e-9), predicted(sine + 1e-6 * np.random.default_rng(0).standard_normal(t.size), 1e-9)
    (True, False)
    """
    x = np.asarray(x, dtype=float)
    spread = float(np.std(x))
    if spread == 0 or not np.all(np.isfinite(x)):
        return False
    return float(np.std(innovations(x, prewhitening(x)[1:]))) <= tolerance * spread
