"""Statistics of residuals: how many independent samples a correlated residual carries.

A residual that is white carries one independent sample per row; a correlated one (unmodelled dynamics,
coloured noise, a closed loop) carries fewer, ``N_eff = N / (1 + 2 sum_j rho_j)`` with ``rho_j`` its
autocorrelation at lag ``j``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["effective_fraction"]


def effective_fraction(r: np.ndarray, max_lag: int = 50) -> float:
    """``N_eff / N = 1 / (1 + 2 sum_j rho_j)`` from the autocorrelation of the residual rows ``r``.

    The sum runs over the lags up to ``max_lag`` until the first ``|rho_j| < 0.05`` (the initial positive
    sequence, truncated where the correlation is no longer distinguishable from noise); the fraction is
    at most 1.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> round(effective_fraction(rng.standard_normal(20000)), 2)
    1.0
    >>> e = rng.standard_normal(20000)
    >>> ar = np.zeros_like(e)
    >>> for t in range(1, e.size):
    ...     ar[t] = 0.9 * ar[t - 1] + e[t]
    >>> round(effective_fraction(ar), 2)  # AR(1) with a = 0.9: (1 - a) / (1 + a) = 0.053
    0.05
    """
    r = r - r.mean()
    c0, total = float(r @ r), 0.0
    for j in range(1, min(max_lag, len(r) - 1)):
        rho = float(r[:-j] @ r[j:]) / c0
        if abs(rho) < 0.05:
            break
        total += rho
    return float(min(1.0, 1.0 / max(1.0 + 2.0 * total, 1.0)))
