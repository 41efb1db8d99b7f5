"""The discrepancy workflow: find what a physics model is missing, name it, add it, show the gain.

Starting from a user's model (per state, a list of terms whose coefficients are fitted), each
iteration

1. fits the current model on weak-form rows of the training record (every term kept: the
   structure is the user's, the coefficients are the data's) and re-simulates it on the
   training and held-out records;
2. locates the disagreement: the equation residual of the velocity equation and the
   simulation error, where in time and in the phase plane (displacement, velocity) they
   concentrate (:class:`Disagreement`);
3. scores every effect of the catalogue (:mod:`symsbl.catalogue`) by the exact change of the
   RVM log evidence when its term(s) join the velocity equation (a refit, other terms free),
   and by the held-out error of the refitted model;
4. adds the winner only when its evidence gain clears a threshold calibrated against "nothing
   missing", beats the runner-up by ``margin_nats`` and lowers the held-out error by at least
   ``min_improvement``; otherwise it reports "nothing missing" or "ambiguous between A and B".

Calibration. The weak form on non-overlapping windows gives rows with independent noise, so under
"nothing missing" the gain of one candidate is ``1/2 (z^2 - 1 - ln z^2)`` with ``z^2 ~ chi^2_1``.
Errors in the regressors (noise on the measured states), finite-difference effects and the
fitted-coefficient bias break that ideal, so the threshold is also measured by a parametric
bootstrap: the current model is simulated on the training input, noise of the level measured in
the data (:func:`noise_levels`) is added to every channel, and the whole scoring is rerun; the
threshold is ``max(floor_nats, bootstrap_factor * max null gain)``. When the residual rows are
correlated (a real record's unmodelled dynamics), the statistics are scaled by the effective
sample fraction ``N_eff / N`` before scoring (:class:`Disagreement`).

Measured (oscillator m = 1, c = 20, k = 1e4; 3 s of a 100 N, 10 Hz sine at 16384 Hz; 0.4 % noise;
7 effects, 15 candidates): under "nothing missing" the largest gain over the catalogue stayed below
6 nats in 600 runs (white noise on the states, noise on every channel, a Duffing model that already
has its cubic term; 200 seeds each; the bootstrap raised the threshold to 24.5 nats at most) and
nothing was added. Hidden effects that move the training re-simulation by less than 2x the noise
gain 230-440 nats, 20-90 nats ahead of the runner-up. Ten times smaller ones (cubic stiffness,
Coulomb friction, quadratic damping; 3 seeds each) ended as "nothing missing", "ambiguous" or the
right name, never a wrong one.

The held-out error is the simulation NRMSE averaged over the states (``error="simulation"``)
or, for closed-loop or drifting plants, the NRMSE of the velocity equation on the held-out
weak-form rows (``error="equation"``, a one-step force error).
"""

from __future__ import annotations

import math
from typing import Sequence

import casadi as ca
import numpy as np

from .catalogue import CATALOGUE, Effect
from .data import Trajectory
from .derivatives import get_differentiator
from .errors import DataError, LibraryError, SimulationError
from .evaluator import Evaluator
from .identify import regression_stats
from .library import Library
from .model import Equation, IdentifiedModel, TermEstimate
from .progress import Progress
from .rvm import RVM
from .selection import subset_stats
from .signals import Sampled
from .simulate import simulate
from .validate import validate_model
from .discrepancy_data import _check_traj, _split, noise_levels, parse_base, position_record
from .discrepancy_results import Disagreement, DiscrepancyReport, DiscrepancyStep, EffectScore

__all__ = [
    "Disagreement", "EffectScore", "DiscrepancyStep", "DiscrepancyReport",
    "discrepancy", "parse_base", "noise_levels", "position_record", "ERROR_MEASURES",
]

ERROR_MEASURES = ("simulation", "equation")


class _Design:
    """One library holding every base and candidate term, its columns, and the statistics of each
    record (computed once per record, shared by every fit of every iteration)."""

    def __init__(self, base, candidates, states, inputs, derivative):
        self.states, self.inputs = states, inputs
        variables = tuple(states) + tuple(inputs)
        self.variables = variables
        exprs = [e for terms in base.values() for e in terms] + [e for v in candidates for e in v.exprs]
        self.library = Library(exprs, variables)
        self.derivative = derivative
        self._stats: dict[int, object] = {}
        #: Effective-sample fraction of the rows (1 for independent residuals), see ``_effective_fraction``.
        self.weight = 1.0

    def column(self, expr) -> int | None:
        """Column of ``expr`` (None when the library merged it into an equal term)."""
        name = Library([expr], self.variables).names
        if not name or name[0] not in self.library:
            return None
        return self.library.index(name[0])

    def stats(self, traj: Trajectory):
        key = id(traj)
        if key not in self._stats:
            self._stats[key] = (traj, regression_stats(traj, self.library, derivative=self.derivative).stats)
        return self._stats[key][1]

    def forget(self, traj: Trajectory) -> None:
        """Drop the statistics of a record no longer needed (a bootstrap replicate)."""
        self._stats.pop(id(traj), None)

    def fit(self, traj, k, cols) -> RVM:
        rvm = RVM(free=tuple(range(len(cols))), prune_nats=None)
        stats = subset_stats(self.stats(traj), cols, k)
        return rvm.fit_stats(stats if self.weight == 1.0 else stats.scaled(self.weight))

    def equation(self, lhs, cols, fit, n_rows) -> Equation:
        terms = tuple(
            TermEstimate(self.library.terms[c].expr, float(fit.coef_[i]), float(math.sqrt(fit.sigma_[i, i])),
                         float(fit.alpha_[i]), float(fit.evidence_contribution_[i]))
            for i, c in enumerate(cols)
        )
        return Equation(lhs, terms, np.array(fit.sigma_), float(fit.noise_var_), float(fit.log_evidence_), int(n_rows))

    def model(self, structure, traj) -> IdentifiedModel:
        equations = []
        names = list(traj.state_names)
        for lhs, cols in structure.items():
            fit = self.fit(traj, names.index(lhs), cols)
            equations.append(self.equation(lhs, cols, fit, self.stats(traj).n_samples))
        return IdentifiedModel(tuple(self.states), tuple(self.inputs), tuple(equations),
                               metadata={"derivative": type(self.derivative).__name__})


def _error(model: IdentifiedModel, traj: Trajectory, measure: str, design: _Design, velocity: str) -> float:
    if measure == "simulation":
        result = validate_model(model, traj, method="rk4")
        return math.inf if result.status != "ok" else float(np.mean(list(result.nrmse.values())))
    stats = design.stats(traj)
    k = list(traj.state_names).index(velocity)
    eq = model.equation(velocity)
    cols = [design.column(t.expr) for t in eq.terms]
    theta = eq.coefs
    rss = stats.yty[k] - 2 * theta @ stats.dty[cols, k] + theta @ stats.gram[np.ix_(cols, cols)] @ theta
    n = stats.n_samples
    var = stats.yty[k] / n - (stats.y_sum[k] / n) ** 2
    return float(math.sqrt(max(rss, 0.0) / n / var))


# ------------------------------------------------------------------------------- localisation
def _locate(model, train, heldout, design, displacement, velocity, measure) -> Disagreement:
    diff = design.derivative
    eq = model.equation(velocity)
    lib = Library([t.expr for t in eq.terms], design.variables)
    Z = np.column_stack([train.column(n) for n in lib.variable_names])
    D = diff.reduce(Evaluator(lib, jit=False).evaluate(Z))
    y = diff.targets(train.t, train.column(velocity)[:, None])[:, 0]
    r = y - D @ np.array([eq.coef(n) for n in lib.names])
    xv = diff.reduce(np.column_stack([train.column(displacement) if displacement else np.zeros(train.n_samples),
                                      train.column(velocity)]))
    x, v = xv[:, 0], xv[:, 1]
    X, V = max(np.max(np.abs(x)), 1e-300), max(np.max(np.abs(v)), 1e-300)
    energy = r**2 / max(np.sum(r**2), 1e-300)
    masks = [("velocity reversals (|v| < 0.15 V)", np.abs(v) < 0.15 * V),
             ("peak speed (|v| > 0.75 V)", np.abs(v) > 0.75 * V)]
    if displacement:
        masks.append(("large displacement (|x| > 0.75 X)", np.abs(x) > 0.75 * X))
    regions = tuple((name, float(m.mean()), float(energy[m].sum())) for name, m in masks)
    up, down = r[(v > 0) & (v < 0.15 * V)], r[(v < 0) & (v > -0.15 * V)]
    jump, jump_z = 0.0, 0.0
    if len(up) > 1 and len(down) > 1:
        jump = float(up.mean() - down.mean())
        jump_z = jump / math.sqrt(up.var() / len(up) + down.var() / len(down) + 1e-300)
    edges_x, edges_v = np.linspace(-X, X, 9), np.linspace(-V, V, 9)
    total, _, _ = np.histogram2d(x, v, [edges_x, edges_v], weights=r)
    count, _, _ = np.histogram2d(x, v, [edges_x, edges_v])
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_map = np.where(count > 0, total / count, np.nan)
    # time profile of the held-out error
    if measure == "simulation":
        sim = validate_model(model, heldout, method="rk4").simulated
        states = [n for n in model.state_names]
        meas = np.column_stack([heldout.column(n) for n in states])[: sim.n_samples]
        segments = np.array_split(np.arange(sim.n_samples), 10)
        scale = np.std(meas, axis=0)
        err = [float(np.mean(np.sqrt(np.mean((meas[s] - sim.states[s]) ** 2, axis=0)) / scale)) for s in segments]
        mids = [float(heldout.t[s].mean()) for s in segments]
    else:
        mids, err = [], []
    residual_nrmse = float(math.sqrt(np.mean(r**2)) / max(np.std(y), 1e-300))
    worst = max(regions, key=lambda reg: reg[2] / max(reg[1], 1e-12))
    words = [f"equation residual {100 * residual_nrmse:.3g} % of the target's spread"]
    if worst[2] > 1.5 * worst[1]:
        words.append(f"concentrated at {worst[0]}: {100 * worst[2]:.0f} % of its energy in {100 * worst[1]:.0f} % of the rows")
    else:
        words.append("spread evenly over the phase plane")
    if abs(jump_z) > 5:
        words.append(f"it jumps by {jump:.3g} (z = {jump_z:.0f}) across v = 0")
    if err:
        i = int(np.argmax(err))
        words.append(f"held-out simulation error largest near t = {mids[i]:.3g} s ({100 * err[i]:.3g} %)")
    return Disagreement(residual_nrmse, _effective_fraction(r), regions, jump, float(jump_z), (edges_x, edges_v, mean_map),
                        (np.array(mids), np.array(err)), "; ".join(words))


def _effective_fraction(r: np.ndarray, max_lag: int = 50) -> float:
    r = r - r.mean()
    c0, total = float(r @ r), 0.0
    for j in range(1, min(max_lag, len(r) - 1)):
        rho = float(r[:-j] @ r[j:]) / c0
        if abs(rho) < 0.05:
            break
        total += rho
    return float(min(1.0, 1.0 / max(1.0 + 2.0 * total, 1.0)))


# ------------------------------------------------------------------------------------- scoring
def _score(design, structure, traj, velocity, candidates, bar) -> list[tuple]:
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


def _best_per_effect(scored) -> dict[str, tuple]:
    """Per effect, its best variant with the grid penalty ``log(len(grid))`` applied."""
    best: dict[str, tuple] = {}
    for variant, gain, fit, cols in scored:
        penalty = math.log(len(variant.effect.grid)) if variant.effect.grid else 0.0
        entry = (variant, gain - penalty, fit, cols)
        if variant.effect.name not in best or entry[1] > best[variant.effect.name][1]:
            best[variant.effect.name] = entry
    return best


def _admissible(effect: Effect, coef: float, input_coef: float | None) -> tuple[bool, str]:
    if effect.sign == 0 or not np.isfinite(coef):
        return True, ""
    reference = 1.0 if input_coef is None else math.copysign(1.0, input_coef)
    if coef * reference < 0:
        return True, ""
    return False, "wrong sign: it would feed energy in"


def _null_gains(design, structure, model, train, velocity, candidates, noise, n_bootstrap, seed, bar) -> list[float]:
    """Largest candidate gain on records simulated from ``model`` with the measured noise."""
    system = model.to_system()
    U = train.inputs if train.inputs.shape[1] else None
    x0 = train.states[0]
    out = []
    try:
        clean = simulate(system, train.t, inputs=None if U is None else Sampled(train.t, U), x0=x0, method="rk4",
                         on_divergence="raise")
    except SimulationError:
        return out
    rng = np.random.default_rng(seed)
    for _ in range(n_bootstrap):
        states = clean.states + rng.standard_normal(clean.states.shape) * [noise[n] for n in train.state_names]
        inputs = train.inputs
        if U is not None:
            inputs = clean.inputs + rng.standard_normal(U.shape) * [noise[n] for n in train.input_names]
        fake = Trajectory(train.t, states, inputs, train.state_names, train.input_names)
        gains = [g for _, g, _, _ in _best_per_effect(_score(design, structure, fake, velocity, candidates, bar)).values()]
        design.forget(fake)
        out.append(max([g for g in gains if np.isfinite(g)], default=0.0))
    return out


# ------------------------------------------------------------------------------------ workflow
def _pair(base, state_names, displacement, velocity):
    """The (displacement, velocity) pair: ``x: v`` in the base names them unless given."""
    for name, label in ((displacement, "displacement"), (velocity, "velocity")):
        if name is not None and name not in state_names:
            raise DataError(f"{label} must be one of the states {list(state_names)}; received {name!r}.")
    if velocity is None:
        for x, terms in base.items():
            names = [str(t) for t in terms]
            if len(names) == 1 and names[0] in state_names and names[0] != x and (displacement in (None, x)):
                return x, names[0]
        raise DataError(
            "cannot tell which state is the velocity: no state has the base equation 'x: v' with v another "
            f"state (base: {{{', '.join(f'{k}: {[str(t) for t in v]}' for k, v in base.items())}}}). "
            "Pass velocity= (and displacement=) explicitly."
        )
    return displacement, velocity


def discrepancy(
    data: Trajectory,
    base,
    *,
    heldout: Trajectory | None = None,
    effects: Sequence[Effect] = CATALOGUE,
    displacement: str | None = None,
    velocity: str | None = None,
    derivative="weak",
    error: str = "simulation",
    floor_nats: float = 8.0,
    n_bootstrap: int = 2,
    bootstrap_factor: float = 2.0,
    margin_nats: float = 3.0,
    min_improvement: float = 0.1,
    max_iterations: int = 4,
    seed: int = 0,
) -> DiscrepancyReport:
    """Find, name and add what the model ``base`` is missing; show the held-out gain.

    Parameters
    ----------
    data : Trajectory
        Training record (states and inputs).
    base : str or dict
        The starting model: ``"x1: x2; x2: F, x1, x2"`` (see :func:`parse_base`) or a dict
        state -> sequence of casadi.SX terms. Its coefficients are fitted.
    heldout : Trajectory, optional
        Held-out record, ideally at another forcing level; without it the last 30 % of ``data``
        is held out.
    effects : sequence of Effect
        The catalogue (default :data:`symsbl.catalogue.CATALOGUE`; see
        :func:`symsbl.catalogue.catalogue` to add or remove entries).
    displacement, velocity : str, optional
        State names of the pair the effects act on; by default read from a base equation
        ``x: v``.
    derivative : str or strategy
        Regression rows (default the weak form on non-overlapping windows; its window is fixed
        from the training record and reused for every record).
    error : {"simulation", "equation"}
        Held-out error: mean NRMSE of the re-simulated states, or NRMSE of the velocity equation
        on the held-out rows (for closed-loop or drifting plants that cannot be run open-loop).
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
    max_iterations : int
    seed : int
        Seed of the bootstrap noise.

    Returns
    -------
    DiscrepancyReport

    Raises
    ------
    DataError, LibraryError
        Malformed records or base model, naming the argument, what was expected and received.

    Examples
    --------
    A linear model misses 1 N of Coulomb friction; trained at 100 N it hides, held out at 10 N it shows:

    >>> import symsbl
    >>> truth = symsbl.systems.coulomb(kc=1.0)
    >>> grid = symsbl.time_grid(2.0, 8192)
    >>> train = symsbl.simulate(truth, grid, inputs=symsbl.Sine(100.0, 10.0)).with_noise(0.004, seed=0)
    >>> held = symsbl.simulate(truth, grid[:8193], inputs=symsbl.Sine(10.0, 10.0)).with_noise(0.004, seed=1)
    >>> report = symsbl.discrepancy(train, "x1: x2; x2: F, x1, x2", heldout=held, n_bootstrap=0)
    >>> report.verdict
    'added coulomb_friction; then nothing missing'
    >>> (added,) = report.added
    >>> added.terms, round(added.coef, 1)
    (('sign(x2)',), -1.0)
    >>> step = report.steps[0]
    >>> step.error_heldout > 10 * step.error_after    # held-out error before and after
    True
    """
    _check_traj(data, "data", None)
    names = (tuple(data.state_names), tuple(data.input_names))
    if error not in ERROR_MEASURES:
        raise DataError(f"error must be one of {list(ERROR_MEASURES)}; received {error!r}.")
    if heldout is None:
        data, heldout = _split(data)
    _check_traj(heldout, "heldout", names)
    if isinstance(base, str):
        base = parse_base(base, data.state_names, data.input_names)
    if not isinstance(base, dict) or set(base) != set(data.state_names):
        raise LibraryError(
            f"base must give terms for exactly the states {list(data.state_names)}; received "
            f"{sorted(base) if isinstance(base, dict) else type(base).__name__}."
        )
    run = _Workflow(data, heldout, base, effects, displacement, velocity, derivative, error)
    settings = dict(floor_nats=floor_nats, n_bootstrap=n_bootstrap, bootstrap_factor=bootstrap_factor,
                    margin_nats=margin_nats, min_improvement=min_improvement)
    initial = model = run.design.model(run.structure, data)
    steps, names_added, note = [], [], "nothing missing"
    for it in range(1, max_iterations + 1):
        step = run.iterate(it, model, seed=seed + it, **settings)
        steps.append(step)
        if step.added is None:
            note = step.verdict.split(":")[0]
            break
        names_added.append(step.added.effect)
        model = step.model_after
    verdict = f"added {', '.join(names_added)}; then {note}" if names_added else note
    return DiscrepancyReport(initial, model, tuple(steps), verdict, error, run.noise)


class _Workflow:
    """The state of one discrepancy run: the records, the design and the current structure."""

    def __init__(self, data, heldout, base, effects, displacement, velocity, derivative, error):
        self.data, self.heldout, self.error, self.effects = data, heldout, error, tuple(effects)
        self.x, self.v = _pair(base, data.state_names, displacement, velocity)
        states = tuple(ca.SX.sym(n) for n in data.state_names)
        inputs = tuple(ca.SX.sym(n) for n in data.input_names)
        sym = dict(zip(data.state_names, states))
        x_amp = float(np.max(np.abs(data.column(self.x)))) if self.x else 1.0
        x_sym = sym[self.x] if self.x else ca.SX.sym("_unused")
        variants = [w for e in self.effects
                    for w in e.variants(x_sym, sym[self.v], x_amp, float(np.max(np.abs(data.column(self.v)))))]
        variants = [w for w in variants if self.x or not any(ca.depends_on(e, x_sym) for e in w.exprs)]
        n_terms = len(variants) + sum(map(len, base.values()))
        diff = get_differentiator(derivative).resolve(data.t, data.states, n_terms=n_terms)
        self.design = _Design(base, variants, states, inputs, diff)
        self.structure = {s: [self.design.column(e) for e in terms] for s, terms in base.items()}
        for s, cols in self.structure.items():
            if None in cols or len(set(cols)) < len(cols):
                raise LibraryError(f"base: the terms of state {s!r} repeat (up to a constant factor); list each once.")
        candidates = [(w, [self.design.column(e) for e in w.exprs]) for w in variants]
        self.candidates = [(w, cols) for w, cols in candidates if None not in cols]
        lib = self.design.library
        self.input_terms = [i for i, c in enumerate(self.structure[self.v]) if lib.terms[c].name in data.input_names]
        self.noise = noise_levels(data)

    def err(self, model, traj) -> float:
        return _error(model, traj, self.error, self.design, self.v)

    def with_terms(self, *scores) -> dict:
        trial = dict(self.structure)
        trial[self.v] = self.structure[self.v] + [self.design.library.index(n) for c in scores for n in c.terms]
        return trial

    def scores(self, model, bar) -> list[EffectScore]:
        eq = model.equation(self.v)
        input_coef = eq.terms[self.input_terms[0]].coef if len(self.input_terms) == 1 else None
        out = []
        scored = _score(self.design, self.structure, self.data, self.v, self.candidates, bar)
        for variant, gain, fit, cols in _best_per_effect(scored).values():
            e = variant.effect
            if fit is None:
                out.append(EffectScore(e.name, variant.label, e.description, e.family, tuple(str(x) for x in variant.exprs),
                                       -math.inf, math.nan, math.nan, None, False, "already in the model", None, variant.shape))
                continue
            i = len(self.structure[self.v])
            coef, std = float(fit.coef_[i]), float(math.sqrt(fit.sigma_[i, i]))
            ok, reason = _admissible(e, coef, input_coef)
            out.append(EffectScore(e.name, variant.label, e.description, e.family,
                                   tuple(self.design.library.names[c] for c in cols[i:]), gain, coef, std,
                                   None if input_coef is None else -coef / input_coef, ok, reason, None, variant.shape))
        return sorted(out, key=lambda c: -c.evidence_gain)

    def iterate(self, it, model, *, floor_nats, n_bootstrap, bootstrap_factor, margin_nats, min_improvement, seed):
        design, data = self.design, self.data
        err_train, err_held = self.err(model, data), self.err(model, self.heldout)
        design.weight = 1.0
        where = _locate(model, data, self.heldout, design, self.x, self.v, self.error)
        design.weight = where.effective_fraction
        model = design.model(self.structure, data)
        replicates = n_bootstrap if self.error == "simulation" else 0
        with Progress(f"discrepancy iteration {it}: scoring the catalogue", unit="fits",
                      total=(1 + replicates) * len(self.candidates)) as bar:
            scores = self.scores(model, bar)
            null = []
            if replicates > 0:
                null = _null_gains(design, self.structure, model, data, self.v, self.candidates, self.noise,
                                   n_bootstrap, seed, bar)
        threshold = max([floor_nats] + [bootstrap_factor * g for g in null])
        for pos, c in enumerate(scores[:3]):  # held-out error of the leading candidates
            if c.admissible and c.evidence_gain > 0:
                scores[pos] = _replace(c, error_after=self.err(design.model(self.with_terms(c), data), self.heldout))
        ranked = [c for c in scores if c.admissible and np.isfinite(c.evidence_gain)]
        best = ranked[0] if ranked else None
        runner = ranked[1] if len(ranked) > 1 else None
        target = (1 - min_improvement) * err_held
        step = dict(iteration=it, model=model, error_train=err_train, error_heldout=err_held, disagreement=where,
                    scores=tuple(scores), threshold=threshold, null_gains=tuple(null))
        if best is None or best.evidence_gain <= threshold:
            gain = "none" if best is None else f"{best.evidence_gain:.1f}"
            return DiscrepancyStep(**step, decision="nothing missing", verdict=(
                f"nothing missing: no effect gains more than the threshold ({gain} <= {threshold:.1f} nats)"))
        if runner is not None and best.evidence_gain - runner.evidence_gain < margin_nats:
            return DiscrepancyStep(**step, decision="ambiguous", verdict=(
                f"ambiguous between {best.effect} and {runner.effect}: evidence gains {best.evidence_gain:.1f} "
                f"and {runner.evidence_gain:.1f} nats differ by less than {margin_nats:g}"))
        joint = ""
        if not (best.error_after is not None and best.error_after < target):
            # The held-out error may be dominated by a second missing effect: confirm jointly.
            for other in ranked[1:]:
                if other.evidence_gain <= threshold:
                    break
                if self.err(design.model(self.with_terms(best, other), data), self.heldout) < target:
                    joint = f" (confirmed together with {other.effect})"
                    break
            if not joint:
                after = "-" if best.error_after is None else f"{100 * best.error_after:.3g}"
                return DiscrepancyStep(**step, decision="no held-out gain", verdict=(
                    f"{best.effect} gains {best.evidence_gain:.1f} nats but does not lower the held-out error "
                    f"enough ({100 * err_held:.3g} % -> {after} %); not added"))
        self.structure = self.with_terms(best)
        after_model = design.model(self.structure, data)
        after_err = best.error_after if best.error_after is not None else self.err(after_model, self.heldout)
        coef_name = next((e.coefficient for e in self.effects if e.name == best.effect), "k")
        phys = "" if best.physical is None else f", {coef_name} = {best.physical:.4g}"
        lead = best.evidence_gain - (runner.evidence_gain if runner else 0.0)
        verdict = (f"added {best.effect} ({best.description}){phys}: +{best.evidence_gain:.1f} nats, {lead:.1f} ahead "
                   f"of {runner.effect if runner else 'nothing'}; held-out error {100 * err_held:.3g} % -> "
                   f"{100 * after_err:.3g} %{joint}")
        return DiscrepancyStep(**step, decision="added", verdict=verdict, added=best, model_after=after_model,
                               error_after=after_err)


def _replace(score: EffectScore, **changes) -> EffectScore:
    import dataclasses

    return dataclasses.replace(score, **changes)
