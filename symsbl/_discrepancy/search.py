"""One iteration of the discrepancy search on output-error evidence: score, decide, confirm.

Every candidate (catalogue effects on every pair and between connected pairs, and, beyond the
catalogue, library terms) is screened, the leaders are refitted, and the best admissible one is

- **added** when its evidence gain clears the threshold (calibrated against "nothing missing") and
  the cross-validated predictive log likelihood confirms it (:mod:`.confirm`); it is *named* when its
  Bayes factor over the runner-up is at least ``exp(margin_nats)``; below that the verdict is
  "ambiguous between A and B" with the odds and the record that would separate them, and the better
  model is kept;
- **not confirmed** when it clears the threshold but does not predict the held-out records better;
- otherwise nothing is added: "unexplained" when the model's residual stands above the measured
  noise level and follows the input (dynamics the search did not find), "nothing missing" when it
  is at the noise level or does not follow the input (correlated measurement noise, which the
  white-noise estimate cannot see).

A library term is chosen only when it beats every catalogue effect; the verdict then says "not in the
catalogue" and how far the closest named effects fall behind.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .._base.errors import SimulationError
from .._base.progress import Progress
from .candidates import reshaped, term_name
from .confirm import cross_validated_gain, separating_experiment
from .results import OUTSIDE_CATALOGUE, Decision, DiscrepancyStep, EffectScore
from .scoring import REFITS

__all__ = ["oe_step", "as_in_final", "UNEXPLAINED_RATIO"]

#: Residual standard deviation over the measured noise level above which a model is not "nothing missing".
UNEXPLAINED_RATIO = 1.5
#: Library terms refitted per iteration at most (besides the catalogue's leaders).
LIBRARY_REFITS = 2
#: Refitted candidates whose held-out error is computed (the leaders by evidence).
HELDOUT_CHECKS = 3


def _leaders(candidates, gains: np.ndarray) -> list[int]:
    """Indices of the best variant of each effect and place, the leading ones first."""
    best: dict = {}
    for i, c in enumerate(candidates):
        score = gains[i] - c.penalty
        if c.key not in best or score > best[c.key][0]:
            best[c.key] = (score, i)
    ranked = sorted(best.values(), key=lambda item: -item[0])
    named = [i for _, i in ranked if candidates[i].effect is not None][:REFITS]
    library = [i for _, i in ranked if candidates[i].effect is None][:LIBRARY_REFITS]
    return named + library


def _input_coefficient(model, state: str, input_names) -> float | None:
    eq = model.equation(state)
    coefs = [t.coef for t in eq.terms if t.name in input_names]
    return coefs[0] if len(coefs) == 1 else None


def _inverse_mass(model, velocity: str, run) -> float | None:
    """``1/m`` of the mass whose acceleration is ``velocity``'s equation: its input gain, or, for a mass the
    input does not drive, from a coupled mass ``j`` that it drives by reciprocity (a spring or damper between
    them pulls both ways alike, ``m_i a_ij = m_j a_ji``, with ``a_ij`` the coefficient of ``j``'s position,
    else velocity, in ``i``'s equation): ``1/m_i = (1/m_j) a_ij / a_ji``. None when neither applies."""
    direct = _input_coefficient(model, velocity, run.input_names)
    if direct is not None:
        return direct or None
    singles = [p for p in getattr(run, "pairs", ()) if len(p.velocities) == 1]
    own = next((p for p in singles if p.v == velocity), None)
    if own is None:
        return None
    for other in (p for p in singles if p is not own):
        b = _input_coefficient(model, other.v, run.input_names)
        if not b:
            continue
        for mine, theirs in ((own.x, other.x), (own.v, other.v)):
            a_ij, a_ji = model.equation(velocity).coef(theirs), model.equation(other.v).coef(mine)
            if a_ij * a_ji > 0:
                return b * a_ij / a_ji
    return None


def _score(run, c, fit, model, lin: float, check: bool = True) -> EffectScore:
    """The :class:`EffectScore` of candidate ``c`` (``fit``: its refit, None when only screened)."""
    e = c.effect
    family = e.family if e is not None else OUTSIDE_CATALOGUE
    description = e.description if e is not None else f"the library term {c.label}, outside the catalogue"
    first = c.additions[0][0]
    if fit is None:
        return EffectScore(
            c.name,
            c.label,
            description,
            family,
            c.terms,
            lin - c.penalty,
            math.nan,
            math.nan,
            None,
            True,
            "screened only (quadratic model of the evidence)",
            None,
            c.shape,
            where=c.pair.where,
        )
    coef, std = float(fit["coefs"][0]), float(fit["stds"][0])
    ref = _inverse_mass(fit["model"], first, run)  # from the same fit as coef
    ok, reason = True, ""
    if e is not None and e.sign == -1 and ref is not None and coef * ref > 0:
        ok, reason = False, "wrong sign: it would feed energy in"
    physical = None if ref is None else -coef / ref
    gain = _net(fit) - c.penalty
    return EffectScore(
        c.name,
        c.label,
        description,
        family,
        c.terms,
        gain,
        coef,
        std,
        physical,
        ok,
        reason,
        run.err(fit["model"], run.heldout) if check else None,
        c.shape,
        where=c.pair.where,
    )


def _net(fit: dict) -> float:
    return fit["gain"] * fit["fraction"]


#: Shape values tried around the best grid point, in grid steps; each further round tries the same offsets in
#: steps a quarter as long around the best so far.
SHAPE_STEPS = (-0.75, -0.5, -0.25, 0.25, 0.5, 0.75)
#: Rounds of shape refinement: the shape ends within 1/128 of a grid step of the best on those offsets (a
#: clearance with the gap at 0.107 of the amplitude, grid step 0.1: one round left it 17 % off and the search
#: then added y|y|, y^3 and sign(y) to make up for it; three rounds, within 2 %).
SHAPE_ROUNDS = 3


def _refine_shape(scorer, avail: list, refitted: dict, i: int) -> None:
    """Refit candidate ``i`` at shape values around its grid point and keep the best (in place), in rounds of
    finer steps: the grid alone leaves the shape (and the coefficient that goes with it) up to half a grid step
    off."""
    c = avail[i]
    grid = sorted({a.shape for a in avail if a.key == c.key})
    if len(grid) < 2:
        return
    step = float(np.min(np.diff(grid)))
    for _ in range(SHAPE_ROUNDS):
        centre = avail[i].shape
        trial = [reshaped(c, centre + d * step) for d in SHAPE_STEPS if centre + d * step > 0]
        for t, fit in zip(trial, scorer.refit(trial)):
            if fit is not None and _net(fit) > _net(refitted[i]):
                avail[i], refitted[i] = t, fit
        step /= 4


def _present(model, c) -> bool:
    for state, exprs in c.additions:
        names = set(model.equation(state).names)
        if not all(term_name(e) in names for e in exprs):
            return False
    return True


def oe_step(run, it: int, model, rule, seed: int, history=()) -> DiscrepancyStep:
    """One iteration on ``run`` (a :class:`~symsbl._discrepancy.workflow.Workflow` with output-error evidence)
    from the current structure ``model``, after the steps ``history``."""
    scorer = run.scorer(model, run.records)
    fitted = scorer.fitted()
    err_train, err_held = run.err(fitted, run.data), run.err(fitted, run.heldout)
    swap = _prune(run, model, scorer, fitted, history) or _revisit(run, it, model, scorer, rule, history)
    if swap is not None:
        return DiscrepancyStep(
            iteration=it,
            model=fitted,
            error_train=err_train,
            error_heldout=err_held,
            disagreement=run.where(fitted),
            evidence="output-error",
            residual_ratio=run.residual_ratio(scorer),
            **swap,
        )
    where = run.where(fitted)
    # an effect once at a place is not added again (at another shape): its shape was refined when it was added
    present = run.added_keys | {c.key for c in run.oe_candidates if _present(model, c)}
    avail = [c for c in run.oe_candidates if c.key not in present]
    with Progress(f"discrepancy iteration {it}: output-error scores", total=3, unit="stages") as bar:
        lin = scorer.screen(avail) if avail else np.zeros(0)
        bar.update()
        lead = _leaders(avail, lin)
        fits = scorer.refit([avail[i] for i in lead]) if lead else []
        bar.update()
        penalties = np.array([c.penalty for c in avail])
        null = scorer.null_gains(avail, rule.n_bootstrap, seed, penalties) if avail else []
        bar.update()
    refitted = {i: f for i, f in zip(lead, fits) if f is not None}
    order = sorted(refitted, key=lambda i: -(_net(refitted[i]) - avail[i].penalty))
    if order and avail[order[0]].shape is not None:
        _refine_shape(scorer, avail, refitted, order[0])
    scores = [_score(run, avail[i], refitted[i], fitted, lin[i], check=n < HELDOUT_CHECKS) for n, i in enumerate(order)]
    seen = {avail[i].key for i in refitted}
    for i in _leaders(avail, lin):
        if avail[i].key not in seen and i not in refitted:
            scores.append(_score(run, avail[i], None, fitted, lin[i]))
    scores.sort(key=lambda s: -s.evidence_gain if np.isfinite(s.evidence_gain) else math.inf)
    threshold = max([rule.floor_nats] + [rule.bootstrap_factor * g for g in null])
    step = dict(
        iteration=it,
        model=fitted,
        error_train=err_train,
        error_heldout=err_held,
        disagreement=where,
        scores=tuple(scores),
        threshold=threshold,
        null_gains=tuple(null),
        evidence="output-error",
        residual_ratio=run.residual_ratio(scorer),
    )
    by_label = {(avail[i].label): (avail[i], refitted[i]) for i in refitted}
    ratio = (step["residual_ratio"], run.input_share(scorer))
    reaches = [r for r in [scorer.horizon] + [f.get("horizon") for f in refitted.values()] if r is not None]
    chosen = _choose(run, model, scores, by_label, threshold, rule, ratio, err_held, reaches)
    return DiscrepancyStep(**step, **_cannot_tell(run, scorer, chosen, ratio[0], err_held, reaches))


def _cannot_tell(run, scorer, chosen: dict, level: float, err_held: float, reaches: list) -> dict:
    """``chosen``, unless its leading candidate failed the held-out check while the model misfits the record
    (a residual above :data:`UNEXPLAINED_RATIO` x the noise level): then "no held-out gain" would blame the
    candidate, and the honest verdict is that the model is badly wrong and this record cannot tell why. On a
    hypersensitive record (the current model or a candidate's refit amplifying a state error 10^4-fold within
    the record: ``reaches``, in samples) held-out simulations and predictions fail whatever the model; the
    verdict says so."""
    if chosen["decision"] is not Decision.NO_HELDOUT_GAIN or not level > UNEXPLAINED_RATIO:
        return chosen
    why = chosen["verdict"].removesuffix("; not added")
    if reaches:
        seconds = min(reaches) * float(np.mean([r.dt for r in scorer.records]))
        why += (
            f"; the record is hypersensitive (chaotic-like: a fitted model amplifies a state error 10^4-fold "
            f"within {seconds:.3g} s), so held-out simulations and predictions fail whatever the model"
        )
    return dict(
        chosen,
        decision=Decision.CANNOT_TELL,
        verdict=(
            f"the model is badly wrong (its residual stands at {level:.3g}x the measured noise level; held-out "
            f"{run.error} error {100 * err_held:.3g} %) and this record cannot tell why: {why}; record a response that "
            "tells the candidates apart (another excitation level or band) before adding any"
        ),
    )


def _choose(run, model, scores, by_label, threshold, rule, ratio, err_held, reaches: list) -> dict:
    """The decision of one iteration, its verdict and, when something is added, the model after; the horizons of
    the cross-validation's fits join ``reaches``."""
    ranked = [s for s in scores if s.admissible and s.label in by_label and np.isfinite(s.evidence_gain)]
    named = [s for s in ranked if s.family != OUTSIDE_CATALOGUE]
    best = ranked[0] if ranked else None
    if best is None or best.evidence_gain <= threshold:
        return _below_threshold(best, threshold, ratio)
    candidate, fit = by_label[best.label]
    outside = candidate.effect is None  # a library term: named only when it beats every named effect by the margin
    runner = (
        named[0] if outside and named else next((s for s in ranked if s is not best and s.effect != best.effect), None)
    )
    if best.error_after is None:
        best = dataclasses.replace(best, error_after=run.err(fit["model"], run.heldout))
    cv = cross_validated_gain(run.scorer, model, fit["model"], run.records, run.measured, run.settings, reaches)
    log_bf = best.evidence_gain - runner.evidence_gain if runner is not None else math.inf
    info = dict(
        added=best, bayes_factor=_bf(log_bf), runner_up=None if runner is None else runner.label, confirmation=cv
    )
    if not cv > 0:
        return _not_confirmed(best, info)
    after = fit["model"]
    coef_name = best.effect if outside else candidate.effect.coefficient
    phys = "" if best.physical is None else f", {coef_name} = {best.physical:.4g}"
    odds = "" if runner is None else f", Bayes factor {_bf_text(log_bf)} over {runner.label}"
    tail = (
        f"held-out error {100 * err_held:.3g} % -> {100 * best.error_after:.3g} %; "
        f"cross-validated predictive log likelihood {cv:+.1f} nats"
    )
    if outside and (runner is None or log_bf >= rule.margin_nats):
        closest = ", ".join(f"{s.label} ({s.evidence_gain - best.evidence_gain:+.1f} nats)" for s in named[:2])
        verdict = (
            f"added a term not in the catalogue: {best.label} in {candidate.additions[0][0]}' with coefficient "
            f"{best.coef:.4g} +- {best.std:.2g}: +{best.evidence_gain:.1f} nats; the closest named effects "
            f"explain less: {closest or 'none'}; {tail}"
        )
        return dict(decision=Decision.ADDED, verdict=verdict, model_after=after, error_after=best.error_after, **info)
    if runner is not None and log_bf < rule.margin_nats:
        experiment = separating_experiment(
            after, by_label[runner.label][1]["model"], run.data, run.measured, run.noise_of(fit)
        )
        verdict = (
            f"ambiguous between {best.label}{f' ({OUTSIDE_CATALOGUE})' if outside else ''} and {runner.label}: "
            f"Bayes factor {_bf_text(log_bf)} (below {_bf_text(rule.margin_nats)}); the better, {best.label}, "
            f"is kept{phys}{_separation(experiment)}; {tail}"
        )
        return dict(
            decision=Decision.AMBIGUOUS,
            verdict=verdict,
            model_after=after,
            error_after=best.error_after,
            separating_experiment=experiment,
            **info,
        )
    verdict = f"added {best.label} ({best.description}){phys}: +{best.evidence_gain:.1f} nats{odds}; {tail}"
    return dict(decision=Decision.ADDED, verdict=verdict, model_after=after, error_after=best.error_after, **info)


def _not_confirmed(best, info: dict) -> dict:
    """The decision when the leading candidate does not predict held-out records better (``info``: its Bayes
    factor, runner-up and cross-validated gain)."""
    cv = info["confirmation"]
    return dict(
        decision=Decision.NO_HELDOUT_GAIN,
        bayes_factor=info["bayes_factor"],
        runner_up=info["runner_up"],
        confirmation=cv,
        verdict=(
            f"{best.label} gains {best.evidence_gain:.1f} nats but does not predict held-out records "
            f"better (cross-validated predictive log likelihood {cv:+.1f} nats); not added"
        ),
    )


def _below_threshold(best, threshold: float, ratio: tuple) -> dict:
    """The decision when no candidate clears ``threshold``: unexplained when the residual ``ratio`` (its level
    over the noise, its share that follows the input) says the model misfits, else nothing missing."""
    gain = "none" if best is None else f"{best.evidence_gain:.1f}"
    level, share = ratio
    if level > UNEXPLAINED_RATIO and share > 1:
        return dict(
            decision=Decision.UNEXPLAINED,
            verdict=(
                f"unexplained: no candidate gains more than the threshold ({gain} <= {threshold:.1f} nats), "
                f"but the residual stands at {level:.2f}x the measured noise level and follows the input "
                f"({share:.2g}x the share chance explains)"
            ),
        )
    coloured = (
        ""
        if level <= UNEXPLAINED_RATIO
        else (
            f"; the residual is {level:.3g}x the white-noise level but does not follow the input: correlated "
            f"measurement noise"
        )
    )
    return dict(
        decision=Decision.NOTHING_MISSING,
        verdict=f"nothing missing: no effect gains more than the threshold ({gain} <= {threshold:.1f} nats){coloured}",
    )


def _separation(experiment: dict | None) -> str:
    """The verdict's clause on the experiment that would separate two ambiguous effects (empty: none found)."""
    if experiment is None:
        return ""
    return (
        f"; {experiment['input']} would separate them (predictions {experiment['difference_noise_std']:.3g} noise "
        f"std apart, against {experiment['difference_on_training_input']:.3g} on the training input)"
    )


def _without(model, names, base) -> object:
    """``model`` without the terms ``names`` (terms of the base structure ``base`` stay)."""
    eqs = []
    for eq in model.equations:
        keep = [k for k, t in enumerate(eq.terms) if t.name not in names or t.name in base.get(eq.lhs, ())]
        if len(keep) < len(eq.terms):
            eq = dataclasses.replace(
                eq, terms=tuple(eq.terms[k] for k in keep), covariance=np.asarray(eq.covariance)[np.ix_(keep, keep)]
            )
        eqs.append(eq)
    return dataclasses.replace(model, equations=tuple(eqs))


def _base_terms(history) -> dict:
    """The terms of the structure the search started from, per equation (they are never taken out)."""
    return {eq.lhs: set(eq.names) for eq in history[0].model.equations} if history else {}


def _kept_additions(history) -> list:
    """The steps whose addition is still in the model and was followed by a later one."""
    gone = {s.replaces for s in history if s.replaces is not None}
    return [
        s
        for k, s in enumerate(history)
        if s.added is not None
        and s.model_after is not None
        and s.added.label not in gone
        and any(h.model_after is not None for h in history[k + 1 :])
    ]


def _prune(run, model, scorer, fitted, history) -> dict | None:
    """An earlier addition that the ones made since have made superfluous, taken out: its terms lose their
    Bayesian-model-reduction evidence in the current fit, and the refit without them has at least the
    evidence of the fit with them (a v x^2 term that stood in for a Coulomb force kept 0.2 std of its
    coefficient once the force was added, and was reported as found). ``fitted``: ``scorer``'s model."""
    base = _base_terms(history)
    for s in _kept_additions(history):
        terms = [t for eq in fitted.equations if not eq.fixed for t in eq.terms if t.name in s.added.terms]
        if not terms or any(t.evidence > 0 for t in terms):
            continue
        try:
            without = run.scorer(_without(model, set(s.added.terms), base), run.records)
        except SimulationError:
            continue
        gain = without.log_evidence - scorer.log_evidence
        if not (_comparable(without.solution, scorer.solution) and gain >= 0):
            continue
        after = without.fitted()
        error = run.err(after, run.heldout)
        verdict = (
            f"removed {s.added.label} (added in iteration {s.iteration}): with the effects added since, "
            f"the records are explained as well without it ({gain:+.1f} nats, Bayes factor {_bf_text(gain)} "
            f"for removing it); held-out error -> {100 * error:.3g} %"
        )
        return dict(
            scores=(),
            threshold=0.0,
            null_gains=(),
            decision=Decision.REMOVED,
            verdict=verdict,
            model_after=after,
            error_after=error,
            bayes_factor=_bf(gain),
            replaces=s.added.label,
        )
    return None


def _revisit(run, it: int, model, scorer, rule, history) -> dict | None:
    """An earlier addition reconsidered given the ones made since: its runner-up takes its place when, with
    everything added later, it explains the records better by ``margin_nats`` (greedy choices are made
    before the effects that confound them are in the model: a clearance can stand in for a cubic spring
    while a Coulomb force is missing)."""
    by_label = {c.label: c for c in run.oe_candidates}
    base = _base_terms(history)
    for s in _kept_additions(history):
        r = by_label.get(s.runner_up)
        if s.replaces is not None or r is None or r.key in run.added_keys or _present(model, r):
            continue
        try:
            without = run.scorer(_without(model, set(s.added.terms), base), run.records)
        except SimulationError:
            continue
        if not _comparable(without.solution, scorer.solution):
            continue  # segments cut short (a model that runs away): its evidence is of another, easier problem
        try:
            (fit,) = without.refit([r])
        except SimulationError:
            continue
        gain = (without.log_evidence + fit["gain"] - scorer.log_evidence) if fit is not None else -math.inf
        if not gain >= rule.margin_nats:
            continue
        score = _score(run, r, fit, without.fitted(), math.nan)
        assert score.error_after is not None  # measured for a refitted candidate
        if not np.isfinite(score.error_after):
            continue  # it runs away on the held-out record
        # confirmed like an addition: it must predict the halves it was not fitted on better
        cv = cross_validated_gain(run.scorer, model, fit["model"], run.records, run.measured, run.settings)
        if not cv > 0:
            continue
        verdict = (
            f"replaced {s.added.label} (added in iteration {s.iteration}) by {r.label}: with the effects "
            f"added since, it explains the records better by {gain:.1f} nats (Bayes factor {_bf_text(gain)}); "
            f"held-out error -> {100 * score.error_after:.3g} %; cross-validated predictive log likelihood "
            f"{cv:+.1f} nats"
        )
        return dict(
            scores=(score,),
            threshold=rule.margin_nats,
            null_gains=(),
            decision=Decision.REPLACED,
            verdict=verdict,
            added=score,
            model_after=fit["model"],
            error_after=score.error_after,
            bayes_factor=_bf(gain),
            runner_up=s.added.label,
            replaces=s.added.label,
            confirmation=cv,
        )
    return None


def _comparable(a, b) -> bool:
    """Whether two output-error fits of the same records have log evidences that can be compared: the same
    shooting segments (a fit whose segments stopped growing, because its model amplifies state errors past
    ``PHI_STOP``, has the easier likelihood of shorter simulations)."""
    return a.length == b.length and np.array_equal(a.starts, b.starts)


def _bf(log_bf: float) -> float:
    return math.exp(min(log_bf, 700.0))


def _bf_text(log_bf: float) -> str:
    return f"{math.exp(log_bf):.3g}" if log_bf < 50 else f"e^{log_bf:.0f}"


def as_in_final(run, steps, final) -> list:
    """``steps`` with each added effect's coefficient, standard deviation and physical value as ``final`` holds
    them (the model the report returns), where its term is in exactly one equation of ``final``.

    A step's scores come from refits of the candidates inside the current model's fit, whose RK4 substeps were
    chosen for the current model: a Coulomb candidate's smoothed sign needs more (measured: at 5 % of the force,
    the refit's Fc was 0.18 % high, 2.7 standard deviations, where the final fit and a fresh
    :func:`symsbl.refine` agree within 0.01 %). Later additions also move earlier coefficients.
    """
    out = []
    for step in steps:
        s = step.added
        hits = (
            []
            if s is None
            else [(eq, t) for eq in final.equations if not eq.fixed for t in eq.terms if t.name == s.terms[0]]
        )
        if len(hits) != 1:
            out.append(step)
            continue
        ((eq, t),) = hits
        ref = _inverse_mass(final, eq.lhs, run)
        added = dataclasses.replace(s, coef=t.coef, std=t.std, physical=None if ref is None else -t.coef / ref)
        out.append(dataclasses.replace(step, added=added))
    return out
