"""The model path: which structure the identification keeps, chosen by a validation it did not fit.

The evidence of an output-error fit is exact only when its likelihood is: white (or correctly modelled)
noise, a model class that contains the truth, an exact input, an open loop. On measured records none of these
is certain, and each extra term buys evidence by absorbing what the likelihood misdescribes. So the structure
the evidence selected, the equation error's and every structure between them and below them (backward
elimination by Bayesian model reduction from their union, each refitted) are fitted by output error in one
compiled engine, each is scored by its evidence and by its cross-validated free-run error
(:mod:`.crossval`), and the :class:`~symsbl.SelectionRule` chooses (by default the fewest terms whose
cross-validated error is within one standard error of the best).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._base.errors import SimulationError
from .._base.rule import SelectionRule, mean_errors, paired_se
from .._data.excitation import period, relative_noise
from .._data.residuals import MODEL_ERROR
from .._model import IdentifiedModel, ModelPath, PathEntry
from .candidates import prior
from .crossval import cross_validate, folds
from .diagnostics import as_record, residual_tests
from .engine import Engine, Settings, residual_fraction
from .laplace import reduce_model
from .result import to_model
from .selection import _every_term_clears
from .solver import TOL, Solution, restarted

__all__ = ["choose_structure", "beyond_library", "MAX_PATH", "BEYOND", "PATH_SAMPLES"]

#: Backward elimination steps at most.
MAX_PATH = 12
#: A path stops descending once a structure's cross-validated error is this many times the best one's.
STOP_RATIO = 4.0
#: Levenberg-Marquardt steps of a backward step's screen: a structure near the path converges within them (8-9
#: measured), one that crawls for hundreds is judged by where they leave it.
SCREEN_PASSES = 12
#: A screened structure this many times the best error ends the path: twice :data:`STOP_RATIO`, as a screen
#: stopped short of its optimum only bounds where the refit would end (in the demo, 12-1e20 times).
SCREEN_STOP = 2 * STOP_RATIO
#: The source of a screened structure among the path's entries (a ``"path"`` entry marked ``screened``).
SCREENED = "path, screened"


def _names(engine: Engine, active) -> tuple:
    """Per fitted equation, ``(lhs, term names)`` of the coefficients ``active``."""
    out = []
    chosen = set(int(k) for k in active)
    for i, eq in enumerate(engine.full.equations):
        if eq.fixed:
            continue
        names = tuple(eq.terms[j].name for k, (ii, j) in enumerate(engine.positions) if ii == i and k in chosen)
        out.append((eq.lhs, names))
    return tuple(out)


def _backward(engine: Engine, sol, alpha: np.ndarray, screen: int | None = None):
    """The next structure below ``sol``: the term whose removal Bayesian model reduction says costs least, refitted
    (None when every fitted equation is down to one term, or the refit runs away); ``screen``: the refit stopped
    after that many passes (see :func:`symsbl._refine.engine.Engine.fit`)."""
    active = [int(k) for k in sol.active]
    per_equation: dict[int, list[int]] = {}
    for k in active:
        per_equation.setdefault(engine.positions[k][0], []).append(k)
    removable = [n for n, k in enumerate(active) if len(per_equation[engine.positions[k][0]]) > 1]
    if not removable:
        return None
    a = sol.alpha[sol.active]
    gains = {n: reduce_model(sol.posterior, a, [n])[0] for n in removable}
    keep, start = _reduction(sol, [max(gains, key=gains.__getitem__)])
    return _fit(engine, keep, start, alpha, warm=sol, screen=screen)


def _reduction(sol, off: list[int]) -> tuple[list[int], np.ndarray]:
    """The coefficients of ``sol`` left when those at ``off`` (places in ``sol.active``) are switched off, and
    their start: ``sol``'s posterior reduced by Bayesian model reduction, the others at zero."""
    _, mean, _ = reduce_model(sol.posterior, sol.alpha[sol.active], off)
    dropped = set(off)
    keep = [int(k) for n, k in enumerate(sol.active) if n not in dropped]
    start = np.zeros_like(sol.theta)
    start[keep] = mean
    return keep, start


def _noise_floor(passes) -> float:
    """The cross-validated error of a perfect model: each measured channel's noise relative to its spread, told
    from the excitation (:func:`symsbl._data.excitation.noise_std`: between periods, in the quiet bands; the
    third differences read a band that reaches a third of the sampling rate as noise), averaged over the
    channels, as the folds' errors are. A channel whose noise the record does not resolve (low-passed,
    reconstructed) is taken at the others' level, not at zero; 0 when none is resolved (no floor known)."""
    records = passes.records
    n = records.n_total
    Y, valid, U = records.Y, passes.valid[:n], passes.UN[:n]
    spans = list(zip(records.starts, records.lengths))
    periods = [period(U[a : a + m]) if U.shape[1] else None for a, m in spans]
    levels = [
        relative_noise([np.where(valid[a : a + m, c], Y[a : a + m, c], np.nan) for a, m in spans], periods)
        for c in range(Y.shape[1])
    ]
    resolved = [level for level in levels if np.isfinite(level)]
    return float(np.mean(resolved)) if resolved else 0.0


#: A chosen structure whose cross-validated error exceeds this many times the noise floor leaves more than noise.
BEYOND = 3.0


def beyond_library(
    sizes, E: np.ndarray, chosen: int, floor: float, min_gain: float, follows: float = float("nan")
) -> str | None:
    """What the model path says of the library, one line or None: the chosen structure's cross-validated error
    stays above :data:`BEYOND` times the noise ``floor`` (relative errors; ``E`` the fold errors of the path's
    structures of ``sizes`` terms) while its residual follows the model's own simulated trajectory (``follows``:
    the largest share of a channel's innovations it predicts out of sample, at least
    :data:`symsbl._data.residuals.MODEL_ERROR`) or the path's other terms buy little: a richer structure lowers
    it beyond one standard error but was refused as too small a gain, or the chosen one is the richest and its
    last term closed less than ``min_gain`` of the gap. An exact model whose folds stay above the floor (three
    accelerometer records at 3 % noise: 3.4 times) gains nothing from more terms, its residual follows nothing,
    and it is not named."""
    mean = mean_errors(E)
    if floor <= 0 or not np.isfinite(mean[chosen]) or mean[chosen] <= BEYOND * floor:
        return None
    sizes = np.asarray(sizes)
    scored = [k for k in range(len(sizes)) if np.isfinite(mean[k])]
    richer = [k for k in scored if sizes[k] > sizes[chosen]]
    if richer:
        small = any(mean[chosen] - mean[k] > paired_se(E[k], E[chosen]) for k in richer)
    else:
        last = max((k for k in scored if sizes[k] < sizes[chosen]), key=lambda k: sizes[k], default=None)
        small = last is not None and mean[last] - mean[chosen] < min_gain * (mean[last] - floor)
    traced = bool(follows >= MODEL_ERROR)
    if not (small or traced):
        return None
    best = float(np.min(mean[np.isfinite(mean)]))
    head = (
        f"the chosen structure leaves {100 * mean[chosen]:.3g} % cross-validated error, "
        f"{mean[chosen] / floor:.2g} times the noise floor ({100 * floor:.2g} %), and the best on the path "
        f"{100 * best:.3g} %: the library does not seem to hold the law"
    )
    if traced:
        return (
            f"{head}: its residual follows the model's own simulated trajectory ({100 * follows:.2g} % of the "
            "innovations predicted out of sample, which a disturbance would not be); the model is an approximation "
            "within the training range"
        )
    return (
        f"{head} (its terms each buy little), or the record holds a disturbance (see the doubts); the model is an "
        "approximation within the training range"
    )


def _positions(engine: Engine, model: IdentifiedModel) -> list[int]:
    """The engine's coefficients that are ``model``'s terms (by equation and name)."""
    wanted = {(eq.lhs, t.name) for eq in model.equations if not eq.fixed for t in eq.terms if not t.fixed}
    return [k for k, name in enumerate(engine.names) if name in wanted]


def _fit(engine: Engine, active, theta0: np.ndarray, alpha: np.ndarray, warm=None, screen: int | None = None):
    start = np.zeros_like(theta0)
    start[active] = theta0[active]
    try:
        sol = engine.fit(active, start, alpha, warm=warm, screen=screen)
    except (SimulationError, np.linalg.LinAlgError):
        return None
    return sol if np.isfinite(sol.posterior.log_evidence) else None


def _union(start: IdentifiedModel, refined: IdentifiedModel, records, measured, settings: Settings):
    """One engine for the union of the two structures (``refined``'s noise order kept), the prior precisions, the
    starting coefficients (each structure's own) and the equation error's coefficients by (state, term)."""
    order = max((len(v["ar"]) for v in refined.metadata.get("refine", {}).get("noise", {}).values()), default=0)
    extra = {}
    for eq in refined.equations:
        if eq.fixed or eq.lhs not in start.state_names:
            continue
        theirs = [t for t in start.equation(eq.lhs).terms if t.name not in set(eq.names)]
        if theirs:
            extra[eq.lhs] = [(t.expr, t.coef) for t in theirs]
    engine = Engine(refined, records, measured, dataclasses.replace(settings, noise=order), extra)
    theta0 = np.zeros(len(engine.positions))
    theta0[engine.base] = engine.param.theta0[engine.base]
    by_name = {(eq.lhs, t.name): t.coef for eq in start.equations for t in eq.terms}
    base = set(engine.base.tolist())
    for k, name in enumerate(engine.names):
        if k not in base:
            theta0[k] = by_name.get(name, 0.0)
    return engine, prior(engine), theta0, by_name


def _candidates(engine: Engine, start: IdentifiedModel, alpha, theta0, by_name, seed: Solution | None = None):
    """The union's fit and the fits of the evidence's and the equation error's structures (None: ran away). With
    ``seed``, the evidence's fit on the whole records, the union starts there, its other terms at zero; else (or
    where that runs away) by continuation from the equation error's coefficients."""
    every = np.arange(len(engine.positions))
    warm = None if seed is None else restarted(seed, engine.passes, engine.longest)
    union = None
    if warm is not None:
        near = np.zeros_like(theta0)
        near[engine.base] = theta0[engine.base]
        union = _fit(engine, every, near, alpha, warm=warm)
    union = union or _fit(engine, every, theta0, alpha)
    if union is None:
        return None, {}
    fits = {"evidence": _fit(engine, engine.base, theta0, alpha, warm=union)}
    ee = _positions(engine, start)
    same = fits["evidence"] is not None and set(ee) == set(engine.base.tolist())  # entered once, as the evidence's
    if ee and not same:  # from the union reduced to it; where that runs away, by continuation from its own start
        fits["equation error"] = _reduced(engine, union, ee, alpha) or _fit(
            engine, ee, _own(engine, ee, theta0, by_name), alpha
        )
    return union, fits


def _own(engine: Engine, active, theta0: np.ndarray, by_name: dict) -> np.ndarray:
    """``theta0`` with the coefficients ``active`` at the equation error's values."""
    own = theta0.copy()
    for k in active:
        own[k] = by_name[engine.names[k]]
    return own


def _reduced(engine: Engine, sol, active, alpha: np.ndarray):
    """The fit of the sub-structure ``active`` of ``sol``, started from ``sol``'s posterior with the other
    coefficients switched off by Bayesian model reduction (None: not a sub-structure, or the fit runs away)."""
    whole = [int(k) for k in sol.active]
    wanted = set(int(k) for k in active)
    if not wanted <= set(whole):
        return None
    try:
        keep, start = _reduction(sol, [n for n, k in enumerate(whole) if k not in wanted])
    except np.linalg.LinAlgError:
        return None
    return _fit(engine, keep, start, alpha, warm=sol)


def _scored(engine: Engine, union, fits: dict, alpha, cv) -> list:
    """``(solution, source, fold errors)`` of the candidates and of the backward path from the union, which stops
    descending once a structure's error is :data:`STOP_RATIO` times the best (simpler ones only lose more).

    Each step is screened first: its refit stopped after :data:`SCREEN_PASSES` passes. A structure already
    :data:`SCREEN_STOP` times the best there ends the path as it stands (:data:`SCREENED`): a structure that
    wrong crawls towards its optimum for hundreds of passes, to be refused all the same."""
    seen: dict[frozenset[int], int] = {}
    entries: list[tuple[Solution, str, np.ndarray]] = []

    def errors(sol) -> np.ndarray:
        return cross_validate(engine.passes, sol, cv).fold_errors

    def add(sol, source: str, fold_errors=None) -> float:
        key = _key(sol)
        if key not in seen:
            seen[key] = len(entries)
            entries.append((sol, source, errors(sol) if fold_errors is None else fold_errors))
        return float(np.mean(entries[seen[key]][2]))

    for source, sol in fits.items():
        if sol is not None:
            add(sol, source)
    current, latest = union, add(union, "path")
    for _ in range(MAX_PATH):
        best = min(float(np.mean(e)) for _, _, e in entries)
        if not np.isfinite(latest) or latest > STOP_RATIO * best:
            break
        screened = _backward(engine, current, alpha, SCREEN_PASSES)
        if screened is None:
            break
        key = _key(screened)
        if key in seen:  # a structure fitted already (the evidence's): the path goes on from its own fit
            current, latest = entries[seen[key]][0], float(np.mean(entries[seen[key]][2]))
            continue
        E = errors(screened)
        if not np.isfinite(np.mean(E)) or np.mean(E) > SCREEN_STOP * best:
            add(screened, SCREENED, E)
            break
        current = _finished(engine, screened, alpha)
        if current is None:
            break
        latest = add(current, "path")
    return entries


def _key(sol) -> frozenset[int]:
    """The structure of a fit: its active coefficients."""
    return frozenset(int(k) for k in sol.active)


def _tight(engine: Engine, sol, alpha: np.ndarray):
    """``sol``, a fit of the path (within :data:`PATH_NATS`), carried on to the fit's own tolerance (``sol`` where
    that runs away), its passes counted in; the engine's later fits keep that tolerance."""
    engine.tol = TOL
    return _finished(engine, sol, alpha) or sol


def _finished(engine: Engine, screened, alpha: np.ndarray):
    """The refit of a screened structure carried on from the screen to its optimum (None: it ran away), the
    screen's passes counted in it."""
    sol = _fit(engine, screened.active, screened.theta, alpha, warm=screened)
    return None if sol is None else dataclasses.replace(sol, n_pass=sol.n_pass + screened.n_pass)


#: Samples the path fits and cross-validates at most: longer data (the windows of a long record) contribute each
#: its first stretch, and a structure other than the evidence's is then refitted on every sample. Five folds of
#: 6554 samples rank the structures as the whole record does (the demo's table, a 57344-sample stand-in's choice).
PATH_SAMPLES = 2**15
#: Nats within which the path's fits stop: they rank structures whose objectives differ by the penalty per term
#: (tens of nats); the structure reported is fitted on to the fit's own tolerance.
PATH_NATS = 1.0
#: Data up to this many times :data:`PATH_SAMPLES` are scored whole: cutting them would save less than the refit
#: on every sample costs (1 s at 32768 Hz is 32769 samples).
PATH_MARGIN = 1.25


def _shortened(records, most: int) -> list:
    """Each record's first stretch, in proportion to its length, about ``most`` samples in all (the records
    themselves when they hold no more than :data:`PATH_MARGIN` times that)."""
    total = sum(r.n_samples for r in records)
    if total <= PATH_MARGIN * most:
        return list(records)
    return [r.slice(0, max(64, r.n_samples * most // total)) for r in records]


def _refitted(engine: Engine, sol, records, measured, cost: float, seed: Solution | None = None):
    """The structure of ``sol`` refitted on every sample of ``records`` (from ``seed``'s whole records when given,
    else, or where that runs away, by continuation): its engine and solution, or None when the refit runs away
    there (a structure validated on the first stretches need not hold on the rest)."""
    chosen = to_model(engine, sol, {})
    full = Engine(chosen, records, measured, engine.settings, {})
    full.longest = engine.longest
    warm = None if seed is None else restarted(seed, full.passes, full.longest)
    alpha = prior(full)
    refit = None if warm is None else _fit(full, full.base, full.param.theta0, alpha, warm=warm)
    refit = refit or _fit(full, full.base, full.param.theta0, alpha)
    return None if refit is None else (full, _every_term_clears(full, dataclasses.replace(refit, penalty=cost), cost))


def choose_structure(
    start: IdentifiedModel,
    refined: IdentifiedModel,
    records,
    measured,
    settings: Settings,
    rule: SelectionRule,
    n_candidates: int,
    longest: int | None = None,
    seed: Solution | None = None,
) -> IdentifiedModel:
    """The structure the identification keeps, with the model path it was chosen from.

    Parameters
    ----------
    start : IdentifiedModel
        The equation error's model.
    refined : IdentifiedModel
        The output error's, its structure selected on the evidence.
    records, measured, settings
        What ``refined`` was fitted on and how (its noise model's order is kept).
    rule : SelectionRule
    n_candidates : int
        Candidates the terms were chosen from (the penalty's ``M``).
    longest : int, optional
        The longest segments of the fits (``refined``'s, when held short).
    seed : Solution, optional
        ``refined``'s fit: where it spans whole records, the path's fits start from its initial states.
    """
    scored = _shortened(records, PATH_SAMPLES)
    engine, alpha, theta0, by_name = _union(start, refined, scored, measured, settings)
    engine.longest = longest
    engine.tol = PATH_NATS
    union, fits = _candidates(engine, start, alpha, theta0, by_name, seed)
    cv = folds(engine.passes, engine.length0)
    if union is None or cv is None:
        return refined
    entries = _scored(engine, union, fits, alpha, cv)
    cost = rule.nats_per_term(int(sum(r.n_samples for r in scored)) * len(measured), n_candidates)
    sizes = [int(sol.active.size) for sol, _, _ in entries]
    objectives = [float(sol.posterior.log_evidence) - cost * n for (sol, _, _), n in zip(entries, sizes)]
    E = np.array([e for _, _, e in entries])
    floor = _noise_floor(engine.passes)
    chosen, reason = rule.choose(sizes, objectives, E, floor=floor)
    sol = entries[chosen][0]
    if entries[chosen][1] == SCREENED:  # chosen on the evidence alone (no structure simulated every fold)
        sol = _finished(engine, sol, alpha) or sol
    evidence = next((k for k, entry in enumerate(entries) if entry[1] == "evidence"), None)
    fitted = engine  # the reported solution's engine; the path's entries are the scored engine's
    if chosen != evidence:
        shortened = any(a.n_samples != b.n_samples for a, b in zip(scored, records))
        sol = sol if shortened else _tight(engine, sol, alpha)
        sol = _every_term_clears(engine, dataclasses.replace(sol, penalty=cost), cost)  # the rule every model keeps
        if shortened:
            cost = rule.nats_per_term(int(sum(r.n_samples for r in records)) * len(measured), n_candidates)
            whole = _refitted(engine, sol, records, measured, cost, seed)
            if whole is not None:
                fitted, sol = whole
            elif evidence is not None:  # the evidence's structure, fitted on every sample, stays
                chosen, reason = evidence, f"{reason}; the structure so chosen ran away on every sample"
            else:
                sol = _tight(engine, sol, alpha)
    path = _table(engine, entries, sizes, objectives, E, chosen, reason)
    if chosen == evidence:
        meta = dict(refined.metadata.get("refine", {}), noise_floor=floor)
        meta["beyond_library"] = beyond_library(sizes, E, chosen, floor, rule.min_gain, _follows(meta))
        return dataclasses.replace(refined, path=path, metadata={**refined.metadata, "refine": meta})
    meta = dict(refined.metadata.get("refine", {}))
    meta.update(
        segment_length=int(sol.length),
        stages=sol.stages,
        passes=int(sol.n_pass),
        log_evidence=float(sol.posterior.log_evidence),
        effective_fraction=round(residual_fraction(fitted, sol), 4),
        residual=[as_record(t) for t in residual_tests(fitted, sol)],
        chosen_by=reason,
        noise_floor=floor,
    )
    meta["beyond_library"] = beyond_library(sizes, E, chosen, floor, rule.min_gain, _follows(meta))
    return dataclasses.replace(to_model(fitted, sol, {"refine": meta}), path=path)


def _table(engine: Engine, entries: list, sizes: list, objectives: list, E, chosen: int, reason: str) -> ModelPath:
    """The model path of the scored ``entries`` (``(solution, source, fold errors)``, ``E`` their fold errors),
    simplest first."""
    mean = mean_errors(E)
    best = int(np.argmin(mean))
    return ModelPath(
        tuple(
            PathEntry(
                _names(engine, entries[k][0].active),
                sizes[k],
                float(entries[k][0].posterior.log_evidence),
                objectives[k],
                float(mean[k]),
                paired_se(E[k], E[best]),
                "path" if entries[k][1] == SCREENED else entries[k][1],
                k == chosen,
                entries[k][1] == SCREENED,
            )
            for k in sorted(range(len(entries)), key=lambda k: (sizes[k], -objectives[k]))
        ),
        reason,
    )


def _follows(meta: dict) -> float:
    """The largest share of a channel's innovations that the model's simulated trajectory predicts, over the
    residual tests ``meta`` records (NaN when none says)."""
    shares = [t["trajectory"] for t in meta.get("residual", []) if t.get("trajectory") is not None]
    return float(max(shares)) if shares else float("nan")
