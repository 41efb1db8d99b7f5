"""Scoring the catalogue and deciding: which effect, if any, the model is missing.

Each iteration scores every catalogue effect by the exact change of the RVM log evidence when
its term(s) join the velocity equation (a refit, other terms free), calibrates the threshold
against records simulated from the current model with the measured noise ("nothing missing"),
and applies a :class:`DecisionRule`: add the winner only when its gain clears the threshold,
beats the runner-up by ``margin_nats`` and lowers the held-out error by ``min_improvement``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .._base.checks import integer, number
from .._base.errors import SimulationError
from .._base.progress import Progress
from .._base.rule import DEFAULT as DEFAULT_RULE
from .._base.rule import multiplicity
from .._data.trajectory import Trajectory
from .._simulation.signals import Sampled
from .._simulation.simulate import simulate
from .catalogue import Effect
from .locate import locate
from .results import Decision, DiscrepancyStep, EffectScore

__all__ = ["DecisionRule", "score_candidates", "best_per_effect", "admissible", "null_gains", "decide"]


@dataclass(frozen=True)
class DecisionRule:
    """When the discrepancy workflow adds an effect.

    Attributes
    ----------
    floor_nats : float
        Smallest evidence threshold (8 nats: ``z ~ 4.4`` under white noise).
    n_bootstrap : int
        Records simulated from the current model with the measured noise to calibrate the
        threshold (0: the floor alone; simulation error only).
    bootstrap_factor : float
        Threshold = ``max(floor_nats, bootstrap_factor * largest null gain)``.
    margin_nats : float
        Evidence by which the winner must beat the runner-up (3 nats: Bayes factor 20).
    min_improvement : float
        Fraction by which the held-out error must fall.

    Examples
    --------
    >>> import symsbl
    >>> rule = symsbl.DecisionRule(margin_nats=5.0)    # ask for a Bayes factor of e^5 over the runner-up
    >>> rule.margin_nats, rule.floor_nats
    (5.0, 8.0)
    >>> symsbl.DecisionRule(min_improvement=2.0)
    Traceback (most recent call last):
    ...
    symsbl.ParameterError: min_improvement: expected a finite number in [0.0, 1.0], received 2.0
    """

    floor_nats: float = 8.0
    n_bootstrap: int = 2
    bootstrap_factor: float = 2.0
    margin_nats: float = DEFAULT_RULE.margin_nats
    min_improvement: float = 0.1

    def __post_init__(self):
        number("floor_nats", self.floor_nats, low=0.0)
        integer("n_bootstrap", self.n_bootstrap, low=0)
        number("bootstrap_factor", self.bootstrap_factor, low=0.0)
        number("margin_nats", self.margin_nats, low=0.0)
        number("min_improvement", self.min_improvement, low=0.0, high=1.0)


def score_candidates(design, structure, traj, velocity, candidates, bar) -> list[tuple]:
    """Evidence gain of every candidate variant: ``(variant, gain, fit, cols)``; ``bar`` counts them."""
    k = list(traj.state_names).index(velocity)
    base_cols = structure[velocity]
    base = design.fit(traj, k, base_cols)
    out = []
    present = {v.effect.name for v, cols in candidates if all(c in base_cols for c in cols)}
    for variant, cols in candidates:
        bar.update()
        extra = [c for c in cols if c not in base_cols]
        if len(extra) < len(cols) or variant.effect.name in present:
            out.append((variant, -math.inf, None, cols))
            continue
        fit = design.fit(traj, k, base_cols + extra)
        out.append((variant, float(fit.log_evidence_ - base.log_evidence_), fit, base_cols + extra))
    return out


def best_per_effect(scored) -> dict[str, tuple]:
    """Per effect, its best variant with the grid penalty ``log(len(grid))`` applied."""
    best: dict[str, tuple] = {}
    for variant, gain, fit, cols in scored:
        penalty = multiplicity(len(variant.effect.grid)) if variant.effect.grid else 0.0
        entry = (variant, gain - penalty, fit, cols)
        if variant.effect.name not in best or entry[1] > best[variant.effect.name][1]:
            best[variant.effect.name] = entry
    return best


def admissible(effect: Effect, coef: float, input_coef: float | None) -> tuple[bool, str]:
    """Whether an effect's fitted coefficient is physical (a dissipative effect must dissipate)."""
    if effect.sign == 0 or not np.isfinite(coef):
        return True, ""
    reference = 1.0 if input_coef is None else math.copysign(1.0, input_coef)
    if coef * reference < 0:
        return True, ""
    return False, "wrong sign: it would feed energy in"


def null_gains(design, structure, model, train, velocity, candidates, noise, n_bootstrap, seed, bar) -> list[float]:
    """Largest candidate gain on records simulated from ``model`` with the measured noise."""
    system = model.to_system()
    U = train.inputs if train.inputs.shape[1] else None
    x0 = train.states[0]
    out: list[float] = []
    try:
        clean = simulate(
            system,
            train.t,
            inputs=None if U is None else Sampled(train.t, U),
            x0=x0,
            method="rk4",
            on_divergence="raise",
        )
    except SimulationError:
        return out
    rng = np.random.default_rng(seed)
    for _ in range(n_bootstrap):
        states = clean.states + rng.standard_normal(clean.states.shape) * [noise[n] for n in train.state_names]
        inputs = train.inputs
        if U is not None:
            inputs = clean.inputs + rng.standard_normal(U.shape) * [noise[n] for n in train.input_names]
        fake = Trajectory(train.t, states, inputs, train.state_names, train.input_names)
        scored = score_candidates(design, structure, fake, velocity, candidates, bar)
        gains = [g for _, g, _, _ in best_per_effect(scored).values()]
        design.forget(fake)
        out.append(max([g for g in gains if np.isfinite(g)], default=0.0))
    return out


def effect_scores(run, model, bar) -> list[EffectScore]:
    """Every catalogue effect's score in this iteration, best first."""
    eq = model.equation(run.v)
    input_coef = eq.terms[run.input_terms[0]].coef if len(run.input_terms) == 1 else None
    out = []
    scored = score_candidates(run.design, run.structure, run.data, run.v, run.candidates, bar)
    for variant, gain, fit, cols in best_per_effect(scored).values():
        e = variant.effect
        if fit is None:
            out.append(
                EffectScore(
                    e.name,
                    variant.label,
                    e.description,
                    e.family,
                    tuple(str(x) for x in variant.exprs),
                    -math.inf,
                    math.nan,
                    math.nan,
                    None,
                    False,
                    "already in the model",
                    None,
                    variant.shape,
                )
            )
            continue
        i = len(run.structure[run.v])
        coef, std = float(fit.coef_[i]), float(math.sqrt(fit.sigma_[i, i]))
        ok, reason = admissible(e, coef, input_coef)
        out.append(
            EffectScore(
                e.name,
                variant.label,
                e.description,
                e.family,
                tuple(run.design.library.names[c] for c in cols[i:]),
                gain,
                coef,
                std,
                None if input_coef is None else -coef / input_coef,
                ok,
                reason,
                None,
                variant.shape,
            )
        )
    return sorted(out, key=lambda c: -c.evidence_gain)


def _threshold(run, model, rule: DecisionRule, it: int, seed: int):
    """The scores of this iteration, the evidence threshold and the bootstrap's null gains."""
    replicates = rule.n_bootstrap if run.error == "simulation" else 0
    with Progress(
        f"discrepancy iteration {it}: scoring the catalogue", unit="fits", total=(1 + replicates) * len(run.candidates)
    ) as bar:
        scores = effect_scores(run, model, bar)
        null = []
        if replicates > 0:
            null = null_gains(
                run.design, run.structure, model, run.data, run.v, run.candidates, run.noise, replicates, seed, bar
            )
    return scores, max([rule.floor_nats] + [rule.bootstrap_factor * g for g in null]), null


def decide(run, it: int, model, rule: DecisionRule, seed: int) -> DiscrepancyStep:
    """One iteration of the workflow on ``run`` (a :class:`~symsbl._discrepancy.workflow.Workflow`)."""
    design, data = run.design, run.data
    err_train, err_held = run.err(model, data), run.err(model, run.heldout)
    design.weight = 1.0
    where = locate(model, data, run.heldout, design, run.x, run.v, run.error)
    design.weight = where.effective_fraction
    model = design.model(run.structure, data)
    scores, threshold, null = _threshold(run, model, rule, it, seed)
    for pos, c in enumerate(scores[:3]):  # held-out error of the leading candidates
        if c.admissible and c.evidence_gain > 0:
            scores[pos] = dataclasses.replace(
                c, error_after=run.err(design.model(run.with_terms(c), data), run.heldout)
            )
    step = dict(
        iteration=it,
        model=model,
        error_train=err_train,
        error_heldout=err_held,
        disagreement=where,
        scores=tuple(scores),
        threshold=threshold,
        null_gains=tuple(null),
    )
    return DiscrepancyStep(**step, **_choose(run, scores, threshold, err_held, rule))


def _choose(run, scores, threshold: float, err_held: float, rule: DecisionRule) -> dict:
    """The decision, its verdict and, when an effect is added, the model after it."""
    ranked = [c for c in scores if c.admissible and np.isfinite(c.evidence_gain)]
    best = ranked[0] if ranked else None
    runner = ranked[1] if len(ranked) > 1 else None
    if best is None or best.evidence_gain <= threshold:
        gain = "none" if best is None else f"{best.evidence_gain:.1f}"
        return dict(
            decision=Decision.NOTHING_MISSING,
            verdict=(f"nothing missing: no effect gains more than the threshold ({gain} <= {threshold:.1f} nats)"),
        )
    if runner is not None and best.evidence_gain - runner.evidence_gain < rule.margin_nats:
        return dict(
            decision=Decision.AMBIGUOUS,
            verdict=(
                f"ambiguous between {best.effect} and {runner.effect}: evidence gains {best.evidence_gain:.1f} "
                f"and {runner.evidence_gain:.1f} nats differ by less than {rule.margin_nats:g}"
            ),
        )
    target = (1 - rule.min_improvement) * err_held
    joint = ""
    if not (best.error_after is not None and best.error_after < target):
        # The held-out error may be dominated by a second missing effect: confirm jointly.
        for other in ranked[1:]:
            if other.evidence_gain <= threshold:
                break
            if run.err(run.design.model(run.with_terms(best, other), run.data), run.heldout) < target:
                joint = f" (confirmed together with {other.effect})"
                break
        if not joint:
            after = "-" if best.error_after is None else f"{100 * best.error_after:.3g}"
            return dict(
                decision=Decision.NO_HELDOUT_GAIN,
                verdict=(
                    f"{best.effect} gains {best.evidence_gain:.1f} nats but does not lower the held-out error "
                    f"enough ({100 * err_held:.3g} % -> {after} %); not added"
                ),
            )
    run.structure = run.with_terms(best)
    after_model = run.design.model(run.structure, run.data)
    after_err = best.error_after if best.error_after is not None else run.err(after_model, run.heldout)
    coef_name = next((e.coefficient for e in run.effects if e.name == best.effect), "k")
    phys = "" if best.physical is None else f", {coef_name} = {best.physical:.4g}"
    lead = best.evidence_gain - (runner.evidence_gain if runner else 0.0)
    verdict = (
        f"added {best.effect} ({best.description}){phys}: +{best.evidence_gain:.1f} nats, {lead:.1f} ahead "
        f"of {runner.effect if runner else 'nothing'}; held-out error {100 * err_held:.3g} % -> "
        f"{100 * after_err:.3g} %{joint}"
    )
    return dict(decision=Decision.ADDED, verdict=verdict, added=best, model_after=after_model, error_after=after_err)
