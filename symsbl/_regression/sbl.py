"""Sequential sparse Bayesian learning on a unit-normalised Gram matrix.

This is the numerical core behind :class:`symsbl.RVM`: the fast marginal-likelihood
algorithm of Tipping and Faul (2003), with the decision rule, initialisation, noise updates and
convergence test of Tipping's SparseBayes v2, written entirely in terms of the sufficient
statistics ``G = D^T D`` (columns scaled to unit norm), ``b = D^T t``, ``t^T t`` and ``N``.
After one O(N M^2) pass to build ``G`` every iteration costs O(M m + m^2), independent of N.

The solver reads ``G`` through a column source (:class:`DenseGram` for a matrix held in full):
its diagonal and the columns of the terms that enter, nothing else (the factors ``S``, ``Q`` of
every column follow from those), so columns may also be computed on demand from the design.

One addition to SparseBayes: an optional penalty of ``prune`` nats per non-free term, i.e. the
objective is ``L(alpha, beta) - prune * m``. Adding a term must gain more than ``prune`` nats of
log evidence and a kept term is deleted as soon as deleting it costs less than ``prune`` nats.
With ``prune = 0`` the rule is exactly SparseBayes v2. With ``prune > 0`` the solver first
converges with ``prune = 0`` and then continues from there with the penalty (a continuation: the
penalised greedy path alone can stall after one term among collinear candidates).

References
----------
M. E. Tipping and A. C. Faul, "Fast marginal likelihood maximisation for sparse Bayesian
models", AISTATS 2003.
M. E. Tipping, "Sparse Bayesian learning and the relevance vector machine", JMLR 1 (2001).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["DenseGram", "Solution", "contribution", "log_evidence_at", "posterior", "solve"]

_ZERO_FACTOR = 1e-12  # theta = q^2 - s below this counts as "not relevant" (SparseBayes)
_ALIGN_MAX = 1.0 - 1e-3  # refuse a column this aligned with an active one (SparseBayes)
_SPAN_TOL = 1e-10  # refuse a column whose part outside the active span is below this (relative)
_INIT_ALPHA_MAX = 1e3
_BETA_UPDATE_START = 10
_BETA_UPDATE_EVERY = 5
_MIN_DELTA_LOG_BETA = 1e-6

_REESTIMATE, _ADD, _DELETE = 0, 1, 2
_ACTION_NAMES = {_REESTIMATE: "re-estimate", _ADD: "add", _DELETE: "delete"}


class DenseGram:
    """Column source over a Gram matrix held in full: ``diag``, shape (n_terms,), and
    ``columns(idx, priority)`` returning ``G[:, idx]``. ``priority`` (a score per column, higher
    first) names the columns likely to be asked for next, for sources that compute columns in
    batches; this one ignores it."""

    def __init__(self, matrix):
        self.matrix = matrix
        self.diag = np.diag(matrix).copy()

    def columns(self, idx, priority=None):
        """``G[:, idx]``, shape (n_terms, len(idx))."""
        return self.matrix[:, idx]

    def block(self, idx):
        """``G[idx][:, idx]``, shape (len(idx), len(idx)), without copying the other rows of its columns."""
        return self.matrix[np.ix_(idx, idx)]


@dataclass(frozen=True)
class Solution:
    """Converged state in unit-norm column units (see :func:`solve`)."""

    active: np.ndarray  # (m,) sorted column indices
    alpha: np.ndarray  # (m,)
    mu: np.ndarray  # (m,)
    sigma: np.ndarray  # (m, m)
    beta: float
    log_evidence: float
    contribution: np.ndarray  # (m,) log-evidence drop (nats) from deleting each term
    s_out: np.ndarray  # (M,) sparsity factor s_i with basis i left out
    q_out: np.ndarray  # (M,) quality factor q_i with basis i left out
    n_iter: int
    converged: bool


def posterior(gram_uu, b_u, alpha, beta):
    """Posterior of the active weights for fixed hyperparameters.

    Parameters
    ----------
    gram_uu : ndarray, shape (m, m)
        Gram matrix of the active columns.
    b_u : ndarray, shape (m,)
        Inner products of the active columns with the target.
    alpha : ndarray, shape (m,)
        Prior precisions.
    beta : float
        Noise precision.

    Returns
    -------
    mu : ndarray, shape (m,)
    sigma : ndarray, shape (m, m)
    u_inv : ndarray, shape (m, m)
        Inverse of the upper Cholesky factor ``U`` of ``Sigma^-1 = beta G_uu + diag(alpha)``,
        so ``Sigma = u_inv @ u_inv.T``.
    log_det_precision : float
        ``log |Sigma^-1|``.
    """
    precision = beta * gram_uu + np.diag(alpha)
    try:
        upper = np.linalg.cholesky(precision).T
    except np.linalg.LinAlgError:
        # Near-collinear active set: a relative jitter restores positive definiteness.
        jitter = 1e-12 * np.trace(precision) / len(alpha)
        upper = np.linalg.cholesky(precision + jitter * np.eye(len(alpha))).T
    # numpy's LAPACK for these small (m, m) factors: dispatching them to a second BLAS
    # library costs milliseconds of thread hand-over per call after a large Gram product.
    u_inv = np.linalg.inv(upper)
    sigma = u_inv @ u_inv.T
    mu = beta * (sigma @ b_u)
    return mu, sigma, u_inv, 2.0 * float(np.sum(np.log(np.diag(upper))))


class _State:
    """Active set, posterior and the factors S, Q of every column (Tipping & Faul Appendix A).

    ``cols`` holds ``G[:, active]``, the only Gram columns the algorithm reads."""

    def __init__(self, gram, b, beta, active, alpha, priority=None):
        self.gram, self.b, self.beta, self.diag = gram, b, beta, gram.diag
        self.active = list(active)
        self.alpha = np.asarray(alpha, dtype=float)
        self.cols = np.array(gram.columns(self.active, priority), dtype=float).reshape(len(b), -1)
        self.aligned = np.any(np.abs(self.cols) > _ALIGN_MAX, axis=1)
        self.recompute()

    def recompute(self):
        u = self.active
        self.mu, self.sigma, u_inv, self.log_det = posterior(self.cols[u], self.b[u], self.alpha, self.beta)
        self.basis = self.beta * self.cols  # (M, m) beta * D^T Phi
        proj = self.basis @ u_inv
        self.S = self.beta * self.diag - np.sum(proj**2, axis=1)
        self.Q = self.beta * self.b - self.basis @ self.mu

    def factors(self):
        """Sparsity and quality factors with each basis left out, ``s`` and ``q``."""
        s, q = self.S.copy(), self.Q.copy()
        # For an active basis, alpha - S = alpha^2 Sigma_ii and Q = alpha mu_i, so the
        # left-out factors follow from the posterior without cancellation.
        sig = np.diag(self.sigma)
        s[self.active] = 1.0 / sig - self.alpha
        q[self.active] = self.mu / sig
        return s, q

    def contribution(self):
        """Exact log-evidence drop from deleting each active basis (others fixed):
        ``1/2 [mu_i^2 / Sigma_ii + log(alpha_i Sigma_ii)]``."""
        return contribution(self.mu, np.diag(self.sigma), self.alpha)

    def reestimate(self, k, new_alpha):
        sig_k, mu_k = self.sigma[:, k].copy(), self.mu[k]
        kappa = 1.0 / (sig_k[k] + 1.0 / (new_alpha - self.alpha[k]))
        self.sigma -= kappa * np.outer(sig_k, sig_k)
        self.mu -= kappa * mu_k * sig_k
        tmp = self.basis @ sig_k
        self.S += kappa * tmp**2
        self.Q += kappa * mu_k * tmp
        self.alpha[k] = new_alpha

    def add(self, i, new_alpha, priority=None):
        col = np.asarray(self.gram.columns([i], priority), dtype=float).reshape(-1)
        sig_ii = 1.0 / (new_alpha + self.S[i])
        mu_i = sig_ii * self.Q[i]
        basis_i = self.beta * col
        e = self.sigma @ basis_i[self.active]
        m = len(self.active)
        sigma = np.empty((m + 1, m + 1))
        sigma[:m, :m] = self.sigma + sig_ii * np.outer(e, e)
        sigma[:m, m] = sigma[m, :m] = -sig_ii * e
        sigma[m, m] = sig_ii
        self.sigma = sigma
        self.mu = np.append(self.mu - mu_i * e, mu_i)
        c = basis_i - self.basis @ e
        self.S -= sig_ii * c**2
        self.Q -= mu_i * c
        self.basis = np.column_stack([self.basis, basis_i])
        self.cols = np.column_stack([self.cols, col])
        self.aligned |= np.abs(col) > _ALIGN_MAX
        self.active.append(i)
        self.alpha = np.append(self.alpha, new_alpha)

    def delete(self, k):
        sig_k, sig_kk, mu_k = self.sigma[:, k].copy(), self.sigma[k, k], self.mu[k]
        self.sigma -= np.outer(sig_k, sig_k) / sig_kk
        self.mu -= mu_k * sig_k / sig_kk
        c = self.basis @ sig_k
        self.S += c**2 / sig_kk
        self.Q += mu_k * c / sig_kk
        keep = np.arange(len(self.active)) != k
        self.sigma = self.sigma[np.ix_(keep, keep)]
        self.mu, self.alpha = self.mu[keep], self.alpha[keep]
        self.basis, self.cols = self.basis[:, keep], self.cols[:, keep]
        self.aligned = np.any(np.abs(self.cols) > _ALIGN_MAX, axis=1)
        del self.active[k]


def _choose(state, s, q, free_mask, prune):
    """Best action of every basis and its log-evidence gain (penalised by ``prune`` per term)."""
    M = len(s)
    theta = q**2 - s
    gain = np.full(M, -np.inf)
    action = np.full(M, _ADD)
    new_alpha = np.full(M, np.inf)
    u = np.asarray(state.active)

    # Re-estimation of active bases with theta > 0.
    theta_u, s_u = theta[u], s[u]
    relevant = theta_u > _ZERO_FACTOR
    a_new = np.where(relevant, s_u**2 / np.where(relevant, theta_u, 1.0), np.inf)
    delta = 1.0 / a_new - 1.0 / state.alpha
    S_u, Q_u = state.S[u], state.Q[u]
    with np.errstate(invalid="ignore", divide="ignore"):
        re_gain = 0.5 * (delta * Q_u**2 / (delta * S_u + 1.0) - np.log1p(S_u * delta))
    re_gain[~relevant] = -np.inf
    # Deletion of active, non-free bases (always possible when a penalty is set).
    deletable = ~free_mask[u] & (len(u) > 1) & (~relevant | (prune > 0))
    del_gain = np.where(deletable, prune - state.contribution(), -np.inf)
    use_del = del_gain > re_gain
    gain[u] = np.where(use_del, del_gain, re_gain)
    action[u] = np.where(use_del, _DELETE, _REESTIMATE)
    new_alpha[u] = np.where(use_del, np.inf, a_new)

    # Addition of inactive bases with theta > 0, unless aligned with an active column.
    ok = (theta > _ZERO_FACTOR) & (s > _SPAN_TOL * state.beta * state.diag) & ~state.aligned
    ok[u] = False
    add = np.flatnonzero(ok)
    rho = q[add] ** 2 / s[add]
    gain[add] = 0.5 * (rho - 1.0 - np.log(rho)) - prune
    new_alpha[add] = s[add] ** 2 / theta[add]

    deletion_pending = bool((gain[u][use_del] > 0).any())
    if deletion_pending:  # SparseBayes "priority deletion"
        gain = np.where(action == _DELETE, gain, -np.inf)
    return gain, action, new_alpha, deletion_pending


def solve(
    gram,
    b,
    tt,
    n,
    var_t,
    *,
    beta_fixed=None,
    beta_max=np.inf,
    free=(),
    prune=0.0,
    max_iter=10000,
    tol=1e-3,
    residual: Callable | None = None,
    log: Callable | None = None,
):
    """Maximise the (optionally penalised) marginal likelihood from sufficient statistics.

    Parameters
    ----------
    gram : ndarray, shape (n_terms, n_terms), or a column source
        ``D^T D`` of unit-norm (or zero) columns, or an object that hands out its diagonal and
        columns (see :class:`DenseGram`); only the columns of terms that enter are read.
    b : ndarray, shape (n_terms,)
        ``D^T t``.
    tt : float
        ``t^T t``.
    n : float
        Number of samples (possibly effective).
    var_t : float
        Variance of the target, used for the initial noise and the noise floor.
    beta_fixed : float or None
        Fixed noise precision; ``None`` re-estimates it.
    beta_max : float
        Upper bound on the noise precision (the noise floor).
    free : sequence of int
        Columns that are always in the model.
    prune : float
        Penalty in nats per non-free term (0 gives SparseBayes v2).
    max_iter : int
        Maximum number of iterations.
    tol : float
        Convergence threshold on the change of ``log alpha``.
    residual : callable or None
        ``residual(active, mu) -> ||t - Phi mu||^2``; by default computed from the Gram matrix.
    log : callable or None
        Called with one line of text per iteration.

    Returns
    -------
    Solution
    """
    M = len(b)
    gram = DenseGram(gram) if isinstance(gram, np.ndarray) else gram
    diag = gram.diag
    free = list(free)
    free_mask = np.zeros(M, dtype=bool)
    free_mask[free] = True
    residual = residual or _gram_residual(gram, b, tt, n)

    beta = beta_fixed if beta_fixed is not None else min(1.0 / (0.01 * var_t), beta_max)
    norm = np.where(diag > 0, np.sqrt(diag), np.inf)
    active = free if free else [int(np.argmax(np.abs(b) / norm))]
    s0, q0 = beta * diag[active], beta * b[active]
    theta0 = q0**2 - s0
    alpha0 = np.where(theta0 > 0, s0**2 / np.where(theta0 > 0, theta0, 1.0), _INIT_ALPHA_MAX)
    # Columns are admitted in order of q^2 / s; before any is in, that is (b_i / ||d_i||)^2.
    state = _State(gram, b, beta, active, alpha0, priority=np.abs(b) / norm)

    # Continuation: reach the plain SparseBayes optimum first, then switch the penalty on and
    # let it delete (and re-admit) terms from there. Started with the penalty on, the greedy
    # path can stop after one term when every next useful column is collinear with others and
    # none gains ``prune`` nats on its own, although the penalised optimum is far better.
    # the plain optimum is only the penalised search's start: it gets half the iterations when a penalty follows
    first = max_iter if prune <= 0 else max(max_iter // 2, 1)
    n_iter, converged = _iterate(state, 0.0, first, free_mask, beta_fixed, beta_max, tol, residual, n, log)
    if prune > 0:
        more, converged = _iterate(
            state, prune, max_iter - n_iter, free_mask, beta_fixed, beta_max, tol, residual, n, log
        )
        n_iter += more

    state.recompute()  # clear rank-one drift before reporting
    return _finish(state, residual, n, n_iter, converged)


def _iterate(state, prune, max_iter, free_mask, beta_fixed, beta_max, tol, residual, n, log):
    """Run add / delete / re-estimate steps on ``state`` until convergence or ``max_iter``;
    return the number of iterations and whether it converged."""
    converged = False
    n_iter = 0
    for n_iter in range(1, max_iter + 1):
        s, q = state.factors()
        gain, action, new_alpha, deletion_pending = _choose(state, s, q, free_mask, prune)
        j = int(np.argmax(gain))
        terminate = not gain[j] > 0
        if not terminate and action[j] == _REESTIMATE:
            k = state.active.index(j)
            small = abs(np.log(new_alpha[j]) - np.log(state.alpha[k])) < tol
            terminate = small and not deletion_pending
        if not terminate:
            if action[j] == _REESTIMATE:
                state.reestimate(state.active.index(j), new_alpha[j])
            elif action[j] == _ADD:
                state.add(j, new_alpha[j], priority=np.where(action == _ADD, gain, -np.inf))
            else:
                state.delete(state.active.index(j))
            if log is not None:
                log(
                    f"iter {n_iter:5d}  {_ACTION_NAMES[int(action[j])]:11s} column {j:4d}"
                    f"  gain {gain[j]:.4g} nats  m = {len(state.active)}"
                )

        if beta_fixed is None and (terminate or n_iter <= _BETA_UPDATE_START or n_iter % _BETA_UPDATE_EVERY == 0):
            gamma = 1.0 - state.alpha * np.diag(state.sigma)
            resid = residual(state.active, state.mu)
            new_beta = min((n - np.sum(gamma)) / resid, beta_max)
            if abs(np.log(new_beta) - np.log(state.beta)) > _MIN_DELTA_LOG_BETA:
                state.beta = new_beta
                state.recompute()
                terminate = False
        if terminate:
            converged = True
            break
    return n_iter, converged


def contribution(mu, sig, alpha):
    """Exact log-evidence drop from deleting each active basis, others fixed, from its posterior mean ``mu``,
    variance ``sig`` and prior ``alpha``: ``1/2 [mu_i^2 / Sigma_ii + log(alpha_i Sigma_ii)]``."""
    return 0.5 * (mu**2 / sig + np.log(alpha * sig))


def log_evidence_at(n, beta, resid, mu, alpha, log_det):
    """Log marginal likelihood at the posterior mean ``mu`` of ``n`` samples with noise precision ``beta``,
    residual ``resid = ||t - Phi mu||^2``, priors ``alpha`` and ``log_det = log |Sigma^-1|``."""
    return 0.5 * (
        n * np.log(beta) - beta * resid - mu @ (alpha * mu) + np.sum(np.log(alpha)) - log_det - n * np.log(2.0 * np.pi)
    )


def _gram_residual(gram, b, tt, n):
    """``||t - Phi mu||^2`` from the Gram matrix, floored at its own rounding-error bound."""
    eps = np.finfo(float).eps

    def residual(active, mu):
        # a source that holds the matrix hands out the block alone: its columns cost n_terms rows each
        g = gram.block(active) if hasattr(gram, "block") else gram.columns(active)[active]
        value = tt - 2.0 * mu @ b[active] + mu @ g @ mu
        bound = eps * (len(mu) + np.sqrt(n)) * (tt + np.abs(mu) @ np.abs(g) @ np.abs(mu))
        return max(value, bound)

    return residual


def _finish(state, residual, n, n_iter, converged):
    s, q = state.factors()
    order = np.argsort(state.active)
    u = np.asarray(state.active)[order]
    alpha = state.alpha[order]
    mu = state.mu[order]
    sigma = state.sigma[np.ix_(order, order)]
    beta = state.beta
    log_evidence = log_evidence_at(n, beta, residual(list(u), mu), mu, alpha, state.log_det)
    drop = state.contribution()[order]
    return Solution(
        active=u,
        alpha=alpha,
        mu=mu,
        sigma=sigma,
        beta=float(beta),
        log_evidence=float(log_evidence),
        contribution=drop,
        s_out=s,
        q_out=q,
        n_iter=n_iter,
        converged=converged,
    )
