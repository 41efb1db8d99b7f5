"""The weak (integral) form: integrate against compactly supported bumps instead of differentiating.

``int phi_j x' dt = -int phi_j' x dt``: the target needs no derivative of the noisy state. By
default windows do not overlap, so the measurement noise entering one row is independent of every
other row and the RVM's white-noise evidence stays valid without a correction. With ``overlap=q``
there are ``q`` test functions per window length, and the rows are whitened by the banded
covariance that the measurement noise of the target gives them (generalised least squares), so the
rows are again independent with equal variance and the evidence stays valid for that noise.

References
----------
D.A. Messenger, D.M. Bortz (2021), Weak SINDy, Multiscale Model. Simul. 19(3).
D.M. Bortz, D.A. Messenger, V. Dukic (2023), Direct estimation of parameters in ODE models using
WENDy, Bull. Math. Biol. 85(110).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import ClassVar

import numpy as np
from scipy.linalg import cholesky_banded, solve_banded, solve_triangular
from scipy.signal import lfilter

from .._base.checks import integer
from .._base.errors import ParameterError, expected
from .differentiator import Differentiator, Stencil
from .differentiator import check_samples as _check

__all__ = ["WeakForm"]


#: Whitening filters are cut where their taps fall below this share of the largest.
WHITENING_TOLERANCE = 1e-12
#: Longest whitening filter: an overlap whose filter has not decayed by then is refused (its rows' shared noise
#: is singular to rounding; measured: 2 and 3 decay within 300 taps, 8 and above never).
MAX_WHITENING_TAPS = 4096


@lru_cache(maxsize=32)
def _whitening(w_dphi: tuple, stride: int, overlap: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows of the inverse Cholesky factor of the rows' noise correlation: ``(start, taps)``.

    Row ``j`` of the target is ``-sum_k w_k x_{j stride + k}``; white noise in ``x`` gives rows
    correlated over ``overlap - 1`` neighbours, a banded Toeplitz correlation ``C`` (unit
    diagonal). With ``C = L L^T``, ``L^{-1}`` whitens the rows: ``start`` holds its first rows
    exactly (a record's start), ``taps`` the stationary filter of later rows (current row last),
    cut where the taps fall below :data:`WHITENING_TOLERANCE`. ``L`` is banded, so the filter
    costs ``O(size overlap)`` to find; the dense ``start`` is built once the filter has decayed.

    Raises
    ------
    ParameterError
        The filter does not decay within :data:`MAX_WHITENING_TAPS` taps, or ``C`` is not positive
        definite to rounding.
    """
    w = np.asarray(w_dphi)
    c = np.array([w[: len(w) - m * stride] @ w[m * stride :] for m in range(min(overlap, MAX_WHITENING_TAPS))])
    c = c / c[0]
    size = 64
    while True:
        band = min(overlap, size)
        try:  # lower banded storage: row k holds C[j + k, j] = c[k]
            lower = cholesky_banded(np.repeat(c[:band, None], size, axis=1), lower=True)
        except np.linalg.LinAlgError:
            break
        upper = np.zeros_like(lower)  # L^T in upper banded storage
        for k in range(band):
            upper[band - 1 - k, k:] = lower[k, : size - k]
        last = solve_banded((0, band - 1), upper, np.eye(size)[-1])  # the last row of L^{-1}
        keep = np.nonzero(np.abs(last) > WHITENING_TOLERANCE * np.abs(last).max())[0]
        n_taps = size - keep[0]
        if n_taps < size // 2:
            dense = np.zeros((n_taps - 1, n_taps - 1))
            for k in range(min(band, n_taps - 1)):
                dense[np.arange(k, n_taps - 1), np.arange(n_taps - 1 - k)] = lower[k, : n_taps - 1 - k]
            start = solve_triangular(dense, np.eye(n_taps - 1), lower=True) if n_taps > 1 else dense
            return start, last[size - n_taps :]
        if size >= MAX_WHITENING_TAPS:
            break
        size *= 2
    raise ParameterError(
        expected(
            "WeakForm.overlap",
            f"an overlap whose rows a filter of at most {MAX_WHITENING_TAPS} taps whitens",
            f"{overlap} (with windows every {stride} samples the noise the rows share is singular to rounding)",
            "use 2 (half overlap) or 3",
            raw=True,
        )
    )


@dataclass(frozen=True)
class WeakForm(Differentiator):
    """Weak (integral) formulation on windows that do not overlap (default) or overlap, whitened.

    Row j uses the test function ``phi_j(t) = (1 - s^2)^p`` with ``s`` mapping the j-th window of
    ``window`` sample intervals onto [-1, 1]. Integrating by parts (``phi_j`` vanishes at both
    ends of its window),

        int phi_j x' dt = - int phi_j' x dt  ~=  int phi_j D(x) dt beta,

    so the target needs no derivative of the noisy state. Integrals use the trapezoid rule on the
    samples; since ``phi_j`` and ``phi_j'`` vanish at the window ends, the rule is accurate to
    order ``p`` (``p + 1`` for odd ``p``) in the sample interval (Euler-Maclaurin). With
    ``overlap=1`` adjacent windows share only their end sample, where both test functions are
    zero, so rows carry independent noise.

    Parameters
    ----------
    window : int or None
        Window length in sample intervals (the support of each test function). None
        (default): chosen from the data's bandwidth by :meth:`resolve`.
    power : int
        Exponent ``p >= 2`` of the bump; larger is smoother.
    overlap : int
        Test functions per window length: windows start every ``window / overlap`` sample
        intervals (``window`` must be a multiple; :meth:`resolve` rounds it). 1 (default): no
        overlap. Above 1 the rows are whitened by the correlation that white measurement noise
        in the target gives them (generalised least squares), so they stay independent.

    Notes
    -----
    Both sides are divided by ``int phi_j dt`` so rows keep the units of x' and D(x).

    The whitening models the noise of the target only. The noise that the dictionary's columns
    carry (errors in variables) and the quadrature error are correlated between overlapping rows
    too and are not whitened; they are small against the target's noise when the window holds
    many samples, and grow with the overlap.

    Examples
    --------
    The window comes from the data's bandwidth; each row is one window:

    >>> import numpy as np
    >>> import symsbl
    >>> t = np.linspace(0.0, 1.0, 1001)
    >>> x = np.sin(2 * np.pi * t)[:, None]
    >>> weak = symsbl.WeakForm().resolve(t, x)
    >>> weak
    WeakForm(window=10, power=4, overlap=1)
    >>> weak.targets(t, x).shape        # 1000 sample intervals / 10 per window
    (100, 1)

    On the same rows, the weighted derivative equals the weighted ``2 pi cos(2 pi t)`` (to the
    trapezoid rule's error, 1e-6 here):

    >>> exact = weak.reduce(2 * np.pi * np.cos(2 * np.pi * t)[:, None])
    >>> bool(np.max(np.abs(weak.targets(t, x) - exact)) < 1e-5)
    True
    """

    window: int | None = None
    power: int = 4
    overlap: int = 1
    name: ClassVar[str] = "weak"

    def __post_init__(self):
        integer("WeakForm.overlap", self.overlap, low=1, error=ParameterError)
        if self.window is not None and self.window % self.overlap:
            raise ParameterError(expected("WeakForm.window", f"a multiple of overlap={self.overlap}", self.window))

    @property
    def _length(self) -> int:
        """The window, which must have been resolved from data."""
        if self.window is None:
            raise ParameterError(expected("WeakForm.window", "a window resolved from data (call resolve(t, X))", None))
        return self.window

    @property
    def stride(self) -> int:
        """Sample intervals between the starts of consecutive windows."""
        return self._length // self.overlap

    @property
    def stencil(self) -> Stencil:
        """Windows of ``window`` sample intervals every ``stride``, aligned with the record's start;
        overlapping rows are combined with the earlier rows their whitening reads."""
        left = len(self._whitening()[1]) - 1 if self.overlap > 1 else 0
        return Stencil(stride=self.stride, left=left, right=0, min_samples=self._length + 1, span=self._length)

    #: Fraction of the power of each state below the bandwidth used by the automatic window.
    POWER_QUANTILE: ClassVar[float] = 0.999
    #: Amplitude response of the p = 4 bump is 0.9 at f = 0.5 / window duration.
    RESPONSE_FACTOR: ClassVar[float] = 0.5
    #: Spectral bins count as signal when above this multiple of the white-noise floor (a noise
    #: bin exceeds it with probability exp(-20) ~ 2e-9).
    NOISE_MARGIN: ClassVar[float] = 20.0

    def resolve(self, t: np.ndarray, X: np.ndarray, n_terms: int = 0) -> WeakForm:
        """Fix an automatic window (``window=None``) from the data; a set window is kept.

        The window duration is ``0.5 / f_hi``, where ``f_hi`` is the highest over the states
        of the frequency below which 99.9 % of the (detrended) state's signal power lies: the
        bump's amplitude response is then at least 0.9 over the band that carries the
        dynamics. Signal power means periodogram bins more than 20 times the white-noise
        floor (estimated from the upper half of the band), so the window does not shrink as
        the measurement noise grows. The window is at least 4 samples and short enough to leave at least
        ``2 * n_terms`` rows.

        Parameters
        ----------
        t : ndarray, shape (n_samples,)
        X : ndarray, shape (n_samples, n_states)
        n_terms : int
            Number of candidate terms the rows will be regressed on.
        """
        if self.window is not None:
            return self
        X, h = _check(t, X, 8)
        n = len(X)
        idx = np.arange(n)
        f_hi = 0.0
        for col in X.T:
            resid = col - np.polyval(np.polyfit(idx, col, 1), idx)
            power = np.abs(np.fft.rfft(resid)) ** 2
            # Measurement noise is white: its periodogram is flat, exponentially distributed
            # about its mean. Estimate that mean from the upper half of the band and keep only
            # bins far above it, so the noise's share of the power does not read as bandwidth.
            floor = np.median(power[len(power) // 2 :]) / np.log(2.0)
            power = np.where(power > self.NOISE_MARGIN * floor, power, 0.0)
            if power.sum() <= 0:
                continue
            freq = np.fft.rfftfreq(n, h)
            cum = np.cumsum(power) / power.sum()
            f_hi = max(f_hi, freq[min(int(np.searchsorted(cum, self.POWER_QUANTILE)), len(freq) - 1)])
        window = int(round(self.RESPONSE_FACTOR / f_hi / h)) if f_hi > 0 else 4
        most = (n - 1) // max(2 * n_terms, 1)
        window = max(4, min(window, most))
        q = self.overlap
        if 2 * q > n - 1:
            raise ParameterError(
                expected(
                    "WeakForm.overlap",
                    f"at most {(n - 1) // 2} for a record of {n} samples (a "
                    "window spans at least 2 x overlap sample intervals)",
                    q,
                    "use 2 (half overlap) or 3",
                )
            )
        return WeakForm(window=max(q * round(window / q), 4 if q == 1 else 2 * q), power=self.power, overlap=q)

    @property
    def order(self) -> int:
        """Order of the quadrature error in the sample interval at a fixed window duration
        (measured: 2, 4, 4, 6 for power 2, 3, 4, 6)."""
        return self.power + (self.power % 2)

    def _weights(self, h: float) -> tuple[np.ndarray, np.ndarray]:
        if self.window is None:
            raise ParameterError(expected("WeakForm.window", "a window resolved from data (call resolve(t, X))", None))
        if self.window < 4 or self.power < 2:
            raise ParameterError(
                expected(
                    "WeakForm", "window >= 4 and power >= 2", f"window={self.window}, power={self.power}", raw=True
                )
            )
        L = self.window
        s = np.linspace(-1.0, 1.0, L + 1)
        half = 0.5 * L * h  # dt/ds
        phi = (1.0 - s**2) ** self.power
        dphi = -2.0 * self.power * s * (1.0 - s**2) ** (self.power - 1) / half
        # Trapezoid weights are h everywhere but the ends, where phi and dphi are zero anyway.
        # Each side is normalised so that it is exact for x = t (x' = 1): this removes the
        # leading quadrature error, which is a common factor of every window.
        w_phi = phi / phi.sum()
        w_dphi = dphi / -(dphi * np.arange(L + 1) * h).sum()
        return w_phi, w_dphi

    def n_rows(self, n_samples: int) -> int:
        """Number of windows that fit in ``n_samples`` samples."""
        return self.stencil.rows(n_samples, True, True)[1]

    def _windows(self, A: np.ndarray) -> np.ndarray:
        """View of ``A`` as ``(n_rows, window + 1, n_cols)`` windows starting every ``stride`` samples."""
        A = np.ascontiguousarray(A, dtype=float)
        if A.ndim == 1:
            A = A[:, None]
        n = self.n_rows(len(A))
        return np.lib.stride_tricks.as_strided(
            A,
            shape=(n, self._length + 1, A.shape[1]),
            strides=(self.stride * A.strides[0], A.strides[0], A.strides[1]),
            writeable=False,
        )

    def _whitening(self) -> tuple[np.ndarray, np.ndarray]:
        _, w_dphi = self._weights(1.0)
        return _whitening(tuple(w_dphi), self.stride, self.overlap)

    def _whiten(self, R: np.ndarray) -> np.ndarray:
        """Rows of overlapping windows made independent (rows from a record's start; see :func:`_whitening`)."""
        if self.overlap == 1 or not len(R):
            return R
        start, taps = self._whitening()
        out = lfilter(taps[::-1], [1.0], R, axis=0)
        head = min(len(start), len(R))
        out[:head] = start[:head, :head] @ R[:head]
        return out

    def targets(self, t: np.ndarray, X: np.ndarray) -> np.ndarray:
        """Weak derivative ``-int phi_j' x dt / int phi_j dt``, shape ``(n_rows, n_states)``
        (whitened when windows overlap)."""
        self._weights(1.0)  # validates the settings first
        X, h = _check(t, X, self._length + 1)
        _, dphi = self._weights(h)
        return self._whiten(-np.einsum("k,jkc->jc", dphi, self._windows(X)))

    def reduce(self, D: np.ndarray) -> np.ndarray:
        """Window averages ``int phi_j D dt / int phi_j dt``, shape ``(n_rows, n_cols)``
        (whitened like the targets when windows overlap).

        The sample interval only scales the weights, which are normalised, so ``reduce`` needs
        no time vector.
        """
        phi, _ = self._weights(1.0)
        return self._whiten(np.einsum("k,jkc->jc", phi, self._windows(D)))
