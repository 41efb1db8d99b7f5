"""Confirming an effect on data its choice did not see, and the experiment that would separate two.

**Confirmation.** The effect is chosen on the evidence of every record. Cross-validation then asks
whether the model with the effect *predicts* data it was not fitted on better than the model
without it. Every record is cut in two halves; both models are fitted on the first halves of all
records and predict the second halves with their coefficients fixed (only each half's initial state
is fitted, a few numbers against thousands of samples), then the other way round. Each fold so sees
every operating condition the user recorded: holding out whole records instead would ask a model
fitted on a small-amplitude record to predict a large one, where an effect the small record cannot
excite has no determined coefficient (measured: a Coulomb force worth 2000 nats lost 24000 nats of
predictive likelihood that way). The score is the sum of the Gaussian predictive log likelihoods
under each fit's own noise level, so it knows the noise floor: an effect that brings the error down
to the noise gains, and one that fits the noise of its own records loses.

**Separating experiment.** When two effects are close in evidence, both fitted models are simulated
under inputs a user can apply: the training input scaled up and down, and sines across its band.
The one where their predictions differ most, in units of the measurement noise, is the record to
take next.
"""

from __future__ import annotations

import math

import numpy as np

from .._base.errors import SimulationError
from .._refine.engine import Engine
from .._refine.solver import Iterate, lm, noise_precisions
from .._simulation.signals import Sampled, Signal, Sine
from .._simulation.simulate import simulate

__all__ = ["folds", "predictive_log_likelihood", "cross_validated_gain", "separating_experiment"]


def folds(records) -> list[tuple[list, list]]:
    """``(fitted on, predicted)``: the first halves of every record against the second halves, and back."""
    halves = [(r.slice(0, r.n_samples // 2), r.slice(r.n_samples // 2, r.n_samples)) for r in records]
    first, second = [h[0] for h in halves], [h[1] for h in halves]
    return [(first, second), (second, first)]


def predictive_log_likelihood(model, record, measured, settings, w: np.ndarray | None) -> float:
    """``log p(record | model)`` with the coefficients fixed, the initial state fitted and noise precisions ``w``
    (None: the record's own, :func:`symsbl.noise_levels`)."""
    engine = Engine(model, [record], measured, settings, {})
    passes = engine.passes
    starts = passes.segment_starts(record.n_samples)
    theta = np.array(engine.param.theta0, dtype=float)
    if w is None:
        w = noise_precisions(passes.Y[: record.n_samples], passes.valid[: record.n_samples])[0]
    start = Iterate(theta, engine.guess[starts].copy(), passes.segments(starts), np.asarray(w, dtype=float))
    none = np.array([], dtype=int)
    with np.errstate(all="ignore"):
        it, _ = lm(passes, start, np.zeros_like(theta), none, tol=1e-6, crawl=False)  # scores compared: converged
    assert it.blocks is not None  # lm returns the iterate with its pass
    rr = it.blocks.rr.sum(axis=0)
    if not np.all(np.isfinite(rr)):
        return -math.inf
    return float(np.sum(-0.5 * rr + 0.5 * passes.n_obs * np.log(w / (2 * np.pi))))


def cross_validated_gain(scorer_of, without, with_effect, records, measured, settings, horizons=None) -> float:
    """Sum over :func:`folds` of the predictive log-likelihood change from ``without`` to ``with_effect``
    (structures), each fitted on the fold's halves by ``scorer_of(model, records)``; each fit's horizon (see
    :attr:`~symsbl._discrepancy.scoring.Scorer.horizon`) is appended to the list ``horizons`` when given.

    Both structures' predictions are scored at the predicted record's measured noise level, not at their fits':
    a fit held to short segments by a large model error estimates a small noise (6x the precision on an
    oscillator missing friction and a cubic spring, measured on its acceleration), and its full-length
    prediction scored against that precision rejected the effect that halved the error."""
    total = 0.0
    for fitted_on, predicted in folds(records):
        scores = []
        for structure in (without, with_effect):
            try:
                scorer = scorer_of(structure, fitted_on)
            except SimulationError:
                scores.append(-math.inf)
                continue
            model = scorer.fitted()
            if horizons is not None and scorer.horizon is not None:
                horizons.append(scorer.horizon)
            scores.append(sum(predictive_log_likelihood(model, r, measured, settings, None) for r in predicted))
        if not np.isfinite(scores[0]) and not np.isfinite(scores[1]):
            continue
        total += scores[1] - scores[0] if np.isfinite(scores[0]) else math.inf
    return float(total)


def _band(record) -> tuple[float, float]:
    """The frequencies holding 2.5-97.5 % of the input's power."""
    u = record.inputs[:, 0] - record.inputs[:, 0].mean()
    P = np.abs(np.fft.rfft(u)) ** 2
    f = np.fft.rfftfreq(u.size, float(record.t[1] - record.t[0]))
    c = np.cumsum(P) / max(P.sum(), 1e-300)
    lo = f[min(int(np.searchsorted(c, 0.025)), f.size - 1)]
    hi = f[min(int(np.searchsorted(c, 0.975)), f.size - 1)]
    return max(lo, f[1]), max(hi, 2 * f[1])


def _difference(a, b, measured, noise: dict) -> float:
    """RMS over the measured states of the two simulations' difference, in noise standard deviations."""
    out = []
    for n in measured:
        d = a.column(n) - b.column(n)
        out.append(float(np.sqrt(np.mean(d**2))) / max(noise[n], 1e-300))
    return float(np.mean(out))


def separating_experiment(model_a, model_b, record, measured, noise: dict, max_samples: int = 2**14) -> dict | None:
    """The input under which ``model_a`` and ``model_b`` differ most (in noise standard deviations), among the
    training input scaled by 0.1-4 and sines across its band at 0.25-4 times its amplitude; None without an input."""
    if record.inputs.shape[1] != 1:
        return None
    rec = record.slice(0, min(record.n_samples, max_samples))
    sa, sb = model_a.to_system(), model_b.to_system()
    x0 = np.zeros(len(model_a.state_names))
    rms = float(np.sqrt(np.mean(rec.inputs[:, 0] ** 2)))
    lo, hi = _band(rec)
    trials: list[tuple[str, float, float | None, Signal]]  # (description, scale, frequency or None, input)
    trials = [
        (f"the training input scaled by {s:g} (RMS {s * rms:.3g})", s, None, Sampled(rec.t, s * rec.inputs))
        for s in (0.1, 0.25, 0.5, 1.0, 2.0, 4.0)
    ]
    for f in np.geomspace(lo, hi, 6):
        for s in (0.25, 1.0, 4.0):
            amp = s * rms * math.sqrt(2)
            trials.append((f"a sine of {f:.3g} Hz and amplitude {amp:.3g}", s, float(f), Sine(amp, float(f))))
    scored = []
    for text, scale, freq, u in trials:
        try:
            a = simulate(sa, rec.t, inputs=u, x0=x0, method="rk4", on_divergence="raise")
            b = simulate(sb, rec.t, inputs=u, x0=x0, method="rk4", on_divergence="raise")
        except SimulationError:
            continue
        scored.append((_difference(a, b, measured, noise), text, scale, freq))
    if not scored:
        return None
    given = next((d for d, _, s, f in scored if s == 1.0 and f is None), math.nan)
    best = max(scored, key=lambda item: item[0])
    return {
        "input": best[1],
        "scale": best[2],
        "frequency_hz": best[3],
        "difference_noise_std": best[0],
        "difference_on_training_input": given,
        "duration_s": float(rec.t[-1] - rec.t[0]),
    }
