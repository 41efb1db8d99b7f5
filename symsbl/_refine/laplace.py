"""The Laplace posterior and evidence of an output-error fit, the prior precisions, model reduction.

At the optimum the Gauss-Newton Hessian ``H = J^T W J`` (``W`` the noise precisions of the measured
channels) plays the part of ``D^T D / sigma^2`` in the linear relevance vector machine:

- the segments' initial states are nuisances with a flat prior, integrated out by a Schur
  complement per segment (directions without information, e.g. a segment in a gap of the data,
  are dropped), so the posterior of the coefficients is ``Sigma = (S + A)^-1`` with ``S`` the Schur
  complement and ``A = diag(alpha)`` the prior precisions;
- the log evidence is the Gaussian integral ``1/2 sum n_c log(w_c / 2 pi) - E + 1/2 sum log alpha
  + 1/2 n_x0 log 2 pi - 1/2 log|H_x0| - 1/2 log|S + A|`` (MacKay 1992), comparable between models fitted
  to the same records with the same segmentation;
- the prior precisions follow MacKay's fixed point ``alpha_i = gamma_i / mu_i^2`` with
  ``gamma_i = 1 - alpha_i Sigma_ii``, as the relevance vector machine's do;
- Bayesian model reduction (Friston and Penny 2011) scores switching coefficients off (prior
  variance to zero) from one fit's posterior, without refitting.

References
----------
D. J. C. MacKay, "Bayesian interpolation", Neural Computation 4 (1992) 415-447.
K. Friston, W. Penny, "Post hoc Bayesian model selection", NeuroImage 56 (2011) 2089-2099.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._base.errors import SimulationError, expected

__all__ = [
    "Posterior",
    "posterior",
    "reduce_model",
    "reprior",
    "mackay_alpha",
    "mackay_fixed_point",
    "schur",
    "x0_pinv",
]


@dataclass(frozen=True)
class Posterior:
    """The Laplace posterior of the free coefficients with the initial states integrated out.

    Attributes
    ----------
    mean : ndarray, shape (n_free,)
    covariance : ndarray, shape (n_free, n_free)
    log_evidence : float
        Nats; comparable between fits to the same records and segmentation.
    log_det_x0 : float
        ``sum log|H_x0|`` over the segments' identifiable initial-state directions.
    n_x0 : int
        Number of identifiable initial-state directions.
    precision : ndarray, shape (n_free, n_free)
        The inverse of ``covariance`` (the Schur complement plus the prior precisions), kept for a
        well-conditioned model reduction.
    data_precision : ndarray, shape (n_free, n_free)
        The Schur complement alone (the data's information), so that another prior can be put in
        its place without cancellation.
    """

    mean: np.ndarray
    covariance: np.ndarray
    log_evidence: float
    log_det_x0: float
    n_x0: int
    precision: np.ndarray | None = None
    data_precision: np.ndarray | None = None

    @property
    def std(self) -> np.ndarray:
        """Posterior standard deviations."""
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))


def x0_pinv(Hxx: np.ndarray):
    """Per segment, the pseudo-inverse of the initial-state block ``(K, nx, nx)`` (eigenvalues below 1e-12 of
    the largest dropped), and the log-determinant and number of the directions kept."""
    ev, V = np.linalg.eigh(Hxx)
    keep = ev > 1e-12 * max(float(ev.max()), 1e-300)
    inv = np.where(keep, 1.0 / np.where(keep, ev, 1.0), 0.0)
    return np.einsum("kij,kj,klj->kil", V, inv, V), float(np.sum(np.log(ev[keep]))), int(keep.sum())


def schur(H: np.ndarray, alpha: np.ndarray):
    """Schur complement of the initial-state blocks, with pseudo-inverses of rank-deficient blocks."""
    npar = alpha.size
    Htt = H[:, :npar, :npar].sum(axis=0) + np.diag(alpha)
    Htx = H[:, :npar, npar:]
    pinv, log_det, n_kept = x0_pinv(H[:, npar:, npar:])
    S = Htt - np.einsum("kpi,kij,kqj->pq", Htx, pinv, Htx)
    return S, log_det, n_kept


def posterior(
    H: np.ndarray, theta: np.ndarray, alpha: np.ndarray, cost: float, n_obs: np.ndarray, w: np.ndarray
) -> Posterior:
    """The Laplace posterior and log evidence at an optimum.

    Parameters
    ----------
    H : ndarray, shape (n_segments, ns, ns)
        Gauss-Newton blocks of every segment (coefficients first, then the segment's initial state).
    theta : ndarray, shape (n_free,)
    alpha : ndarray, shape (n_free,)
        Prior precisions.
    cost : float
        ``E = 1/2 sum w r^2 + 1/2 sum alpha theta^2`` at ``theta``.
    n_obs, w : ndarray, shape (n_measured,) or (n_records, n_measured)
        Measurements and noise precision per channel (of each record).
    """
    if not (np.all(np.isfinite(H)) and np.all(np.isfinite(theta)) and np.isfinite(cost)):
        raise SimulationError(
            expected(
                "output-error refinement",
                "a simulation and sensitivities that stay finite at the optimum",
                "non-finite values (the model diverges on this record)",
                "the equation-error model stands",
                raw=True,
            )
        )
    S_data, log_det_x0, n_x0 = schur(H, np.zeros_like(alpha))  # the prior enters only the diagonal
    S_data = 0.5 * (S_data + S_data.T)
    S = S_data + np.diag(alpha)
    curvature = np.diag(S)
    if not np.all(curvature > 0):  # S_data is positive semi-definite: only round-off makes a diagonal <= 0
        raise SimulationError(
            expected(
                "output-error refinement",
                "a positive curvature of the fit in every coefficient",
                f"{int(np.sum(~(curvature > 0)))} of {curvature.size} coefficients with curvature <= 0 once the "
                "initial states are integrated out (round-off: the record does not separate them from the initial "
                "states)",
                "the equation-error model stands",
                raw=True,
            )
        )
    d = np.sqrt(curvature)
    ev, V = np.linalg.eigh(S / np.outer(d, d))
    ev = np.maximum(ev, 1e-14 * max(float(ev.max()), 1e-300))  # round-off, not information
    cov = (V / ev) @ V.T / np.outer(d, d)
    log_det = float(np.sum(np.log(ev)) + 2 * np.sum(np.log(d)))
    n_obs, w = np.asarray(n_obs, dtype=float), np.asarray(w, dtype=float)
    data = np.where(n_obs > 0, n_obs * np.log(np.where(n_obs > 0, w, 1.0) / (2 * np.pi)), 0.0)
    log_ev = (
        0.5 * float(np.sum(data))
        + 0.5 * float(np.sum(np.log(alpha)))
        - cost
        + 0.5 * n_x0 * np.log(2 * np.pi)
        - 0.5 * (log_det_x0 + log_det)
    )
    return Posterior(np.array(theta, dtype=float), cov, float(log_ev), log_det_x0, n_x0, S, S_data)


def mackay_alpha(post: Posterior, alpha: np.ndarray, floor: float = 1e-300) -> np.ndarray:
    """MacKay's fixed point for the prior precisions: ``alpha_i = gamma_i / mu_i^2``."""
    gamma = np.clip(1.0 - alpha * np.diag(post.covariance), 1e-12, 1.0)
    return np.maximum(gamma / np.maximum(post.mean**2, floor), floor)


#: How far (posterior standard deviations) the prior precisions' fixed point may move a coefficient on the
#: quadratic model of the data term before that model is no longer trusted.
TRUST = 10.0
#: Largest prior precision relative to the data's curvature of the same coefficient. A coefficient the data
#: do not support drives MacKay's ``alpha`` to infinity; at ``1e8`` times its data precision it is already
#: shrunk to 1e-8 of its data estimate (pruned), and the products ``alpha mu`` that a change of prior
#: (:func:`reprior`) needs stay finite (unbounded, ``1e288 x 1e-168`` made the model reduction meaningless
#: and kept pruned terms in the model).
PRUNED = 1e8


def mackay_fixed_point(H: np.ndarray, theta: np.ndarray, alpha: np.ndarray, rounds: int = 50):
    """Prior precisions at MacKay's fixed point and the coefficients they imply, without new passes.

    At an optimum ``theta`` under the prior ``alpha`` the data term's gradient balances the prior
    (``J^T W r = A theta``); with the data term's curvature ``S`` (initial states integrated out), a new
    prior ``A'`` moves the optimum to ``theta + d`` with ``(S + A') d = (A - A') theta``. The fixed point
    ``alpha'_i = gamma_i / mu_i^2`` is iterated on that quadratic model.

    Returns
    -------
    alpha, mean : ndarray
    """
    S_data, _, _ = schur(H, np.zeros_like(alpha))
    curvature = np.diag(S_data)
    cap = np.where(curvature > 0, PRUNED * curvature, 1e300)
    a = np.minimum(np.array(alpha, dtype=float), cap)
    mu = np.array(theta, dtype=float)
    reach = TRUST * np.sqrt(np.maximum(np.diag(np.linalg.pinv(S_data + np.diag(alpha))), 0.0))
    kept = a
    for _ in range(rounds):
        P = S_data + np.diag(a)
        try:
            step = np.linalg.solve(P, (alpha - a) * theta)
            cov = np.linalg.inv(P)
        except np.linalg.LinAlgError:
            break
        # the quadratic model holds near the optimum only: a prior that would move a coefficient
        # by more than TRUST posterior deviations is not followed
        if not (np.all(np.isfinite(step)) and np.all(np.isfinite(cov))) or np.any(np.abs(step) > reach):
            return kept, mu
        kept, mu = a, theta + step
        gamma = np.clip(1.0 - a * np.diag(cov), 1e-12, 1.0)
        new = np.clip(gamma / np.maximum(np.clip(mu, -1e150, 1e150) ** 2, 1e-300), 1e-300, cap)
        done = np.max(np.abs(np.log(new) - np.log(a))) < 1e-4
        a = new
        if done:
            break
    return kept, mu


def _scaled_logdet(P: np.ndarray) -> float:
    """``log|P|`` of a symmetric positive (semi-)definite matrix, scaled to unit diagonal first; eigenvalues
    that round-off pushed below ``1e-14`` of the largest are floored there."""
    if P.size == 0:
        return 0.0
    d = np.sqrt(np.maximum(np.diag(P), 1e-300))
    ev = np.linalg.eigvalsh(P / np.outer(d, d))
    ev = np.maximum(ev, 1e-14 * max(float(ev.max()), 1e-300))
    return float(np.sum(np.log(ev)) + 2 * np.sum(np.log(d)))


def reprior(post: Posterior, alpha: np.ndarray, new_alpha: np.ndarray) -> Posterior:
    """The posterior and evidence under other prior precisions, from one fit (Laplace, no refit).

    With ``D = A' - A`` the new posterior has precision ``P' = P + D`` and mean ``P'^-1 P mu``, and
    the log evidence changes by ``1/2 log(|A'| / |A|) + 1/2 log(|P| / |P'|) - 1/2 mu'^T D mu``.
    """
    P = post.precision if post.precision is not None else np.linalg.inv(post.covariance)
    delta = np.asarray(new_alpha, dtype=float) - np.asarray(alpha, dtype=float)
    data = post.data_precision if post.data_precision is not None else P - np.diag(alpha)
    P_new = data + np.diag(new_alpha)
    d = np.sqrt(np.maximum(np.diag(P_new), 1e-300))
    scaled = P_new / np.outer(d, d)
    mean = np.linalg.solve(scaled, (P @ post.mean) / d) / d
    change = 0.5 * (
        float(np.sum(np.log(new_alpha) - np.log(alpha)))
        + _scaled_logdet(P)
        - _scaled_logdet(P_new)
        - float(mean @ (delta * post.mean))
    )
    cov = np.linalg.inv(scaled) / np.outer(d, d)
    return Posterior(mean, 0.5 * (cov + cov.T), post.log_evidence + change, post.log_det_x0, post.n_x0, P_new, data)


def reduce_model(post: Posterior, alpha: np.ndarray, off) -> tuple[float, np.ndarray, np.ndarray]:
    """Log-evidence change of switching the coefficients ``off`` to zero, and the reduced posterior.

    With a Gaussian prior ``N(0, 1/alpha)`` and posterior ``N(mu, Sigma)``, shrinking the prior of
    the coefficients ``R`` to zero gives (the Savage-Dickey ratio)::

        dF = -1/2 [mu_R^T Sigma_RR^-1 mu_R + log|Sigma_RR| + sum log alpha_R]

    and the reduced posterior of the others by conditioning on ``theta_R = 0``. For one coefficient
    ``-dF`` is the relevance vector machine's evidence contribution of the term. It is computed in
    the precision form (``Sigma_RR^-1 = P_RR - P_RK P_KK^-1 P_KR``, ``|Sigma_RR| = |P_KK| / |P|``),
    which stays well conditioned when the removed set mixes prior-dominated and data-dominated
    coefficients.

    Returns
    -------
    delta : float
        ``log evidence(reduced) - log evidence(full)``.
    mean, covariance : ndarray
        Of the remaining coefficients.
    """
    R = np.atleast_1d(np.asarray(off, dtype=int))
    keep = np.setdiff1d(np.arange(post.mean.size), R)
    P = post.precision if post.precision is not None else np.linalg.inv(post.covariance)
    Pkk, Pkr, Prr = P[np.ix_(keep, keep)], P[np.ix_(keep, R)], P[np.ix_(R, R)]
    if keep.size:
        d = np.sqrt(np.maximum(np.diag(Pkk), 1e-300))
        solved = np.linalg.solve(Pkk / np.outer(d, d), np.column_stack([Pkr, Pkr @ post.mean[R]]) / d[:, None])
        solved /= d[:, None]
        C = Prr - Pkr.T @ solved[:, : R.size]
        mean = post.mean[keep] + solved[:, R.size]
        cov = np.linalg.inv(Pkk / np.outer(d, d)) / np.outer(d, d)
        logdet_k = _scaled_logdet(Pkk)
    else:
        C, mean, cov, logdet_k = Prr, np.zeros(0), np.zeros((0, 0)), 0.0
    mu_r = post.mean[R]
    delta = -0.5 * float(mu_r @ C @ mu_r + logdet_k - _scaled_logdet(P) + np.sum(np.log(alpha[R])))
    return delta, mean, cov
