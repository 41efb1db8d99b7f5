"""The noise model of an output-error fit: white, or autoregressive per measured channel.

A measured channel is its model's output plus noise ``v = H(q) w``, ``w`` white of variance ``sigma^2``. With
an autoregressive ``H = 1 / A(q)``, ``A(q) = 1 + a_1 q^-1 + ... + a_p q^-p``, the innovations of the residual
``r`` are ``e_t = r_t + sum_i a_i r_{t-i}`` (a finite filter): the likelihood, its Gauss-Newton blocks, the
Laplace posterior and the evidence are those of the whitened residual and whitened sensitivities, with the
first ``p`` samples of every segment left out (the conditional likelihood; Ljung, *System Identification*,
ch. 7). With ``p = 0`` everything is as for white noise.

Coloured residuals come from coloured sensor noise, from process noise (a random force not in the recorded
input, filtered by the system) and from noise on a measured input; under a white likelihood each extra term
buys evidence by absorbing them. The order is chosen by BIC on the residual of the fitted structure (with a
common hold-back of the largest order, so that the orders compare on the same samples), the coefficients by
least squares of the residual on its own past (conditional maximum likelihood), alternately with the
model's coefficients (iterated generalised least squares).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from .._data.residuals import innovations

__all__ = ["NoiseModel", "fit_ar", "choose_order", "MAX_ORDER", "innovations"]

#: Largest autoregressive order tried per channel.
MAX_ORDER = 8


@dataclass(frozen=True)
class NoiseModel:
    """The noise of each measured channel.

    Attributes
    ----------
    ar : ndarray, shape (n_channels, order)
        ``a_1 .. a_p`` of each channel (zeros beyond a channel's own order); ``order = 0``: white noise.
    """

    ar: np.ndarray

    @classmethod
    def white(cls, n_channels: int) -> NoiseModel:
        return cls(np.zeros((n_channels, 0)))

    @property
    def order(self) -> int:
        return int(self.ar.shape[1])

    def orders(self) -> list[int]:
        """Each channel's own order (its last nonzero coefficient)."""
        out = []
        for row in self.ar:
            nz = np.flatnonzero(row)
            out.append(int(nz[-1]) + 1 if nz.size else 0)
        return out

    def spectrum_gain(self) -> np.ndarray:
        """Per channel, the variance of the noise over the variance of its innovations, ``sum_k psi_k^2`` with
        ``psi`` the impulse response of ``1 / A(q)`` (1 for white noise, inf for an unstable filter)."""
        out = []
        for row in self.ar:
            if not np.any(row):
                out.append(1.0)
                continue
            radius = float(np.max(np.abs(np.roots(np.concatenate([[1.0], row])))))
            if radius >= 1.0:
                out.append(math.inf)
                continue
            # the impulse response decays like radius^k: long enough for its tail to fall below 1e-16
            impulse = np.zeros(max(64, int(np.ceil(-37.0 / np.log(radius))) + 1) if radius > 0 else 64)
            impulse[0] = 1.0
            out.append(float(np.sum(lfilter([1.0], np.concatenate([[1.0], row]), impulse) ** 2)))
        return np.array(out)


def _lagged(r: np.ndarray, since: np.ndarray, run: np.ndarray, order: int, hold: int):
    """Rows usable at a hold-back of ``hold`` samples: the residual and its ``order`` lags (every one finite)."""
    finite = np.isfinite(r)
    finite_run = np.cumsum(finite) - np.maximum.accumulate(np.where(~finite, np.cumsum(finite), 0))
    keep = (since >= hold) & (run > hold) & (finite_run > hold)
    idx = np.flatnonzero(keep)
    y = r[idx]
    X = np.column_stack([r[idx - i] for i in range(1, order + 1)]) if order else np.zeros((idx.size, 0))
    return y, X


@np.errstate(all="ignore")  # a residual that ran away gives a non-finite variance, which no order is chosen for
def fit_ar(r: np.ndarray, since: np.ndarray, run: np.ndarray, order: int, hold: int | None = None):
    """Autoregressive coefficients of one channel's residual ``r`` by least squares on its own past.

    Parameters
    ----------
    r : ndarray, shape (n_samples,)
        The residual (NaN where not measured).
    since : ndarray of int
        Samples since each row's segment started (the lags never cross a segment start).
    run : ndarray of int
        Consecutive measured samples ending at each row.
    order : int
    hold : int, optional
        Samples held back at each segment start (default ``order``).

    Returns
    -------
    a : ndarray, shape (order,)
        ``e_t = r_t + sum_i a_i r_{t-i}``.
    variance : float
        Of the innovations ``e``.
    n : int
        Rows used.
    """
    y, X = _lagged(r, since, run, order, order if hold is None else hold)
    if order == 0 or y.size <= order:
        return np.zeros(order), float(np.mean(y**2)) if y.size else math.nan, int(y.size)
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(y))):
        return np.zeros(order), math.inf, int(y.size)
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    e = y - X @ coef
    return -coef, float(np.mean(e**2)), int(y.size)


def _stable(a: np.ndarray) -> bool:
    """``1 / A(q)`` stable: the roots of ``z^p + a_1 z^(p-1) + ... + a_p`` inside the unit circle."""
    return bool(np.all(np.abs(np.roots(np.concatenate([[1.0], a]))) < 0.999)) if a.size else True


def choose_order(r: np.ndarray, since: np.ndarray, run: np.ndarray, max_order: int = MAX_ORDER) -> int:
    """The autoregressive order of a residual by BIC, ``n log sigma_p^2 + p log n``, every order on the same
    rows (a common hold-back of ``max_order``); an order whose filter is unstable is not chosen."""
    best, best_bic = 0, math.inf
    for p in range(max_order + 1):
        a, var, n = fit_ar(r, since, run, p, hold=max_order)
        if not (n > max_order and var > 0 and np.isfinite(var)) or not _stable(a):
            continue
        bic = n * math.log(var) + p * math.log(n)
        if bic < best_bic - 1e-9:
            best, best_bic = p, bic
    return best
