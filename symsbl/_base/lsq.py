"""Least squares on tall matrices: the normal equations where they are well conditioned, else one QR.

The residual tests fit long records (10^5 to 10^6 rows) on up to a hundred lagged columns. numpy's SVD-based
solver costs about twenty times the Gram product there (measured: 98304 x 101 rows, 0.61 s against 0.03 s in
one thread). Where the Gram matrix's condition number is below :data:`GRAM_COND`, its Cholesky solution
differs from the SVD's by about ``cond * eps`` (1e-10 relative), far below what any test resolves. A
rank-deficient or nearly collinear design (the lags of a pure sine) is solved from the design's QR factor
instead: ``X = Q R`` and, for its first ``p <= n`` columns, ``X[:, :p] = Q[:, :p] R[:p, :p]``, whose singular
values are the design's to rounding, so the SVD of the small ``R[:p, :p]`` truncates as an SVD of ``X[:, :p]``
would (numpy's default cut), and every ``p`` shares the one factorisation (measured: the 30 autoregressive orders
of a noise-free sine's 98304 samples, 0.64 s by an SVD each, 0.20 s so).
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve

__all__ = ["Gram", "GRAM_COND", "lstsq"]

#: Condition number of the Gram matrix below which the normal equations are solved (``cond(X) < 1e3``).
GRAM_COND = 1e6


class Gram:
    """``X^T X`` and ``X^T y`` of a design ``X`` (n_samples, n_columns) and a target ``y`` (n_samples,); the
    least-squares coefficients on its first ``p`` columns by :meth:`coef`."""

    def __init__(self, X: np.ndarray, y: np.ndarray):
        self.X, self.y = X, y
        self.G = X.T @ X
        self.b = X.T @ y
        self._r: np.ndarray | None = None

    def coef(self, p: int | None = None) -> np.ndarray:
        """The coefficients on the first ``p`` columns (default all)."""
        p = self.G.shape[0] if p is None else p
        G = self.G[:p, :p]
        w = np.linalg.eigvalsh(G)
        if np.all(np.isfinite(w)) and w[0] > 0 and w[-1] <= GRAM_COND * w[0]:
            return cho_solve(cho_factor(G), self.b[:p])
        if self._r is None:  # the factor of [X, y]: its last column above the diagonal is Q^T y
            factor = np.linalg.qr(np.column_stack([self.X, self.y]), mode="r")
            self._r = np.asarray(factor)  # mode "r" returns R alone, (k + 1) square (numpy's stubs name the pair)
        n, k = self.X.shape
        cut = np.finfo(float).eps * max(n, p)  # numpy's default for an SVD of X[:, :p]
        return np.linalg.lstsq(self._r[:p, :p], self._r[:p, k], rcond=cut)[0]


def lstsq(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The least-squares coefficients of ``y`` on the columns of ``X`` (see :class:`Gram`)."""
    return Gram(X, y).coef()
