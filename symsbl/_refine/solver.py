"""Levenberg-Marquardt on segmented output error, with continuation in the segment length.

The record is cut into segments, each with its own free initial state; the coefficients are shared.
The normal equations are arrow-shaped, so the segment states are eliminated by a Schur complement
per segment and an iteration costs one compiled pass plus ``O(K n_x^3 + n_theta^3)``. From short
segments (each barely longer than the system's memory, so a poor starting point cannot make the
simulation run away) the fit continues with segments ``growth`` times longer, warm-started, until one
segment spans each record (the true output error) or a segment's state-transition matrix grows past
:data:`PHI_STOP` (a chaotic or unstable system, whose long-horizon output error is ill-posed: the fit
stays at that segment length, which is still a consistent estimator). After each stage the whole
records are tried at once and kept when they simulate the data about as well as the segments did
(:func:`_jump`), which skips the stages between when the coefficients are already good.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from .._base.errors import SimulationError, expected
from .._data.trajectory import third_difference_std
from .laplace import Posterior, mackay_fixed_point, posterior
from .noise import NoiseModel, choose_order, fit_ar
from .sensitivity import Blocks, Passes, Segments

__all__ = [
    "Solution",
    "Warm",
    "restarted",
    "Iterate",
    "fit",
    "lm",
    "noise_precisions",
    "pooled",
    "initial_states",
    "horizon",
    "PHI_STOP",
    "LM_STEPS",
]

#: Largest growth of a segment's state-transition matrix before the segments stop lengthening.
PHI_STOP = 1e4

#: Excess of the whole records' cost over the segments' (as a share of it) up to which the continuation
#: jumps to whole records (see :func:`_jump`).
JUMP = 0.02


@dataclass(frozen=True)
class Iterate:
    """Where a fit stands: coefficients, the segments and their initial states, the noise precisions, and
    the blocks of the pass made there (None until one is made). Every step of the solver takes one and
    returns a new one.

    Attributes
    ----------
    theta : ndarray, shape (n_free,)
    X0 : ndarray, shape (n_segments, n_states)
    seg : Segments
    w : ndarray, shape (n_records, n_measured)
        Noise precisions of the measured channels in each record (of their innovations, with an autoregressive
        noise model).
    blocks : Blocks or None
    ar : ndarray, shape (n_measured, order), optional
        The autoregressive noise model (see :mod:`symsbl._refine.noise`); None: white noise.
    """

    theta: np.ndarray
    X0: np.ndarray
    seg: Segments
    w: np.ndarray
    blocks: Blocks | None = None
    ar: np.ndarray | None = None

    @property
    def order(self) -> int:
        return 0 if self.ar is None else int(self.ar.shape[1])

    @property
    def made(self) -> Blocks:
        """The blocks of the pass made at this iterate (see :meth:`evaluated`)."""
        assert self.blocks is not None  # every step evaluates an iterate before it reads the pass
        return self.blocks

    def evaluated(self, passes: Passes, stop=None, rows=None) -> tuple[Iterate, int]:
        """This iterate with its pass made (and the number of passes that took: 0 or 1); ``stop``, ``rows``: see
        :meth:`~symsbl._refine.sensitivity.Passes.sensitivities`."""
        if self.blocks is not None:
            return self, 0
        blocks = passes.sensitivities(self.theta, self.X0, self.seg, self.w, self.ar, stop, rows)
        return replace(self, blocks=blocks), 1


@dataclass
class Solution:
    """An output-error optimum with its posterior."""

    theta: np.ndarray
    X0: np.ndarray
    starts: np.ndarray
    length: int
    cost: float
    ssr: np.ndarray
    w: np.ndarray
    alpha: np.ndarray
    posterior: Posterior
    #: The Gauss-Newton blocks of the last pass (zero outside ``active`` when the pass carried only those).
    H: np.ndarray
    #: The indices of the coefficients fitted (the others held where they started).
    active: np.ndarray
    stages: list = field(default_factory=list)
    n_pass: int = 0
    #: The nats per term selection asked for; refits' evidence for terms the posterior put below it (by index).
    penalty: float | None = None
    confirmed: dict = field(default_factory=dict)
    ar: np.ndarray | None = None
    n_kept: np.ndarray | None = None
    #: Samples kept per record and channel, ``(n_records, n_measured)``.
    n_kept_by_record: np.ndarray | None = None

    @property
    def noise(self) -> NoiseModel:
        """The noise model of the fit."""
        return NoiseModel(np.zeros((self.w.shape[-1], 0)) if self.ar is None else self.ar)

    @property
    def channel_w(self) -> np.ndarray:
        """One noise precision per channel, ``(n_measured,)``, the records pooled by their samples."""
        return pooled(self.w, self.n_kept_by_record)


@dataclass(frozen=True)
class Warm:
    """Where a fit starts warm: the attributes of a :class:`Solution` that a warm start reads.

    Attributes
    ----------
    X0 : ndarray, shape (n_segments, n_states)
        The segments' initial states.
    starts : ndarray of int
        The segments' first rows (every record's first row among them).
    length : int
        The segment length, which the fit keeps.
    w : ndarray, shape (n_records, n_measured)
        Noise precisions.
    ar : ndarray, shape (n_measured, order), optional
        The autoregressive noise model; None: white noise.
    """

    X0: np.ndarray
    starts: np.ndarray
    length: int
    w: np.ndarray
    ar: np.ndarray | None = None


def restarted(sol: Solution, passes: Passes, longest: int | None = None) -> Warm | None:
    """The warm start, on ``passes``' records, of the whole-record fit ``sol`` of the same records or of their first
    stretches: each record one segment from ``sol``'s initial state, with ``sol``'s noise. None unless ``sol`` held
    one segment per record, its model amplifies no state error :data:`PHI_STOP`-fold within them (the continuation
    would hold such records on shorter segments) and they are no longer than ``longest``."""
    records = passes.records
    length = int(records.lengths.max())
    reach = horizon(sol.stages)
    if len(sol.starts) != len(records.starts) or (reach is not None and reach < length):
        return None
    if longest is not None and length > longest:
        return None
    return Warm(sol.X0.copy(), records.starts.copy(), length, sol.w, sol.ar)


def noise_precisions(Y: np.ndarray, valid: np.ndarray, starts=None) -> np.ndarray:
    """Per record and channel, ``1 / sigma^2`` of white noise from third differences (robust: median absolute
    deviation), ``(n_records, n_channels)``; ``starts`` are the records' first rows (default: one record)."""
    starts = [0] if starts is None else [int(a) for a in starts]
    stops = starts[1:] + [len(Y)]
    return np.array(
        [
            [1.0 / max(third_difference_std(Y[a:b][valid[a:b, c], c]) ** 2, 1e-300) for c in range(Y.shape[1])]
            for a, b in zip(starts, stops)
        ]
    )


def pooled(w: np.ndarray, n: np.ndarray | None = None) -> np.ndarray:
    """One noise precision per channel from per-record ones ``(n_records, n_channels)``: the precision of the
    pooled variance, the records weighted by their samples ``n`` (default equally)."""
    w = np.atleast_2d(np.asarray(w, dtype=float))
    n = np.ones_like(w) if n is None else np.broadcast_to(np.asarray(n, dtype=float), w.shape)
    return np.sum(n, axis=0) / np.maximum(np.sum(n / w, axis=0), 1e-300)


def restrict(H: np.ndarray, g: np.ndarray | None, active: np.ndarray, npar: int):
    """The blocks of the active coefficients (and every segment's initial state)."""
    idx = np.concatenate([active, npar + np.arange(H.shape[1] - npar)])
    return H[:, idx][:, :, idx], (None if g is None else g[:, idx])


# -- the damped step -------------------------------------------------------------------------------
def damped_step(H, g, theta, alpha, lam):
    """The Levenberg-Marquardt step ``(H + A + lam diag) d = g - A theta`` with every segment's initial state
    eliminated by its own Schur complement; returns the coefficients' step, the initial states' steps and
    the decrease of the quadratic model."""
    npar = theta.size
    Htt = H[:, :npar, :npar].sum(0) + np.diag(alpha)
    Htx, Hxx = H[:, :npar, npar:], H[:, npar:, npar:].copy()
    gt, gx = g[:, :npar].sum(0) - alpha * theta, g[:, npar:]
    nx = Hxx.shape[1]
    dxx = np.einsum("kii->ki", Hxx)
    scale = np.sqrt(np.where(dxx > 0, dxx, 1.0))  # each state in its own unit: solve the unit-diagonal system
    Hxx /= scale[:, :, None] * scale[:, None, :]
    Hxx[:, np.arange(nx), np.arange(nx)] += lam * (dxx > 0) + 1e-12
    rhs = np.concatenate([np.transpose(Htx, (0, 2, 1)), gx[:, :, None]], axis=2)
    sol = np.linalg.solve(Hxx, rhs / scale[:, :, None]) / scale[:, :, None]
    S = Htt + np.diag(lam * np.diag(Htt)) - np.einsum("kpi,kiq->pq", Htx, sol[:, :, :npar])
    b = gt - np.einsum("kpi,ki->p", Htx, sol[:, :, npar])
    d = np.sqrt(np.maximum(np.diag(S), 1e-300))
    dth = np.linalg.solve(S / np.outer(d, d), b / d) / d
    dX = sol[:, :, npar] - np.einsum("kip,p->ki", sol[:, :, :npar], dth)
    Hd_t = Htt @ dth + np.einsum("kpi,ki->p", Htx, dX)
    Hd_x = np.einsum("kpi,p->ki", Htx, dth) + np.einsum("kij,kj->ki", H[:, npar:, npar:], dX)
    predicted = dth @ gt + np.sum(dX * gx) - 0.5 * (dth @ Hd_t + np.sum(dX * Hd_x))
    return dth, dX, predicted


# -- the acceptance rule ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Damping:
    """The Levenberg-Marquardt damping ``lam`` and its growth factor ``nu`` (Nielsen's update)."""

    lam: float = 1e-4
    nu: float = 2.0

    def accepted(self, rho: float) -> Damping:
        """After an accepted step with gain ratio ``rho``: less damping."""
        return Damping(max(self.lam * max(0.1, 1 - (2 * rho - 1) ** 3), 1e-12), 2.0)

    def refused(self) -> Damping:
        """After a refused step: more damping, growing faster each time."""
        return Damping(self.lam * self.nu, self.nu * 2.0)


def _objective(blocks: Blocks, theta, alpha, active) -> float:
    return blocks.cost + _prior_term(theta, alpha, active)


def _prior_term(theta, alpha, active) -> float:
    return 0.5 * float(np.sum(alpha[active] * theta[active] ** 2))


def accept(E: float, E_trial: float, predicted: float) -> tuple[bool, float]:
    """Whether a trial step is taken, and its gain ratio: the actual decrease of the objective over the
    quadratic model's, which must be positive beyond round-off."""
    rho = (E - E_trial) / predicted if predicted > 0 else -1.0
    return bool(np.isfinite(E_trial) and rho > 1e-4), rho


#: Levenberg-Marquardt steps of one round at most.
LM_STEPS = 60
#: A crawl ends a round: its last CRAWL_PASSES passes lowered the objective by less than CRAWL_NATS together.
CRAWL_PASSES, CRAWL_NATS = 10, 0.1


@np.errstate(over="ignore", invalid="ignore")  # a trial that overflows is rejected by its non-finite cost
def lm(
    passes: Passes,
    it: Iterate,
    alpha,
    active,
    *,
    tol: float,
    max_iter: int = LM_STEPS,
    damping: Damping = Damping(),
    crawl: bool = True,
) -> tuple[Iterate, int]:
    """Levenberg-Marquardt on the ``active`` coefficients (the others stay as they are) at fixed noise
    precisions and segments; returns the iterate reached (with its pass) and the number of passes made.

    A round ends at ``tol``, after ``max_iter`` passes, or (``crawl``) when its last :data:`CRAWL_PASSES`
    passes lowered the objective by less than :data:`CRAWL_NATS`: a misfitting structure over-predicts its
    Gauss-Newton steps, which then gain a thousandth to a hundredth of a nat each, far below the nats the
    model choice weighs."""
    it, n_pass = it.evaluated(passes)
    npar = it.theta.size
    E = _objective(it.made, it.theta, alpha, active)
    if not np.isfinite(E):
        return it, n_pass
    history = [E]  # the objective after each pass
    for _ in range(max_iter):
        Hs, gs = restrict(it.made.H, it.made.g, active, npar)
        try:
            step, dX, predicted = damped_step(Hs, gs, it.theta[active], alpha[active], damping.lam)
        except np.linalg.LinAlgError:
            step, dX, predicted = None, None, np.nan
        if not (np.isfinite(predicted) and np.all(np.isfinite(step)) and np.all(np.isfinite(dX))):
            damping = damping.refused()
            if damping.lam > 1e12:
                break
            continue
        dth = np.zeros(npar)
        dth[active] = step
        theta = it.theta + dth
        prior = _prior_term(theta, alpha, active)

        def refused(cost, E=E, prior=prior, predicted=predicted):  # the cost only grows over the rest of the pass
            return not accept(E, cost + prior, predicted)[0]

        trial, _ = replace(it, theta=theta, X0=it.X0 + dX, blocks=None).evaluated(passes, stop=refused)
        n_pass += 1
        E_trial = _objective(trial.made, trial.theta, alpha, active)
        taken, rho = accept(E, E_trial, predicted)
        if taken:
            E_old, E, it = E, E_trial, trial
            damping = damping.accepted(rho)
            if predicted < tol and E_old - E < 2 * tol:
                break
        else:
            if predicted < 1e-3 * tol:
                break
            damping = damping.refused()
        history.append(E)
        if crawl and len(history) > CRAWL_PASSES and history[-CRAWL_PASSES - 1] - E < CRAWL_NATS:
            break
    return it, n_pass


@np.errstate(over="ignore", invalid="ignore")
def initial_states(
    passes: Passes, it: Iterate, sweeps: int = 3, tol: float = 0.1, rtol: float = 1e-3, rows=None
) -> tuple[Iterate, int]:
    """Gauss-Newton on the segments' initial states alone (coefficients fixed), accepted per segment; a
    segment whose step does not lower its cost tries a quarter of it next. At most ``sweeps`` sweeps, fewer
    once every segment's step was accepted and they gained less than ``tol`` nats or ``rtol`` of the cost
    together (the joint fit that follows finishes what is left: it is a start, not the answer). Returns the
    iterate (with its pass) and the number of passes made. ``rows``: only the segments within these rows are
    fitted (see :meth:`~symsbl._refine.sensitivity.Passes.sensitivities`; the others' blocks are zero)."""
    npar = it.theta.size
    it, n_pass = it.evaluated(passes, rows=rows)
    X0, blocks = it.X0, it.made
    cost = 0.5 * blocks.rr.sum(1)
    shrink = np.ones(len(X0))
    for _ in range(sweeps):
        Hxx = blocks.H[:, npar:, npar:].copy()
        nx = Hxx.shape[1]
        dxx = np.einsum("kii->ki", Hxx)
        Hxx[:, np.arange(nx), np.arange(nx)] += 1e-9 * dxx + 1e-300
        dX = np.linalg.solve(Hxx, blocks.g[:, npar:, None])[:, :, 0] * shrink[:, None]
        trial = passes.sensitivities(it.theta, X0 + dX, it.seg, it.w, it.ar, rows=rows)
        n_pass += 1
        c2 = 0.5 * trial.rr.sum(1)
        better = np.isfinite(c2) & (c2 <= cost)
        gain = float(np.sum(cost[better] - c2[better]))
        X0 = X0 + dX * better[:, None]
        blocks = blocks.where(better, trial)
        cost = np.where(better, c2, cost)
        shrink = np.where(better, 1.0, shrink / 4)
        if gain < max(tol, rtol * float(cost.sum())) and np.all(better):
            break  # converged: another sweep would gain little
    return replace(it, X0=X0, blocks=blocks), n_pass


# -- the noise model ---------------------------------------------------------------------------------
def _reweight(passes: Passes, it: Iterate, n_free: int) -> np.ndarray:
    """New noise precisions of every record and channel from the (whitened) residuals, the degrees of freedom
    shared in proportion to the samples: one factor per channel on the precisions it has, so that the records
    keep the ratios of their measured noise (re-estimated per record, a record the structure cannot yet simulate
    would be written off as noise, and the fit would follow the others)."""
    n_kept = passes.segment_rows(it.made.n_kept, it.seg)
    dof = n_free + len(it.seg) * passes.layout["nx"]
    keep = max(1.0 - dof / max(n_kept.sum(), 1), 0.5)
    weighted = passes.segment_rows(it.made.rr, it.seg).sum(axis=0)  # rr is already weighted by the precisions
    return passes.per_record(it.w) * (n_kept.sum(axis=0) * keep / np.maximum(weighted, 1e-300))


def _noise_model(passes: Passes, it: Iterate, order) -> np.ndarray | None:
    """The autoregressive coefficients of every channel's residual at ``it`` (``order``: an int, or "auto" to
    choose it by BIC per channel; channels padded with zeros to the largest order); None for white noise."""
    if order != "auto" and int(order) == 0:
        return None
    if it.made.residual is None:  # blocks merged from two passes (initial states): the residual of one pass
        it, _ = replace(it, blocks=None).evaluated(passes)
    R, since = it.made.residual, it.seg.since
    assert R is not None  # the blocks of a single pass carry its residual
    run = passes.valid_runs[: R.shape[0]]
    ny = R.shape[1]
    orders = [choose_order(R[:, c], since, run[:, c]) if order == "auto" else int(order) for c in range(ny)]
    p = max(orders, default=0)
    if p == 0:
        return None
    ar = np.zeros((ny, p))
    for c, pc in enumerate(orders):
        ar[c, :pc] = fit_ar(R[:, c], since, run[:, c], pc, hold=p)[0]
    return ar


#: Nats within which a fit stops by default.
TOL = 1e-4
#: Rounds of alternating noise-model and coefficient estimates at most (iterated generalised least squares).
NOISE_ROUNDS = 4
#: Nats within which a round of those stops (as a stage before the last does): a round's optimum moves with the
#: noise model it is fitted at, so only the last noise model's is sought to the fit's tolerance.
ROUND_NATS = 1.0


def _settle_noise(
    passes: Passes,
    it: Iterate,
    alpha,
    active,
    tol: float,
    update_noise: bool,
    noise="white",
    max_iter: int = LM_STEPS,
    rounds: int = NOISE_ROUNDS,
):
    """LM at the current noise model, then the noise re-estimated and LM again while it moves (its precisions by
    more than 2 %, an autoregressive coefficient by more than 0.01). ``noise``: "white", an autoregressive
    order, or "auto" (the order chosen by BIC); ``max_iter``: LM passes of each round at most; ``rounds``: noise
    re-estimates at most. While the noise moves, each round stops within :data:`ROUND_NATS` (its optimum moves
    with the noise), and the last noise model's is then sought to ``tol``."""
    if not update_noise:
        return lm(passes, it, alpha, active, tol=tol, max_iter=max_iter)
    loose = max(tol, ROUND_NATS)
    it, n = lm(passes, it, alpha, active, tol=loose, max_iter=max_iter)
    for _ in range(rounds):
        ar = None if noise == "white" else _noise_model(passes, it, noise)
        if noise == "auto":
            noise = 0 if ar is None else ar.shape[1]  # the order is chosen once, the coefficients follow
        trial = replace(it, ar=ar, blocks=None) if not _same_ar(ar, it.ar) else it
        if trial is not it:
            trial, n1 = trial.evaluated(passes)
            n += n1
        w_new = _reweight(passes, trial, active.size)
        if not np.all(np.isfinite(w_new) & (w_new > 0)):
            break  # a residual that is not finite says nothing of the noise: its precisions stay as they were
        if trial is it and np.max(np.abs(np.log(w_new / it.w))) <= 0.02:
            break
        it, n2 = lm(passes, replace(trial, w=w_new, blocks=None), alpha, active, tol=loose, max_iter=max_iter)
        n += n2
        if ar is None:  # white noise: one re-estimate of the precisions, as the noise rarely moves again
            break
    if loose > tol:
        it, n2 = lm(passes, it, alpha, active, tol=tol, max_iter=max_iter)
        n += n2
    return it, n


def _same_ar(a: np.ndarray | None, b: np.ndarray | None, tol: float = 0.01) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return a.shape == b.shape and bool(np.max(np.abs(a - b), initial=0.0) <= tol)


# -- the continuation policy -------------------------------------------------------------------------
def _longest(length: int, phi: float) -> int:
    """The longest segment whose state-transition growth stays below :data:`PHI_STOP`, if it grows
    exponentially from ``phi`` over ``length`` samples (no limit for a contracting system)."""
    if phi <= math.e:
        return np.iinfo(np.int64).max
    return int(length * np.log(PHI_STOP) / np.log(phi))


def horizon(stages: list) -> int | None:
    """Samples within which the fitted model amplifies a state error :data:`PHI_STOP`-fold, from the growth
    measured over the last stage's segments (None when it does not grow: a contracting system)."""
    measured = [st for st in stages if not np.isnan(st.get("growth", np.nan))]  # inf: a growth past doubles
    longest = _longest(int(measured[-1]["length"]), float(measured[-1]["growth"])) if measured else None
    return None if longest in (None, np.iinfo(np.int64).max) else max(int(longest), 1)


def _growth(end_S, npar: int, scale: np.ndarray) -> float:
    """Largest singular value of the segments' scaled state-transition matrices."""
    if not len(end_S):
        return 1.0
    Phi = end_S[:, npar:, :] * scale[:, None] / scale[None, :]
    if not np.all(np.isfinite(Phi)):
        return np.inf
    return float(np.max(np.linalg.svd(Phi, compute_uv=False)))


def _state_scale(guess: np.ndarray, X0: np.ndarray) -> np.ndarray:
    """Each state's typical size: RMS of its guess, or (a latent state, no guess) of the segments' initial
    states, else 1."""
    rms: np.ndarray = np.sqrt(np.mean(guess**2, axis=0))
    start = np.sqrt(np.mean(X0**2, axis=0))
    scale: np.ndarray = np.where(rms > 0, rms, start)
    return np.where(scale > 0, scale, 1.0)


def _resegment(passes: Passes, it: Iterate, starts: np.ndarray) -> Iterate:
    """The iterate on segments ``starts``, their initial states from the current segments: a current segment's
    own where one starts there (the continuation's lengths are multiples of each other), else the state its
    simulation reaches."""
    old = it.seg.starts
    idx = np.minimum(np.searchsorted(old, starts), len(old) - 1)
    if np.array_equal(old[idx], starts):
        X0 = it.X0[idx]
    else:
        X0 = passes.simulate(it.theta, it.X0, it.seg)[starts]
    return replace(it, X0=X0, seg=passes.segments(starts), blocks=None)


@np.errstate(over="ignore", invalid="ignore")  # a whole record that diverges is refused by its non-finite cost
def _jump(passes: Passes, it: Iterate, full: int, scale: np.ndarray) -> tuple[bool, Iterate, float]:
    """Whole segments of ``full`` samples tried at once, from the initial states of the segments they start
    with; kept if they simulate the record as well as the short segments did, up to what the short
    segments' extra initial states fit of the noise (half a nat each) and :data:`JUMP` of the cost, with a
    state-transition growth below :data:`PHI_STOP`. Returns whether they are kept, the trial iterate (with
    its pass) and the growth over the whole segments."""
    trial, _ = _resegment(passes, it, passes.segment_starts(full)).evaluated(passes)
    phi = _growth(trial.made.end_S, it.theta.size, scale)
    cost = it.made.cost
    allowance = 0.5 * passes.layout["nx"] * (len(it.seg) - len(trial.seg)) + JUMP * cost
    kept = bool(np.all(np.isfinite(trial.made.rr)) and trial.made.cost <= cost + allowance and phi <= PHI_STOP)
    return kept, trial, phi


def _lengthen(passes: Passes, it: Iterate, length: int, phi: float, growth: int, full: int):
    """Segments ``growth`` times longer (at most ``full``, and short enough that the state-transition growth
    ``phi`` over ``length`` samples, extrapolated, stays below :data:`PHI_STOP`), from the states the
    current segments reach at their starts: ``(iterate, length)``, or None when not even twice as long is."""
    factor = min(growth, _longest(length, phi) // length)
    if factor < 2:
        return None
    length = min(length * factor, full)
    starts = passes.segment_starts(length)
    if np.array_equal(starts, passes.segment_starts(full)):
        length = full  # the same segments (each record's last one runs to its end): the final stage
    return _resegment(passes, it, starts), length


def _reuse(it: Iterate, trial: Iterate | None) -> Iterate:
    """``it`` with the pass of a refused ``trial`` when the segments and initial states are the same."""
    if (
        trial is not None
        and np.array_equal(it.seg.starts, trial.seg.starts)
        and np.array_equal(it.X0, trial.X0)
        and np.array_equal(it.theta, trial.theta)
        and np.array_equal(it.w, trial.w)
    ):
        return replace(it, blocks=trial.blocks)
    return it


def _require_finite(theta, H) -> None:
    if not (np.all(np.isfinite(theta)) and np.all(np.isfinite(H))):
        raise SimulationError(
            expected(
                "output-error refinement",
                "a simulation that stays finite",
                "non-finite states or sensitivities (the model diverges on this record)",
                "the equation-error model stands",
                raw=True,
            )
        )


def _prior_precisions(H, theta, alpha, active):
    """MacKay's fixed point for the prior precisions of the active coefficients, on the quadratic model of
    the data term at the optimum (no further passes); see :func:`~symsbl._refine.laplace.mackay_fixed_point`."""
    Hs, _ = restrict(H, None, active, theta.size)
    new, _ = mackay_fixed_point(Hs, theta[active], alpha[active])
    out = alpha.copy()
    out[active] = new
    return out


def _stage(length: int, it: Iterate, n: int, phi: float, **extra) -> dict:
    return dict(length=length, segments=len(it.seg), passes=n, growth=phi, cost=it.made.cost, **extra)


def _continuation(
    passes: Passes,
    it: Iterate,
    alpha,
    active,
    guess,
    length: int,
    full: int,
    growth: int,
    tol: float,
    update_noise: bool,
    noise="white",
    max_iter: int = LM_STEPS,
):
    """The stages of :func:`fit` from segments of ``length`` samples: ``iterate, length, stages, passes``.

    Each stage fits at its segment length; then the whole records are tried (:func:`_jump`) until once
    they amplified the state past :data:`PHI_STOP`; else the segments grow (:func:`_lengthen`). A length
    whose fit amplifies the state past :data:`PHI_STOP` sends the fit back to the last length that did not.
    ``noise="auto"`` chooses the noise model's order on the final stage (before it, the order reached so far).
    A stage before the final one re-estimates the noise (when it is re-estimated) once: it only brings the
    coefficients near, and the noise of its short segments is not the whole records' anyway; :func:`fit`
    settles it where the continuation stops short.
    """
    scale = _state_scale(guess, it.X0)
    stages, previous, leap, jumped, n_pass = [], None, True, False, 0
    while True:
        final = length >= full
        policy = noise if (final or noise != "auto") else it.order
        rounds = NOISE_ROUNDS if final else 1
        it, n = _settle_noise(
            passes, it, alpha, active, tol if final else ROUND_NATS, update_noise, policy, max_iter, rounds
        )
        n_pass += n
        phi = _growth(it.made.end_S, it.theta.size, scale)
        stages.append(_stage(length, it, n, phi))
        trial = None
        if phi > PHI_STOP and previous is not None:
            # this length amplifies state errors past PHI_STOP (the growth outran its prediction): the
            # initial states and coefficients are then nearly collinear; back to the last length that did not
            length, back = previous
            # at the noise precisions reached since, unless the longer segments ran away (no precisions)
            w = it.w if np.all(np.isfinite(it.w)) else back.w
            it = replace(back, w=w, blocks=None)
            if jumped:  # whole records that grew once fitted: lengthen stage by stage from before the jump
                stages[-1]["back"], leap, jumped = True, False, False
                continue
            it, n = _settle_noise(passes, it, alpha, active, tol, update_noise, noise, max_iter)
            n_pass += n
            stages.append(_stage(length, it, n, float("nan"), back=True))
            break
        if final or phi > PHI_STOP or not np.all(np.isfinite(it.theta)):
            break
        previous = (length, it)
        if leap:  # not once whole segments amplified the state past PHI_STOP: they would again
            n_pass += 1
            kept, trial, phi_full = _jump(passes, it, full, scale)
            stages[-1]["jump"], leap = kept, phi_full <= PHI_STOP
            if kept:
                it, length, jumped = trial, full, True
                continue
        longer = _lengthen(passes, it, length, phi, growth, full)
        if longer is None:
            break  # longer segments would amplify the state by more than PHI_STOP: stay here
        it, length = longer
        it = _reuse(it, trial)
    return it, length, stages, n_pass


def fit(
    passes: Passes,
    theta0,
    alpha0,
    guess,
    *,
    active=None,
    length0: int = 256,
    growth: int = 8,
    w=None,
    update_noise: bool = True,
    mackay: bool = True,
    tol: float = TOL,
    warm: Solution | Warm | None = None,
    longest: int | None = None,
    noise="white",
    max_iter: int = LM_STEPS,
) -> Solution:
    """Continuation in the segment length from ``length0`` up to whole records, then the prior precisions.

    Parameters
    ----------
    passes : Passes
    theta0, alpha0 : ndarray, shape (n_free,)
        Starting coefficients and prior precisions.
    guess : ndarray, shape (n_total, n_states)
        A guess of every state at every sample (measured values, estimated velocities, zeros), from
        which the segments' initial states start.
    active : ndarray of int, optional
        The coefficients fitted (default: all); the others stay at ``theta0`` (a sub-model of the
        compiled structure: a coefficient switched off is held at zero).
    length0, growth : int
        First segment length (samples) and the factor by which it grows.
    w : ndarray, optional
        Noise precisions per record and measured channel, ``(n_records, n_measured)`` (default: from third
        differences; one row serves every record).
    update_noise, mackay : bool
        Re-estimate the noise precisions; re-estimate the prior precisions (MacKay).
    tol : float
        Nats of the objective within which the last round stops (:data:`TOL`; earlier stages and rounds stop
        within :data:`ROUND_NATS`).
    warm : Solution or Warm, optional
        A solution of a nearby structure (or its :func:`restarted` whole records): its segments, initial states
        and noise are the start, and the segments do not grow again (the structure's optimum is near).
    longest : int, optional
        The segments grow to at most this length (default: whole records; a warm start keeps its own).
    noise : {"white", "auto"} or int
        The noise model: white, autoregressive of the order chosen by BIC on the final stage's residual, or of
        a given order (its coefficients estimated alternately with the model's; see
        :mod:`symsbl._refine.noise`).
    max_iter : int
        Levenberg-Marquardt passes of each round at most (a screen passes few, with neither the noise nor the
        prior re-estimated: where a structure is heading, not its optimum).
    """
    theta, alpha = np.array(theta0, dtype=float), np.array(alpha0, dtype=float)
    active = np.arange(theta.size) if active is None else np.asarray(active, dtype=int)
    n_total = passes.records.n_total
    w = (
        noise_precisions(passes.Y[:n_total], passes.valid[:n_total], passes.records.starts)
        if w is None
        else np.array(passes.per_record(w))
    )
    full = int(passes.records.lengths.max())
    full = full if longest is None else min(int(longest), full)
    length = min(length0, full)
    if warm is not None:
        it = Iterate(theta, warm.X0.copy(), passes.segments(warm.starts), w, ar=warm.ar)
        length, full, n_pass = warm.length, warm.length, 0
    else:
        starts = passes.segment_starts(length)
        it, n_pass = initial_states(passes, Iterate(theta, guess[starts].copy(), passes.segments(starts), w))
    it, length, stages, n = _continuation(
        passes, it, alpha, active, guess, length, full, growth, tol, update_noise, noise, max_iter
    )
    n_pass += n
    coloured = noise == "auto" or (noise != "white" and int(noise) > 0)
    if coloured and length < full and update_noise:  # the continuation stopped short: settle the noise here
        it, n = _settle_noise(passes, it, alpha, active, tol, update_noise, noise, max_iter)
        n_pass += n
        stages.append(_stage(length, it, n, float("nan"), noise=it.order))
    _require_finite(it.theta, it.made.H)
    if mackay:
        alpha = _prior_precisions(it.made.H, it.theta, alpha, active)
        # the blocks at the optimum do not depend on the prior: the pass made there is the first of this fit
        it, n = lm(passes, it, alpha, active, tol=tol, max_iter=max_iter)
        n_pass += n
    Hs, _ = restrict(it.made.H, None, active, it.theta.size)
    cost = _objective(it.made, it.theta, alpha, active)
    by_record = passes.segment_rows(it.made.n_kept, it.seg)
    n_kept = by_record.sum(0)
    w = np.array(passes.per_record(it.w))
    post = posterior(Hs, it.theta[active], alpha[active], cost, by_record, w)
    if it.ar is not None and it.order:
        # the noise model's own Occam factor: 1/2 log n a coefficient (BIC), as its order was chosen
        occam = 0.5 * float(np.sum(np.count_nonzero(it.ar, axis=1) * np.log(np.maximum(n_kept, 2))))
        post = replace(post, log_evidence=post.log_evidence - occam)
    return Solution(
        theta=it.theta,
        X0=it.X0,
        starts=it.seg.starts.copy(),
        length=length,
        cost=float(cost),
        ssr=passes.segment_rows(it.made.rr, it.seg) / w,
        w=w,
        alpha=alpha,
        posterior=post,
        H=it.made.H,
        stages=stages,
        n_pass=n_pass,
        active=active,
        ar=it.ar,
        n_kept=n_kept,
        n_kept_by_record=by_record,
    )
