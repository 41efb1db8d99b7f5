"""Pointwise differences: the paper's forward difference, central differences, Savitzky-Golay.

One regression row per sample; the dictionary rows are used as they are. Central differences are
second order; Savitzky-Golay fits a local polynomial of degree ``polyorder``. These smooth or
differentiate the target only, which colours its noise: prefer the weak form when noise matters.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from .._base.errors import ParameterError, expected
from .differentiator import Differentiator, Stencil
from .differentiator import check_samples as _check

__all__ = ["PointDifference", "CentralDifference", "SavitzkyGolay"]


class _Pointwise(Differentiator):
    """Shared behaviour of pointwise strategies: one row per sample, dictionary unchanged."""

    def reduce(self, D: np.ndarray) -> np.ndarray:
        """Identity: pointwise targets pair with pointwise dictionary rows."""
        return np.asarray(D, dtype=float)

    def n_rows(self, n_samples: int) -> int:
        """Number of regression rows produced from ``n_samples`` samples."""
        return n_samples


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
    stencil: ClassVar[Stencil] = Stencil(stride=0, left=0, right=1, min_samples=2)

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
    stencil: ClassVar[Stencil] = Stencil(stride=0, left=1, right=1, min_samples=3)

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
    def stencil(self) -> Stencil:
        """Half a window either side of each row."""
        return Stencil(stride=0, left=self.window // 2, right=self.window // 2, min_samples=self.window)

    @property
    def order(self) -> int:
        """Order of accuracy of the derivative at interior points."""
        return self.polyorder + (self.polyorder % 2)

    def targets(self, t: np.ndarray, X: np.ndarray) -> np.ndarray:
        """Derivative estimate, shape ``(n_samples, n_states)``."""
        if self.window % 2 == 0 or self.window <= self.polyorder:
            raise ParameterError(
                expected("SavitzkyGolay.window", f"an odd number greater than polyorder={self.polyorder}", self.window)
            )
        X, h = _check(t, X, self.window)
        from scipy.signal import savgol_filter  # scipy.signal costs ~1 s to import: only when used

        return savgol_filter(X, self.window, self.polyorder, deriv=1, delta=h, axis=0, mode="interp")
