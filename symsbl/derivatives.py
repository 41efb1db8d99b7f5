"""Numerical differentiation strategies: the regression target of x' = D(x) beta.

Every strategy is a *linear operator pair*. ``targets`` applies it to the sampled states to
estimate (an operator applied to) their derivative; ``reduce`` applies the same operator to any
sampled columns, in particular to the dictionary. For pointwise differences ``reduce`` is the
identity. For the weak (integral) form it integrates each column against a smooth test function,
so the equation ``L x' = L D(x) beta`` holds exactly for any linear ``L``, and the noisy state is
never differentiated: ``int phi x' dt = -int phi' x dt``.

Strategies
----------
``PointDifference``   the paper's forward difference, first order.
``CentralDifference`` second order.
``SavitzkyGolay``     local polynomial fit; order = ``polyorder``.
``WeakForm``          integration against compactly supported bumps on non-overlapping windows.

The weak form uses windows that do not overlap, so the measurement noise entering one row is
independent of every other row: the RVM's white-noise evidence stays valid without a correction.
(Overlapping windows or filtering only the target would colour the noise, which is what makes a
sparse learner admit spurious terms.)

References
----------
R. Fuentes, N. Dervilis, K. Worden, E.J. Cross (2019), J. Phys.: Conf. Ser. 1264 012050, Sec. 3-4.
D.A. Messenger, D.M. Bortz (2021), Weak SINDy, Multiscale Model. Simul. 19(3).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy.signal import savgol_filter

from .errors import DataError

__all__ = [
    "PointDifference",
    "CentralDifference",
    "SavitzkyGolay",
    "WeakForm",
    "DIFFERENTIATORS",
    "get_differentiator",
]


def _check(t: np.ndarray, X: np.ndarray, min_samples: int) -> tuple[np.ndarray, float]:
    X = np.asarray(X, dtype=float)
    if X.ndim == 1:
        X = X[:, None]
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or X.ndim != 2 or len(t) != len(X):
        raise DataError(
            f"t and X must be (n_samples,) and (n_samples, n_states); received t.shape={t.shape}, "
            f"X.shape={X.shape}."
        )
    if len(t) < min_samples:
        raise DataError(
            f"X has {len(t)} samples; this differentiator needs at least {min_samples}. "
            "Use a longer record or a shorter window."
        )
    return X, float(t[1] - t[0])


class _Pointwise:
    """Shared behaviour of pointwise strategies: one row per sample, dictionary unchanged."""

    def reduce(self, D: np.ndarray) -> np.ndarray:
        """Identity: pointwise targets pair with pointwise dictionary rows."""
        return np.asarray(D, dtype=float)

    def n_rows(self, n_samples: int) -> int:
        """Number of regression rows produced from ``n_samples`` samples."""
        return n_samples

    def sample_span(self, row_start: int, row_stop: int) -> tuple[int, int]:
        """Samples ``[start, stop)`` whose ``reduce`` gives rows ``[row_start, row_stop)``."""
        return row_start, row_stop

    def resolve(self, t: np.ndarray, X: np.ndarray, n_terms: int = 0):
        """This strategy has no data-dependent settings: returns itself."""
        return self


@dataclass(frozen=True)
class PointDifference(_Pointwise):
    """Forward point difference ``(x[k+1] - x[k]) / h``, the paper's choice.

    First order as an estimate of x'(t_k) (it is second order at the half-sample point
    t_k + h/2, so it lags by half a sample). The last sample uses the backward difference.

    Examples
    --------
    >>> import numpy as np
    >>> import symsbl
    >>> t = np.linspace(0.0, 1.0, 1001)
    >>> x = np.sin(2 * np.pi * t)[:, None]
    >>> dx = symsbl.PointDifference().targets(t, x)
    >>> float(np.round(np.max(np.abs(dx[:-1, 0] - 2 * np.pi * np.cos(2 * np.pi * t[:-1]))), 3))  # O(h)
    0.02
    """

    order: ClassVar[int] = 1
    name: ClassVar[str] = "point"

    def targets(self, t: np.ndarray, X: np.ndarray) -> np.ndarray:
        """Derivative estimate, shape ``(n_samples, n_states)``."""
        X, h = _check(t, X, 2)
        d = np.empty_like(X)
        d[:-1] = np.diff(X, axis=0) / h
        d[-1] = d[-2]
        return d


@dataclass(frozen=True)
class CentralDifference(_Pointwise):
    """Central difference ``(x[k+1] - x[k-1]) / 2h``, second order.

    The end points use second-order one-sided formulas.

    Examples
    --------
    >>> import numpy as np
    >>> import symsbl
    >>> t = np.linspace(0.0, 1.0, 1001)
    >>> x = np.sin(2 * np.pi * t)[:, None]
    >>> dx = symsbl.CentralDifference().targets(t, x)
    >>> bool(np.max(np.abs(dx[:, 0] - 2 * np.pi * np.cos(2 * np.pi * t))) < 1e-4)  # O(h^2)
    True
    """

    order: ClassVar[int] = 2
    name: ClassVar[str] = "central"

    def targets(self, t: np.ndarray, X: np.ndarray) -> np.ndarray:
        """Derivative estimate, shape ``(n_samples, n_states)``."""
        X, h = _check(t, X, 3)
        return np.gradient(X, h, axis=0, edge_order=2)


@dataclass(frozen=True)
class SavitzkyGolay(_Pointwise):
    """Savitzky-Golay derivative: a least-squares polynomial of degree ``polyorder`` over
    ``window`` samples, differentiated at the centre.

    Parameters
    ----------
    window : int
        Odd window length in samples.
    polyorder : int
        Degree of the local polynomial. The derivative is accurate to order ``polyorder`` for
        even ``polyorder`` and ``polyorder + 1`` for odd (the symmetric derivative filters of
        degrees 2q - 1 and 2q coincide).

    Notes
    -----
    This smooths the target only, not the dictionary. On noisy data the smoothed target is
    correlated in time, which a white-noise evidence does not know about; prefer
    :class:`WeakForm` when the noise matters.

    Examples
    --------
    >>> import numpy as np
    >>> import symsbl
    >>> t = np.linspace(0.0, 1.0, 1001)
    >>> x = np.sin(2 * np.pi * t)[:, None]
    >>> dx = symsbl.SavitzkyGolay(window=9, polyorder=3).targets(t, x)
    >>> bool(np.max(np.abs(dx[:, 0] - 2 * np.pi * np.cos(2 * np.pi * t))) < 1e-6)
    True
    """

    window: int = 9
    polyorder: int = 3
    name: ClassVar[str] = "savgol"

    @property
    def order(self) -> int:
        """Order of accuracy of the derivative at interior points."""
        return self.polyorder + (self.polyorder % 2)

    def targets(self, t: np.ndarray, X: np.ndarray) -> np.ndarray:
        """Derivative estimate, shape ``(n_samples, n_states)``."""
        if self.window % 2 == 0 or self.window <= self.polyorder:
            raise DataError(
                f"SavitzkyGolay window must be odd and greater than polyorder={self.polyorder}; "
                f"received window={self.window}."
            )
        X, h = _check(t, X, self.window)
        return savgol_filter(X, self.window, self.polyorder, deriv=1, delta=h, axis=0, mode="interp")


@dataclass(frozen=True)
class WeakForm:
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
            raise DataError("WeakForm(window=None) must be resolved from data first: call resolve(t, X).")
        if self.window < 4 or self.power < 2:
            raise DataError(
                f"WeakForm needs window >= 4 and power >= 2; received window={self.window}, "
                f"power={self.power}."
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
        return max((n_samples - 1) // self.window, 0)

    def sample_span(self, row_start: int, row_stop: int) -> tuple[int, int]:
        """Samples ``[start, stop)`` whose ``reduce`` gives rows ``[row_start, row_stop)``."""
        return row_start * self.window, row_stop * self.window + 1

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


DIFFERENTIATORS: dict[str, type] = {
    "point": PointDifference,
    "central": CentralDifference,
    "savgol": SavitzkyGolay,
    "weak": WeakForm,
}


def get_differentiator(spec: "str | object") -> object:
    """Resolve a differentiator from its registry name or return an instance unchanged.

    Parameters
    ----------
    spec : str or differentiator instance
        One of ``DIFFERENTIATORS`` (``"point"``, ``"central"``, ``"savgol"``, ``"weak"``) or an
        object with ``targets``, ``reduce`` and ``n_rows`` methods.
    """
    if isinstance(spec, str):
        try:
            return DIFFERENTIATORS[spec]()
        except KeyError:
            raise ValueError(
                f"derivative must be one of {sorted(DIFFERENTIATORS)}; received {spec!r}."
            ) from None
    if all(hasattr(spec, m) for m in ("targets", "reduce", "n_rows", "sample_span", "resolve")):
        return spec
    raise ValueError(
        "derivative must be a registry name or an object with targets(t, X), reduce(D), "
        f"n_rows(n), sample_span(r0, r1) and resolve(t, X, n_terms); received {type(spec).__name__}."
    )
