"""The weak (integral) form: integrate against compactly supported bumps instead of differentiating.

``int phi_j x' dt = -int phi_j' x dt``: the target needs no derivative of the noisy state. Windows do
not overlap, so the measurement noise entering one row is independent of every other row and the
RVM's white-noise evidence stays valid without a correction.

References
----------
D.A. Messenger, D.M. Bortz (2021), Weak SINDy, Multiscale Model. Simul. 19(3).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ._differentiator import Differentiator, Stencil, check_samples as _check
from ._errors import ParameterError, expected

__all__ = ["WeakForm"]


@dataclass(frozen=True)
class WeakForm(Differentiator):
    """Weak (integral) formulation on non-overlapping windows.

    Row j uses the test function ``phi_j(t) = (1 - s^2)^p`` with ``s`` mapping the j-th window of
    ``window`` sample intervals onto [-1, 1]. Integrating by parts (``phi_j`` vanishes at both
    ends of its window),

        int phi_j x' dt = - int phi_j' x dt  ~=  int phi_j D(x) dt beta,

    so the target needs no derivative of the noisy state. Integrals use the trapezoid rule on the
    samples; since ``phi_j`` and ``phi_j'`` vanish at the window ends, the rule is accurate to
    order ``p`` (``p + 1`` for odd ``p``) in the sample interval (Euler-Maclaurin). Adjacent windows share only their end sample,
    where both test functions are zero, so rows carry independent noise.

    Parameters
    ----------
    window : int or None
        Window length in sample intervals (the support of each test function). None
        (default): chosen from the data's bandwidth by :meth:`resolve`.
    power : int
        Exponent ``p >= 2`` of the bump; larger is smoother.

    Notes
    -----
    Both sides are divided by ``int phi_j dt`` so rows keep the units of x' and D(x).

    Examples
    --------
    The window comes from the data's bandwidth; each row is one window:

    >>> import numpy as np
    >>> import symsbl
    >>> t = np.linspace(0.0, 1.0, 1001)
    >>> x = np.sin(2 * np.pi * t)[:, None]
    >>> weak = symsbl.WeakForm().resolve(t, x)
    >>> weak
    WeakForm(window=10, power=4)
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
    name: ClassVar[str] = "weak"

    @property
    def stencil(self) -> Stencil:
        """Windows of ``window`` sample intervals aligned with the record's start."""
        if self.window is None:
            raise ParameterError(expected("WeakForm.window", "a window resolved from data (call resolve(t, X))",
                                          None))
        return Stencil(stride=self.window, left=0, right=0, min_samples=self.window + 1)

    #: Fraction of the power of each state below the bandwidth used by the automatic window.
    POWER_QUANTILE: ClassVar[float] = 0.999
    #: Amplitude response of the p = 4 bump is 0.9 at f = 0.5 / window duration.
    RESPONSE_FACTOR: ClassVar[float] = 0.5
    #: Spectral bins count as signal when above this multiple of the white-noise floor (a noise
    #: bin exceeds it with probability exp(-20) ~ 2e-9).
    NOISE_MARGIN: ClassVar[float] = 20.0

    def resolve(self, t: np.ndarray, X: np.ndarray, n_terms: int = 0) -> "WeakForm":
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
            f_hi = max(f_hi, freq[min(np.searchsorted(cum, self.POWER_QUANTILE), len(freq) - 1)])
        window = int(round(self.RESPONSE_FACTOR / f_hi / h)) if f_hi > 0 else 4
        most = (n - 1) // max(2 * n_terms, 1)
        return WeakForm(window=max(4, min(window, most)), power=self.power)

    @property
    def order(self) -> int:
        """Order of the quadrature error in the sample interval at a fixed window duration
        (measured: 2, 4, 4, 6 for power 2, 3, 4, 6)."""
        return self.power + (self.power % 2)

    def _weights(self, h: float) -> tuple[np.ndarray, np.ndarray]:
        if self.window is None:
            raise ParameterError(expected("WeakForm.window", "a window resolved from data (call resolve(t, X))", None))
        if self.window < 4 or self.power < 2:
            raise ParameterError(expected("WeakForm", "window >= 4 and power >= 2",
                                          f"window={self.window}, power={self.power}", raw=True))
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
        return max((n_samples - 1) // self.window, 0)

    def _windows(self, A: np.ndarray) -> np.ndarray:
        """View of ``A`` as ``(n_rows, window + 1, n_cols)`` windows sharing end samples."""
        A = np.ascontiguousarray(A, dtype=float)
        if A.ndim == 1:
            A = A[:, None]
        n = self.n_rows(len(A))
        L = self.window
        return np.lib.stride_tricks.as_strided(
            A,
            shape=(n, L + 1, A.shape[1]),
            strides=(L * A.strides[0], A.strides[0], A.strides[1]),
            writeable=False,
        )

    def targets(self, t: np.ndarray, X: np.ndarray) -> np.ndarray:
        """Weak derivative ``-int phi_j' x dt / int phi_j dt``, shape ``(n_rows, n_states)``."""
        self._weights(1.0)  # validates the settings first
        X, h = _check(t, X, self.window + 1)
        _, dphi = self._weights(h)
        return -np.einsum("k,jkc->jc", dphi, self._windows(X))

    def reduce(self, D: np.ndarray) -> np.ndarray:
        """Window averages ``int phi_j D dt / int phi_j dt``, shape ``(n_rows, n_cols)``.

        The sample interval only scales the weights, which are normalised, so ``reduce`` needs
        no time vector.
        """
        phi, _ = self._weights(1.0)
        return np.einsum("k,jkc->jc", phi, self._windows(D))
