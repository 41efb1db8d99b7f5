"""Sparse Bayesian learning on many column subsets of one problem at once.

A support search scores dozens of supports per move, each by refitting the RVM on its columns alone
(:func:`symsbl._regression.sbl.solve`). The supports are small (a few to a few dozen columns), so each
refit is about forty iterations of numpy calls on arrays of ten elements, and numpy's per-call cost is the
whole cost. :func:`solve_subsets` runs the same sequence of steps for every subset side by side, one
numpy call per step for all of them:

- each subset keeps its own active list, priors, posterior, noise precision, phase (plain, then
  penalised) and iteration counter, exactly as its own call of ``solve`` would;
- every array is padded to the largest subset (padded entries are zero, and never chosen), and every
  index is a position within the subset, as in its own call;
- additions, deletions and re-estimations are the same rank-one updates, applied to the subsets that
  chose them; a deletion shifts the positions after it, so the order of a subset's active list is its
  own call's;
- ties go to the first maximum, as in ``solve``.

The results agree with ``solve``'s to rounding: the padded sums differ in their last bits.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .sbl import (
    _ADD,
    _ALIGN_MAX,
    _BETA_UPDATE_EVERY,
    _BETA_UPDATE_START,
    _DELETE,
    _INIT_ALPHA_MAX,
    _MIN_DELTA_LOG_BETA,
    _REESTIMATE,
    _SPAN_TOL,
    _ZERO_FACTOR,
    Solution,
    contribution,
    log_evidence_at,
    posterior,
)

__all__ = ["solve_subsets"]


class _Batch:
    """The state of every subset's solver (see :class:`symsbl._regression.sbl._State`), padded.

    Shapes: ``T`` subsets, ``A`` the largest. Every index is a position within its subset (its sorted columns):
    ``G[t]`` is subset ``t``'s Gram matrix, zero past its size; ``act[t, p]`` the subset's column at active
    position ``p``, ``m[t]`` the number of active positions."""

    def __init__(self, gram, b, tt, n, subsets, beta, beta_max):
        T, A = len(subsets), max(len(s) for s in subsets)
        self.tt, self.n, self.beta_max = tt, n, beta_max
        sub = np.zeros((T, A), dtype=int)
        self.allowed = np.arange(A) < np.array([len(s) for s in subsets])[:, None]
        for t, cols in enumerate(subsets):
            sub[t, : len(cols)] = cols
        both = self.allowed[:, :, None] & self.allowed[:, None, :]
        self.G = np.where(both, gram[sub[:, :, None], sub[:, None, :]], 0.0)
        self.b = np.where(self.allowed, b[sub], 0.0)
        self.d = np.diagonal(self.G, axis1=1, axis2=2).copy()
        self.act = np.zeros((T, A), dtype=int)
        self.m = np.ones(T, dtype=int)
        self.alpha = np.ones((T, A))
        self.mu = np.zeros((T, A))
        self.sigma = np.zeros((T, A, A))
        self.cols = np.zeros((T, A, A))
        self.basis = np.zeros((T, A, A))
        self.S, self.Q = np.zeros((T, A)), np.zeros((T, A))
        self.log_det = np.zeros(T)
        self.beta = np.full(T, float(beta))
        norm = np.where(self.d > 0, np.sqrt(np.where(self.d > 0, self.d, 1.0)), np.inf)
        first = np.argmax(np.where(self.allowed, np.abs(self.b) / norm, -np.inf), axis=1)
        rows = np.arange(T)
        s0, q0 = beta * self.d[rows, first], beta * self.b[rows, first]
        theta0 = q0**2 - s0
        self.alpha[:, 0] = np.where(theta0 > 0, s0**2 / np.where(theta0 > 0, theta0, 1.0), _INIT_ALPHA_MAX)
        self.act[:, 0] = first
        self.cols[:, :, 0] = self.G[rows, first]
        self.aligned = np.abs(self.cols[:, :, 0]) > _ALIGN_MAX
        self.recompute(rows)

    def valid(self, idx):
        """Mask of the active positions, shape (len(idx), A)."""
        return np.arange(self.act.shape[1]) < self.m[idx, None]

    def block(self, idx):
        """``G`` among each subset's active columns, zero at padded positions, and the mask."""
        valid = self.valid(idx)
        g = np.take_along_axis(self.cols[idx], self.act[idx][:, :, None], axis=1)
        return np.where(valid[:, :, None] & valid[:, None, :], g, 0.0), valid

    def recompute(self, idx):
        """Posterior and factors of subsets ``idx`` from scratch (``_State.recompute``)."""
        g, valid = self.block(idx)
        beta = self.beta[idx]
        precision = beta[:, None, None] * g + _diag(np.where(valid, self.alpha[idx], 1.0))
        b_a = np.where(valid, np.take_along_axis(self.b[idx], self.act[idx], axis=1), 0.0)
        try:
            upper = np.linalg.cholesky(precision).transpose(0, 2, 1)
            u_inv = np.linalg.inv(upper)
            self.log_det[idx] = 2.0 * np.sum(np.log(np.diagonal(upper, axis1=1, axis2=2)), axis=1)
        except np.linalg.LinAlgError:  # a near-collinear subset: each factored as ``posterior`` does
            u_inv = np.zeros_like(precision)
            for r, t in enumerate(idx):
                m = self.m[t]
                _, _, u_inv[r, :m, :m], self.log_det[t] = posterior(
                    g[r, :m, :m], b_a[r, :m], self.alpha[t, :m], beta[r]
                )
        u_inv = np.where(valid[:, :, None] & valid[:, None, :], u_inv, 0.0)
        sigma = u_inv @ u_inv.transpose(0, 2, 1)
        self.sigma[idx] = sigma
        self.mu[idx] = beta[:, None] * np.einsum("rab,rb->ra", sigma, b_a)
        basis = beta[:, None, None] * self.cols[idx]
        self.basis[idx] = basis
        proj = basis @ u_inv
        self.S[idx] = beta[:, None] * self.d[idx] - np.sum(proj**2, axis=2)
        self.Q[idx] = beta[:, None] * self.b[idx] - np.einsum("rua,ra->ru", basis, self.mu[idx])

    def factors(self, idx):
        """Left-out sparsity and quality factors ``s``, ``q`` (``_State.factors``), shape (len(idx), A)."""
        s, q = self.S[idx], self.Q[idx]
        valid = self.valid(idx)
        sig = np.where(valid, np.diagonal(self.sigma[idx], axis1=1, axis2=2), 1.0)
        rows, pos = np.nonzero(valid)
        cols = self.act[idx][rows, pos]
        s[rows, cols] = 1.0 / sig[rows, pos] - self.alpha[idx][rows, pos]
        q[rows, cols] = self.mu[idx][rows, pos] / sig[rows, pos]
        return s, q, sig, valid

    def choose(self, idx, prune):
        """Every column's best action, its gain and new prior per subset (``sbl._choose``)."""
        s, q, sig, valid = self.factors(idx)
        R, A = s.shape
        act, alpha, rows = self.act[idx], self.alpha[idx], np.arange(R)[:, None]
        theta = q**2 - s
        gain, action, new_alpha = np.full((R, A), -np.inf), np.full((R, A), _ADD), np.full((R, A), np.inf)
        theta_u, s_u = theta[rows, act], s[rows, act]
        relevant = valid & (theta_u > _ZERO_FACTOR)
        a_new = np.where(relevant, s_u**2 / np.where(relevant, theta_u, 1.0), np.inf)
        S_u, Q_u = self.S[idx][rows, act], self.Q[idx][rows, act]
        delta = 1.0 / a_new - 1.0 / alpha
        with np.errstate(invalid="ignore", divide="ignore"):
            re_gain = 0.5 * (delta * Q_u**2 / (delta * S_u + 1.0) - np.log1p(S_u * delta))
        drop = contribution(self.mu[idx], sig, alpha)
        re_gain = np.where(relevant, re_gain, -np.inf)
        deletable = valid & (self.m[idx, None] > 1) & (~relevant | (prune[:, None] > 0))
        del_gain = np.where(deletable, prune[:, None] - drop, -np.inf)
        use_del = del_gain > re_gain
        rv, pv = np.nonzero(valid)  # padded positions point at column 0: only real ones are written
        cv = act[rv, pv]
        gain[rv, cv] = np.where(use_del, del_gain, re_gain)[rv, pv]
        action[rv, cv] = np.where(use_del, _DELETE, _REESTIMATE)[rv, pv]
        new_alpha[rv, cv] = np.where(use_del, np.inf, a_new)[rv, pv]
        is_active = np.zeros((R, A), dtype=bool)
        is_active[rv, cv] = True
        ok = self.allowed[idx] & ~is_active & ~self.aligned[idx] & (theta > _ZERO_FACTOR)
        ok &= s > _SPAN_TOL * self.beta[idx, None] * self.d[idx]
        with np.errstate(invalid="ignore", divide="ignore"):
            rho = np.where(ok, q**2 / np.where(ok, s, 1.0), 1.0)
            gain = np.where(ok, 0.5 * (rho - 1.0 - np.log(rho)) - prune[:, None], gain)
            new_alpha = np.where(ok, s**2 / np.where(ok, theta, 1.0), new_alpha)
        gain = np.where(self.allowed[idx], gain, -np.inf)
        pending = np.any(valid & use_del & (np.where(use_del, del_gain, re_gain) > 0), axis=1)
        gain = np.where(pending[:, None] & (action != _DELETE), -np.inf, gain)
        return gain, action, new_alpha, pending

    def step(self, idx, prune, tol):
        """One iteration of ``sbl._iterate`` for subsets ``idx``; returns which would terminate."""
        gain, action, new_alpha, pending = self.choose(idx, prune)
        R = len(idx)
        j = np.argmax(gain, axis=1)
        g_j, a_j, new_j = gain[np.arange(R), j], action[np.arange(R), j], new_alpha[np.arange(R), j]
        k = np.argmax((self.act[idx] == j[:, None]) & self.valid(idx), axis=1)
        terminate = ~(g_j > 0)
        re = ~terminate & (a_j == _REESTIMATE)
        with np.errstate(divide="ignore", invalid="ignore"):
            small = np.abs(np.log(new_j) - np.log(self.alpha[idx, k])) < tol
        terminate |= re & small & ~pending
        go = ~terminate
        for kind, apply in ((_REESTIMATE, self.reestimate), (_ADD, self.add), (_DELETE, self.delete)):
            sel = go & (a_j == kind)
            if sel.any():
                apply(idx[sel], k[sel], j[sel], new_j[sel])
        return terminate

    def reestimate(self, idx, k, j, new):
        """A new prior for active position ``k`` (``_State.reestimate``)."""
        r = np.arange(len(idx))
        sig_k, mu_k = self.sigma[idx, :, k], self.mu[idx, k]
        kappa = 1.0 / (sig_k[r, k] + 1.0 / (new - self.alpha[idx, k]))
        self.sigma[idx] -= kappa[:, None, None] * sig_k[:, :, None] * sig_k[:, None, :]
        self.mu[idx] -= (kappa * mu_k)[:, None] * sig_k
        tmp = np.einsum("rua,ra->ru", self.basis[idx], sig_k)
        self.S[idx] += kappa[:, None] * tmp**2
        self.Q[idx] += (kappa * mu_k)[:, None] * tmp
        self.alpha[idx, k] = new

    def add(self, idx, k, j, new):
        """Column ``j`` enters at the next position (``_State.add``)."""
        r, m = np.arange(len(idx)), self.m[idx]
        col = self.G[idx, j]
        sig_ii = 1.0 / (new + self.S[idx, j])
        mu_i = sig_ii * self.Q[idx, j]
        basis_i = self.beta[idx, None] * col
        x = np.where(self.valid(idx), np.take_along_axis(basis_i, self.act[idx], axis=1), 0.0)
        e = np.einsum("rab,rb->ra", self.sigma[idx], x)
        sigma = self.sigma[idx] + sig_ii[:, None, None] * e[:, :, None] * e[:, None, :]
        sigma[r, :, m] = sigma[r, m, :] = -sig_ii[:, None] * e
        sigma[r, m, m] = sig_ii
        self.sigma[idx] = sigma
        self.mu[idx] -= mu_i[:, None] * e
        self.mu[idx, m] = mu_i
        c = basis_i - np.einsum("rua,ra->ru", self.basis[idx], e)
        self.S[idx] -= sig_ii[:, None] * c**2
        self.Q[idx] -= mu_i[:, None] * c
        self.basis[idx, :, m], self.cols[idx, :, m] = basis_i, col
        self.aligned[idx] |= np.abs(col) > _ALIGN_MAX
        self.act[idx, m], self.alpha[idx, m] = j, new
        self.m[idx] += 1

    def delete(self, idx, k, j, new):
        """Active position ``k`` leaves; the positions after it shift down (``_State.delete``)."""
        r = np.arange(len(idx))
        sig_k, mu_k = self.sigma[idx, :, k], self.mu[idx, k]
        sig_kk = sig_k[r, k]
        self.sigma[idx] -= sig_k[:, :, None] * sig_k[:, None, :] / sig_kk[:, None, None]
        self.mu[idx] -= (mu_k / sig_kk)[:, None] * sig_k
        c = np.einsum("rua,ra->ru", self.basis[idx], sig_k)
        self.S[idx] += c**2 / sig_kk[:, None]
        self.Q[idx] += (mu_k / sig_kk)[:, None] * c
        A = self.act.shape[1]
        perm = np.minimum(np.arange(A) + (np.arange(A) >= k[:, None]), A - 1)
        self.sigma[idx] = np.take_along_axis(np.take_along_axis(self.sigma[idx], perm[:, :, None], 1), perm[:, None], 2)
        for name in ("mu", "alpha", "act"):
            getattr(self, name)[idx] = np.take_along_axis(getattr(self, name)[idx], perm, axis=1)
        for name in ("basis", "cols"):
            getattr(self, name)[idx] = np.take_along_axis(getattr(self, name)[idx], perm[:, None, :], axis=2)
        last = self.m[idx] - 1
        self.sigma[idx, last, :] = 0.0
        self.sigma[idx, :, last] = 0.0
        self.mu[idx, last], self.alpha[idx, last], self.act[idx, last] = 0.0, 1.0, 0
        self.basis[idx, :, last] = self.cols[idx, :, last] = 0.0
        self.aligned[idx] = np.any(np.abs(self.cols[idx]) > _ALIGN_MAX, axis=2)
        self.m[idx] = last

    def residual(self, idx):
        """``||t - Phi mu||^2`` of subsets ``idx`` from the Gram matrix, floored (``sbl._gram_residual``)."""
        g, valid = self.block(idx)
        mu = self.mu[idx]
        b_a = np.where(valid, np.take_along_axis(self.b[idx], self.act[idx], axis=1), 0.0)
        value = self.tt - 2.0 * np.sum(mu * b_a, axis=1) + np.einsum("ra,rab,rb->r", mu, g, mu)
        bound = np.einsum("ra,rab,rb->r", np.abs(mu), np.abs(g), np.abs(mu))
        bound = np.finfo(float).eps * (self.m[idx] + np.sqrt(self.n)) * (self.tt + bound)
        return np.maximum(value, bound)

    def update_noise(self, idx):
        """Re-estimate the noise of subsets ``idx``; returns which changed (and were recomputed)."""
        valid = self.valid(idx)
        gamma = np.where(valid, 1.0 - self.alpha[idx] * np.diagonal(self.sigma[idx], axis1=1, axis2=2), 0.0)
        new_beta = np.minimum((self.n - np.sum(gamma, axis=1)) / self.residual(idx), self.beta_max)
        changed = np.abs(np.log(new_beta) - np.log(self.beta[idx])) > _MIN_DELTA_LOG_BETA
        if changed.any():
            self.beta[idx[changed]] = new_beta[changed]
            self.recompute(idx[changed])
        return changed


def _diag(values):
    """Stacked diagonal matrices, shape (R, A, A), from ``values`` (R, A)."""
    out = np.zeros(values.shape + values.shape[-1:])
    idx = np.arange(values.shape[-1])
    out[:, idx, idx] = values
    return out


#: Doubles in one of a batch's (subsets, size, size) arrays at most: larger batches are fitted in parts.
_BATCH_DOUBLES = 2**22


def solve_subsets(
    gram,
    b,
    tt,
    n,
    var_t,
    subsets: Sequence[Sequence[int] | np.ndarray],
    *,
    prune,
    beta_fixed=None,
    beta_max=np.inf,
    max_iter=10000,
    tol=1e-3,
) -> list[Solution | None]:
    """:func:`symsbl._regression.sbl.solve` on each of ``subsets`` of one problem, in lockstep.

    Parameters
    ----------
    gram : ndarray, shape (U, U)
        ``D^T D`` of unit-norm (or zero) columns, symmetric.
    b, tt, n, var_t, beta_fixed, beta_max, max_iter, tol
        As for ``solve``.
    subsets : sequence of sequences of int
        Each subset's columns, as indices into ``gram``: non-empty and increasing.
    prune : float or ndarray, shape (len(subsets),)
        The penalty in nats per term, one for all or one per subset.

    Returns
    -------
    list of Solution or None
        Each subset's solution, its indices (``active``, ``s_out``, ``q_out``) local to the subset as if
        ``solve`` had been given the subset alone; None for a subset that did not converge within
        ``max_iter`` (its own call of ``solve`` then says so).
    """
    subsets = [np.asarray(cols, dtype=int) for cols in subsets]
    assert all(len(c) and np.all(np.diff(c) > 0) for c in subsets), "subsets must be non-empty and increasing"
    assert max_iter >= 1
    prune = np.broadcast_to(np.asarray(prune, dtype=float), (len(subsets),))
    gram, b = np.asarray(gram, dtype=float), np.asarray(b, dtype=float)
    out: list[Solution | None] = []
    size = max(len(c) for c in subsets) ** 2
    step = max(_BATCH_DOUBLES // size, 1)
    for lo in range(0, len(subsets), step):
        batch = subsets[lo : lo + step]
        beta = beta_fixed if beta_fixed is not None else min(1.0 / (0.01 * var_t), beta_max)
        out += _run(_Batch(gram, b, tt, n, batch, beta, beta_max), prune[lo : lo + step], beta_fixed, max_iter, tol)
    return out


def _run(batch: _Batch, prune, beta_fixed, max_iter, tol) -> list[Solution | None]:
    """Iterate every subset of ``batch`` to its end (``sbl.solve``'s two phases and ``sbl._iterate``)."""
    T = len(prune)
    phase = np.where(prune > 0, 0, 1)  # 0: the plain optimum first; 1: the objective with its penalty
    budget = np.where(phase == 0, max(max_iter // 2, 1), max_iter)
    used, it = np.zeros(T, dtype=int), np.zeros(T, dtype=int)
    done, converged = np.zeros(T, dtype=bool), np.zeros(T, dtype=bool)
    while not done.all():
        live = np.flatnonzero(~done)
        it[live] += 1
        terminate = batch.step(live, np.where(phase[live] == 0, 0.0, prune[live]), tol)
        if beta_fixed is None:
            due = terminate | (it[live] <= _BETA_UPDATE_START) | (it[live] % _BETA_UPDATE_EVERY == 0)
            if due.any():
                terminate[due] &= ~batch.update_noise(live[due])
        out = terminate | (it[live] >= budget[live])
        for t, ended in zip(live[out], terminate[out], strict=True):
            used[t] += it[t]
            if phase[t] == 0:
                phase[t], it[t], budget[t] = 1, 0, max_iter - used[t]
                done[t] = budget[t] <= 0
            else:
                done[t], converged[t] = True, bool(ended)
    every = np.arange(T)
    batch.recompute(every)  # clear rank-one drift before reporting
    s, q, _, _ = batch.factors(every)
    resid = batch.residual(every)
    return [_finish(batch, t, used[t], s[t], q[t], resid[t]) if converged[t] else None for t in range(T)]


def _finish(batch, t, n_iter, s, q, resid) -> Solution:
    """Subset ``t``'s solution (``sbl._finish``), from its factors ``s``, ``q`` and residual ``resid``."""
    m, size = int(batch.m[t]), int(batch.allowed[t].sum())
    order = np.argsort(batch.act[t, :m])
    u = batch.act[t, :m][order]
    alpha, mu = batch.alpha[t, :m][order], batch.mu[t, :m][order]
    sigma = batch.sigma[t][np.ix_(order, order)]
    beta = float(batch.beta[t])
    log_evidence = log_evidence_at(batch.n, beta, resid, mu, alpha, batch.log_det[t])
    return Solution(
        active=u,
        alpha=alpha,
        mu=mu,
        sigma=sigma,
        beta=beta,
        log_evidence=float(log_evidence),
        contribution=contribution(mu, np.diag(sigma), alpha),
        s_out=s[:size],
        q_out=q[:size],
        n_iter=int(n_iter),
        converged=True,
    )
