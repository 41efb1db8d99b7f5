"""Cross-validated free-run simulation error of a fitted structure, each fold predicted by the fit without it.

The records are cut into folds (the records themselves when there are at least :data:`MIN_FOLDS`, else
:data:`FOLDS` contiguous stretches of each). For each fold ``k`` the coefficients fitted without it follow
from one Gauss-Newton step of the fit on every fold with ``k`` left out (its initial state and its blocks
removed from the normal equations: the influence of the fold on the estimate, to first order), and the fold
is then simulated free from an initial state estimated on its first :func:`lead` samples, as benchmark
protocols do; its error is the RMS of the rest, relative to each channel's spread. A term fitted to what one
stretch of the record happens to hold (coloured noise, a disturbance, model error elsewhere) does not help
predict another, and its cross-validated error says so where its evidence cannot.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .laplace import schur, x0_pinv
from .sensitivity import Passes
from .solver import Iterate, Solution, initial_states, restrict

__all__ = ["Folds", "folds", "cross_validate", "CrossValidation"]

#: Contiguous folds per record when the records are too few to be the folds.
FOLDS = 5
#: Records from which each record is a fold of its own.
MIN_FOLDS = 3


@dataclass(frozen=True)
class Folds:
    """The folds of a cross-validation: each a stretch of rows ``[start, stop)`` of the records laid end to end,
    and the samples at its start that estimate its initial state."""

    starts: np.ndarray
    stops: np.ndarray
    lead: int

    def __len__(self) -> int:
        return len(self.starts)


def lead(length0: int, shortest: int) -> int:
    """Samples that estimate a fold's initial state: about four periods of the fastest motion measured (the
    refinement's first segment length, ``length0``), at most a quarter of the shortest fold."""
    return int(max(16, min(length0, shortest // 4)))


def folds(passes: Passes, length0: int) -> Folds | None:
    """The folds of ``passes``' records (None when a record is too short to be cut into folds)."""
    starts, lengths = passes.records.starts, passes.records.lengths
    if len(starts) >= MIN_FOLDS:
        a, b = np.array(starts), np.array(starts) + np.array(lengths)
    else:
        lo: list[int] = []
        hi: list[int] = []
        for s, n in zip(starts, lengths):
            cuts = s + (np.arange(FOLDS + 1) * n) // FOLDS
            lo.extend(cuts[:-1])
            hi.extend(cuts[1:])
        a, b = np.array(lo), np.array(hi)
    shortest = int(np.min(b - a))
    n_lead = lead(length0, shortest)
    if shortest < 4 * n_lead or shortest < 64:
        return None
    return Folds(a.astype(np.int64), b.astype(np.int64), n_lead)


@dataclass(frozen=True)
class CrossValidation:
    """The cross-validated free-run error of one structure.

    Attributes
    ----------
    fold_errors : ndarray, shape (n_folds,)
        Each fold's free-run RMS error over its samples after the lead, relative to each channel's spread and
        averaged over the channels (``inf`` where the simulation diverged).
    """

    fold_errors: np.ndarray

    @property
    def error(self) -> float:
        """The mean over the folds."""
        return float(np.mean(self.fold_errors))


def _downdated(blocks, theta: np.ndarray, alpha: np.ndarray, active: np.ndarray, k: int) -> np.ndarray:
    """The coefficients without fold ``k``: one Gauss-Newton step of the fit on the other folds from ``theta``,
    every fold's initial state eliminated."""
    npar = theta.size
    keep = np.array([j for j in range(blocks.H.shape[0]) if j != k])
    H, g = restrict(blocks.H[keep], blocks.g[keep], active, npar)
    a = alpha[active]
    S, _, _ = schur(H, a)
    pinv, _, _ = x0_pinv(H[:, a.size :, a.size :])
    gt = g[:, : a.size].sum(0) - np.einsum("kpi,kij,kj->p", H[:, : a.size, a.size :], pinv, g[:, a.size :])
    step = np.linalg.lstsq(S, gt - a * theta[active], rcond=None)[0]
    out = theta.copy()
    out[active] = theta[active] + step
    return out


@np.errstate(all="ignore")  # a fold whose prediction diverges has an infinite error
def cross_validate(passes: Passes, sol: Solution, cv: Folds) -> CrossValidation:
    """The cross-validated free-run error of the structure fitted in ``sol`` (its active coefficients)."""
    n = passes.records.n_total
    active = sol.active if sol.active is not None else np.arange(sol.theta.size)
    whole = passes.segments(sol.starts)
    simulated = passes.simulate(sol.theta, sol.X0, whole)
    starts = np.unique(np.concatenate([cv.starts, passes.records.starts]))
    seg = passes.segments(starts)
    X0 = simulated[starts]
    blocks = passes.sensitivities(sol.theta, X0, seg, sol.w, sol.ar)
    if not (np.all(np.isfinite(blocks.H)) and np.all(np.isfinite(blocks.g))):
        # a fold's free run diverged: every downdate holds it, so no fold has a finite error
        return CrossValidation(np.full(len(cv), np.inf))
    Y, valid = passes.records.Y, passes.valid[:n]
    spread = np.array([np.std(Y[valid[:, c], c]) for c in range(Y.shape[1])])
    spread[~(spread > 0)] = 1.0
    errors = []
    for a, b in zip(cv.starts, cv.stops):
        theta = _downdated(blocks, sol.theta, sol.alpha, active, int(np.searchsorted(starts, a)))
        # the fold's initial state fitted on its lead (the other segments' states do not matter), then the fold
        # simulated free from it to its end
        lead_starts = np.unique(np.concatenate([starts, [a + cv.lead]]))
        it, _ = initial_states(
            passes,
            Iterate(theta, simulated[lead_starts], passes.segments(lead_starts), sol.w, ar=sol.ar),
            sweeps=4,
            rows=(int(a), int(a) + cv.lead),
        )
        x0 = simulated[starts].copy()
        x0[np.searchsorted(starts, a)] = it.X0[np.searchsorted(lead_starts, a)]
        sim = passes.outputs(theta, x0, seg)
        rows = slice(a + cv.lead, b)
        err = (Y[rows] - sim[rows]) / spread
        ok = valid[rows]
        per_channel = [np.sqrt(np.mean(err[ok[:, c], c] ** 2)) for c in range(err.shape[1]) if ok[:, c].any()]
        value = float(np.mean(per_channel)) if per_channel else np.inf
        errors.append(value if np.isfinite(value) else np.inf)
    return CrossValidation(np.array(errors))
