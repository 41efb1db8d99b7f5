"""Statistics of residuals: whiteness, independence of the inputs, and the samples a correlated residual carries.

A residual that is white carries one independent sample per row; a correlated one (unmodelled dynamics,
coloured noise, a closed loop) carries fewer, ``N_eff = N / (1 + 2 sum_j rho_j)`` with ``rho_j`` its
autocorrelation at lag ``j``. The residual test of system identification (Ljung, *System Identification*,
ch. 16) asks two questions of a fitted model's residual: is it white (the Ljung-Box statistic), and is it
independent of the inputs (the cross-correlation with a band corrected for the colour of both)? A residual
that depends on past inputs says the model is wrong; an input that depends on past residuals says the
record was taken in closed loop.
"""

from __future__ import annotations

import functools
import hashlib
from dataclasses import dataclass

import numpy as np

from .._base.lsq import Gram, lstsq

__all__ = [
    "effective_fraction",
    "ljung_box",
    "cross_correlation",
    "ResidualTest",
    "residual_test",
    "prewhitening",
    "innovations",
    "past_removed",
    "explained_out_of_sample",
    "LEVEL",
    "MODEL_ERROR",
    "COLOUR",
]


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


def _autocovariance(x: np.ndarray, max_lag: int) -> np.ndarray:
    """``R(k) = 1/N sum_t x_t x_{t-k}``, ``k = 0..max_lag``, of the centred ``x``."""
    x = x - x.mean()
    n = x.size
    return np.array([float(x[: n - k] @ x[k:]) / n for k in range(max_lag + 1)])


def ljung_box(e: np.ndarray, lags: int = 25, n_params: int = 0) -> tuple[float, float]:
    """The Ljung-Box statistic of ``e`` over ``lags`` lags and its p-value under whiteness.

    ``Q = N (N + 2) sum_k rho_k^2 / (N - k)`` is compared with chi-squared on ``lags - n_params`` degrees of
    freedom (``n_params``: the noise model's own coefficients, fitted to the same residual).

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(1)
    >>> q, p = ljung_box(rng.standard_normal(5000))
    >>> p > 0.01
    True
    """
    from scipy import stats

    n = e.size
    r = _autocovariance(e, lags)
    rho = r[1:] / r[0] if r[0] > 0 else np.zeros(lags)
    q = float(n * (n + 2) * np.sum(rho**2 / (n - np.arange(1, lags + 1))))
    return q, float(stats.chi2.sf(q, max(lags - n_params, 1)))


def cross_correlation(e: np.ndarray, u: np.ndarray, lags: int = 25) -> tuple[np.ndarray, np.ndarray]:
    """The normalised cross-correlation ``rho(tau)`` of the residual ``e`` with the input ``u`` (``e_t`` against
    ``u_{t - tau}``, ``tau = -lags .. lags``) and the half-width of its band under independence for one
    standard deviation.

    The band is ``sqrt(P / (N R_e(0) R_u(0)))`` with ``P = sum_k R_e(k) R_u(k)`` (Bartlett-weighted over
    ``|k| <= lags``): a coloured input and a coloured residual correlate by chance more than ``1/sqrt(N)`` says,
    and the correction keeps the test's level (Ljung, *System Identification*, sec. 16.6). ``tau > 0``: the
    residual depends on past inputs (the model misrepresents how the input acts); ``tau < 0``: the input
    depends on past residuals (feedback).
    """
    e = e - e.mean()
    u = u - u.mean()
    n = e.size
    scale = np.sqrt(float(e @ e) / n * float(u @ u) / n)
    rho = np.empty(2 * lags + 1)
    for i, tau in enumerate(range(-lags, lags + 1)):
        rho[i] = (float(e[tau:] @ u[: n - tau]) if tau >= 0 else float(e[: n + tau] @ u[-tau:])) / n
    rho = rho / scale if scale > 0 else np.zeros_like(rho)
    re, ru = _autocovariance(e, lags), _autocovariance(u, lags)
    w = 1.0 - np.arange(lags + 1) / (lags + 1)
    p = re[0] * ru[0] + 2.0 * float(np.sum(w[1:] * re[1:] * ru[1:]))
    band = np.full(rho.shape, np.sqrt(max(p, 0.0) / (n * re[0] * ru[0])) if re[0] * ru[0] > 0 else np.inf)
    return rho, band


#: Negative lags left out of the feedback test: a simulation driven by a spline of the input reads the next
#: samples (a cubic spline's support), so its residual correlates with them without any loop.
SPLINE_LAGS = 2

#: Family-wise level of the residual tests (each test's lags together).
LEVEL = 0.01

#: Share of the innovations' variance that the model's simulated trajectory predicts out of sample at which their
#: colour is the model's error. Measured on a hardening oscillator (10 records): with a random force the record
#: lacks, at most 0.009; with the law outside the library, under a random force, at least 0.155.
MODEL_ERROR = 0.05

#: Share of the innovations' variance their own past must predict for a whiteness failure to matter. Measured: a
#: random force the record lacks, of 0.5 % and 2 % of the input, 0.8-9 % (hardening oscillator, 3 records each);
#: the Bouc-Wen benchmark's band-limited measurement noise under its AR(8) model, 0.11 % (p = 2.5e-4 on 35840
#: samples), where refitting on short segments for it raised every posterior std 1.5x and the test error 1.5x.
COLOUR = 0.005


@dataclass(frozen=True)
class ResidualTest:
    """The residual analysis of one measured channel, as every identification tool reports it.

    Attributes
    ----------
    channel : str
    n_samples : int
    whiteness_p : float
        Ljung-Box p-value of the innovations over ``lags`` lags.
    input_ratio : dict
        Per input, the largest ``|rho(tau)| / threshold`` over ``tau = 0 .. lags`` (above 1: the residual
        depends on the input, the model misrepresents how it acts).
    feedback_ratio : dict
        Per input, the largest ``|rho(tau)| / threshold`` over ``tau = -lags .. -3`` (above 1: the input
        depends on past residuals, a closed loop; the two lags before are a spline's support).
    lags : int
    predictable : float
        The share of the residual's variance its own past ``lags`` samples predict (least squares; about
        ``lags / n_samples`` for white noise): how much a whiteness failure matters.
    trajectory : float
        The share of the innovations' variance that the model's own simulated trajectory predicts out of sample
        (:func:`explained_out_of_sample`; below 0 when it predicts nothing; NaN where not computed). At or above
        :data:`MODEL_ERROR` the residual's colour is the model's error, not a disturbance: a random force the
        record does not hold is independent of the trajectory the input drives.
    noise_p : float
        Ljung-Box p-value of the channel's noise alone where the record tells it from the response (its
        measured part that does not repeat from period to period under periodic inputs); NaN elsewhere. A
        residual that is not white while this noise is, is the model's error, not a disturbance.
    """

    channel: str
    n_samples: int
    whiteness_p: float
    input_ratio: dict
    feedback_ratio: dict
    lags: int
    predictable: float = 0.0
    noise_p: float = float("nan")
    trajectory: float = float("nan")

    @property
    def white(self) -> bool:
        return self.whiteness_p >= LEVEL

    @property
    def coloured(self) -> bool:
        """The innovations' own past predicts a share of their variance that matters (:data:`COLOUR`)."""
        return bool(self.predictable >= COLOUR)

    @property
    def noise_white(self) -> bool:
        """The channel's noise, told from the response between periods, is white (False where not told)."""
        return bool(self.noise_p >= LEVEL)

    @property
    def model_error(self) -> bool:
        """The model's own trajectory predicts the innovations (:data:`MODEL_ERROR`): their colour is its error."""
        return bool(self.trajectory >= MODEL_ERROR)

    @property
    def independent(self) -> bool:
        return all(r <= 1.0 for r in self.input_ratio.values())

    @property
    def open_loop(self) -> bool:
        return all(r <= 1.0 for r in self.feedback_ratio.values())

    def summary(self) -> str:
        """One line: the three verdicts with their statistics."""
        parts = [
            f"{self.channel}: innovations {'white' if self.white else 'correlated'} "
            f"(Ljung-Box p = {self.whiteness_p:.2g})"
        ]
        for name, r in self.input_ratio.items():
            parts.append(
                f"{'independent of' if r <= 1 else 'correlated with'} {name} ({r:.2g} x the "
                f"{100 * (1 - LEVEL):g} % threshold)"
            )
        for name, r in self.feedback_ratio.items():
            if r > 1:
                parts.append(f"feedback from past residuals to {name} ({r:.2g} x the threshold)")
        return ", ".join(parts)


#: Largest order of the autoregressive filter that prewhitens an input before its cross-correlation test.
PREWHITEN_ORDER = 30


def _remembered(fn):
    """``fn`` of an array, kept for the arrays of the last :data:`REMEMBERED` calls: every channel of a fit, and
    every structure fitted to the same records, prewhitens the same inputs."""
    kept: dict = {}

    @functools.wraps(fn)
    def inner(u: np.ndarray, *args, **kwargs):
        u = np.ascontiguousarray(u, dtype=float)
        key = (hashlib.blake2b(u.tobytes()).digest(), u.shape, args, tuple(sorted(kwargs.items())))
        if key not in kept:
            if len(kept) >= REMEMBERED:
                kept.clear()
            kept[key] = fn(u, *args, **kwargs)
        return kept[key].copy()

    return inner


#: Inputs whose prewhitening filters are kept.
REMEMBERED = 8


@_remembered
def prewhitening(u: np.ndarray, max_order: int = PREWHITEN_ORDER) -> np.ndarray:
    """The autoregressive filter ``[1, a_1, ..., a_p]`` that whitens ``u`` (order by BIC up to ``max_order``): a
    coloured input correlates with a residual over many lags at once, and filtering both by the input's
    whitening filter leaves the cross-correlation of one lag to the dependence at that lag (Box and Jenkins'
    prewhitening)."""
    x = u - u.mean()
    n = x.size
    best, best_bic = np.ones(1), n * np.log(max(float(x @ x) / n, 1e-300))
    top = min(max_order, n // 10)
    if top < 1:
        return best
    y = x[max_order:]
    lags = Gram(np.column_stack([x[max_order - i : n - i] for i in range(1, top + 1)]), y)  # every order's fit
    for p in range(1, top + 1):
        X = lags.X[:, :p]
        coef = lags.coef(p)
        var = float(np.mean((y - X @ coef) ** 2))
        bic = y.size * np.log(max(var, 1e-300)) + p * np.log(y.size)
        if bic < best_bic:
            best, best_bic = np.concatenate([[1.0], -coef]), bic
    return best


def innovations(r: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``e_t = r_t + sum_i a_i r_{t-i}`` of one channel over one contiguous stretch, ``a = [a_1, ..., a_p]`` (the
    first ``p`` samples, which lack their lags, are dropped)."""
    p = a.size
    e = r[p:].copy()
    for i in range(1, p + 1):
        e += a[i - 1] * r[p - i : r.size - i]
    return e


def residual_test(
    channel: str,
    e: np.ndarray,
    inputs: dict,
    lags: int = 25,
    n_params: int = 0,
    family: int = 1,
    loop: tuple | None = None,
) -> ResidualTest:
    """Whiteness of the residual ``e`` and its independence of each input in ``inputs`` (name -> samples aligned
    with ``e``), at the family-wise level :data:`LEVEL` (Sidak over each test's lags, and over ``family``
    tests of the same kind: the channels times the inputs). Each input and the residual are first filtered by
    the input's prewhitening filter (:func:`prewhitening`). The feedback test runs on ``loop`` (a residual and
    its inputs where only noise and a loop can show, e.g. their parts that do not repeat from period to period:
    a model's error under a periodic input repeats) when given, else on ``e`` and ``inputs``, after the
    residual is whitened by its own filter as well (each series by its own, as in Haugh's test of two series'
    independence) and its part that the past and present input explain is removed (:func:`past_removed`)."""
    from scipy import stats

    _, p = ljung_box(e, lags, n_params)
    z = float(stats.norm.isf((1.0 - (1.0 - LEVEL) ** (1.0 / ((lags + 1) * max(family, 1)))) / 2.0))
    inside, feedback = {}, {}
    filters = {name: prewhitening(u) for name, u in inputs.items()}
    for name, u in inputs.items():
        a = filters[name]
        rho, band = cross_correlation(innovations(e, a[1:]), innovations(u, a[1:]), lags)
        inside[name] = float(np.max(np.abs(rho[lags:]) / (z * band[lags:])))
    loop_e, loop_inputs = (e, inputs) if loop is None else loop
    for name, u in loop_inputs.items():
        a = filters[name] if loop is None else prewhitening(u)
        uf = innovations(u, a[1:])
        # the residual whitened by its own filter too: one that drifts (the free run of an integrating plant) has
        # a band so wide that a loop hides in it (EMPS: 0.7 x the threshold, 7.8 x once whitened); whitened
        # before the input's part is removed, which would notch the input's band out of it and colour it
        ef = innovations(loop_e, a[1:])
        own = prewhitening.__wrapped__(ef)
        uf = uf[own.size - 1 :]
        rest = past_removed(innovations(ef, own[1:]), uf, PAST * lags)
        rho, band = cross_correlation(rest, uf, lags)
        feedback[name] = float(np.max(np.abs(rho[: lags - SPLINE_LAGS]) / (z * band[: lags - SPLINE_LAGS])))
    return ResidualTest(channel, int(e.size), p, inside, feedback, lags, predictable(e, lags))


#: The feedback test first removes from the residual what this many times its lags of the past and present
#: input explain (the Sims form of the test): a model error the input drives over longer than the lags, under
#: an input the prewhitening filter does not whiten (a multisine of many lines), otherwise correlates with the
#: future input as a loop would.
PAST = 4


def past_removed(e: np.ndarray, u: np.ndarray, order: int) -> np.ndarray:
    """``e`` less its least-squares fit on ``u_{t-k}``, ``k = 0 .. order`` (the first ``order`` samples set to
    the mean, which leaves the correlation's sums at every lag to the rest)."""
    n = e.size
    if n <= 4 * (order + 1):
        return e
    X = np.column_stack([u[order - k : n - k] for k in range(order + 1)])
    coef = lstsq(X, e[order:])
    out = np.full(n, float(np.mean(e)))
    out[order:] = e[order:] - X @ coef
    return out


def predictable(e: np.ndarray, lags: int = 25) -> float:
    """The share of ``e``'s variance that a least-squares fit on its own past ``lags`` samples explains."""
    x = e - e.mean()
    n = x.size
    if n <= 4 * lags:
        return 0.0
    X = np.column_stack([x[lags - i : n - i] for i in range(1, lags + 1)])
    y = x[lags:]
    coef = lstsq(X, y)
    total = float(y @ y)
    return float(1.0 - np.sum((y - X @ coef) ** 2) / total) if total > 0 else 0.0


def explained_out_of_sample(e: np.ndarray, A: np.ndarray, folds: int = 2) -> float:
    """The share of ``e``'s variance that least squares on the columns of ``A`` ``(n_samples, n_columns)`` predicts
    in contiguous ``folds``, each fitted on the others (1 - held-out squared error / held-out variance about the
    training mean). Below 0 when the columns predict nothing: a fit on a coloured residual finds chance
    correlations in-sample that the held-out fold does not share, which an in-sample share would count.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> A = rng.standard_normal((4000, 3))
    >>> explained_out_of_sample(A @ [1.0, 0.5, 0.0] + rng.standard_normal(4000), A) > 0.5
    True
    >>> explained_out_of_sample(rng.standard_normal(4000), A) < 0.01
    True
    """
    from scipy import linalg

    n = e.size
    edges = np.linspace(0, n, folds + 1).astype(int)
    error = total = 0.0
    for a, b in zip(edges[:-1], edges[1:]):
        train = np.ones(n, dtype=bool)
        train[a:b] = False
        mean = float(np.mean(e[train]))
        coef = linalg.lstsq(A[train], e[train] - mean, lapack_driver="gelsy")[0]  # QR: 3x faster than an SVD
        error += float(np.sum((e[a:b] - mean - A[a:b] @ coef) ** 2))
        total += float(np.sum((e[a:b] - mean) ** 2))
    return 1.0 - error / total if total > 0 else 0.0
