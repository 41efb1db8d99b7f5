"""The discrepancy workflow: find what a physics model is missing, name it, add it, show the gain.

Starting from a user's model (per state, a list of terms whose coefficients are fitted), each
iteration fits the current model, locates where it disagrees with the records (the equation
residual and the simulation error, in time and over the phase plane: :class:`Disagreement`),
scores candidate effects, and adds the best one only when the evidence says so. Two kinds of
evidence are available:

- **output error** (the default; :mod:`.scoring`, :mod:`.search`): the model is fitted by
  simulation error on every record at once and each candidate (catalogue effects on every
  position-velocity pair and on the relative motion of coupled pairs, and library terms outside
  the catalogue: :mod:`.candidates`) is scored by the change of the Laplace log evidence; the
  winner is confirmed by cross-validation (:mod:`.confirm`), named when its Bayes factor over the
  runner-up clears ``margin_nats``, and an earlier choice is replaced when, with the effects added
  since, its runner-up explains the records better, or removed when they explain it away;
- **equation error** (:mod:`.decide`): the RVM log evidence of the weak-form rows of the training
  record, with the held-out record as a gate (the first release's rule; for closed-loop plants
  that cannot be simulated open loop, ``error="equation"``).

Calibration. A threshold calibrated against "nothing missing": at least ``floor_nats``, and
``bootstrap_factor`` times the largest gain measured by a parametric bootstrap (the current model
simulated with noise of the level measured in the data, :func:`noise_levels`, and the whole
screening rerun). When the residual is correlated (a real record's unmodelled dynamics, coloured
noise), the gains are scaled by the effective sample fraction ``N_eff / N``.

The held-out error is the simulation NRMSE averaged over the states (``error="simulation"``)
or, for closed-loop or drifting plants, the NRMSE of the velocity equation on the held-out
weak-form rows (``error="equation"``, a one-step force error).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import casadi as ca
import numpy as np

from .._base.checks import Constraint, check_params
from .._base.errors import DataError, LibraryError, expected
from .._data.residuals import effective_fraction
from .._data.trajectory import Trajectory, noise_levels
from .._derivatives.kinematics import complete_states, parse_kinematics, sensor_states
from .._derivatives.registry import get_differentiator
from .._model import AccelerationOutput, Equation
from .._model.outputs import state_outputs
from .._refine.diagnostics import residual_tests
from .._refine.engine import Settings
from .._symbolic.symbols import casadi_to_sympy
from .candidates import catalogue_candidates, library_candidates, pairs_of
from .catalogue import CATALOGUE, Effect
from .decide import DecisionRule, decide
from .design import ERROR_MEASURES, Design, heldout_error
from .inputs import check_record, parse_base, split_record
from .locate import locate
from .results import OUTSIDE_CATALOGUE, Decision, DiscrepancyReport, DiscrepancyStep
from .scoring import Scorer
from .search import as_in_final, oe_step

__all__ = ["discrepancy", "Workflow", "EVIDENCE"]

#: What the evidence of an effect is computed from.
EVIDENCE = ("output-error", "equation-error")

#: The default decision rule (frozen, so one shared instance is safe as an argument default).
DEFAULT_RULE = DecisionRule()

#: The accepted values of :func:`discrepancy`'s scalar options, declared as data (checked where they enter).
OPTIONS = {
    "error": Constraint.choice(ERROR_MEASURES),
    "evidence": Constraint.choice(EVIDENCE),
    "search_library": Constraint.boolean(),
    "max_iterations": Constraint.integer(low=1),
    "seed": Constraint.integer(low=0),
}


def _regressors(X: np.ndarray) -> np.ndarray:
    """A constant and simple functions of the (standardised) simulated states ``X``."""
    S = (X - X.mean(axis=0)) / np.maximum(X.std(axis=0), 1e-300)
    cols = [np.ones(X.shape[0])]
    for j in range(S.shape[1]):
        s = S[:, j]
        cols += [s, s**2, s**3, s * np.abs(s), np.sign(s)]
        cols += [s * S[:, i] for i in range(j)]
    return np.column_stack(cols)


def _pair(base, state_names, displacement, velocity):
    """The (displacement, velocity) pair: ``x: v`` in the base names them unless given."""
    for name, label in ((displacement, "displacement"), (velocity, "velocity")):
        if name is not None and name not in state_names:
            raise DataError(expected(label, f"one of the states {list(state_names)}", name))
    if velocity is None:
        for x, terms in base.items():
            names = [str(t) for t in terms]
            if len(names) == 1 and names[0] in state_names and names[0] != x and (displacement in (None, x)):
                return x, names[0]
        shown = {k: [str(t) for t in casadi_to_sympy(list(v))] for k, v in base.items()}
        raise DataError(
            expected(
                "velocity",
                "a base equation 'x: v' naming the velocity v, another state",
                f"the base {shown}",
                "pass velocity= (and displacement=) explicitly",
                raw=True,
            )
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
    kinematics=None,
    evidence: str | None = None,
    search_library: bool = True,
    derivative="weak",
    error: str = "simulation",
    rule: DecisionRule = DEFAULT_RULE,
    max_iterations: int = 8,
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
        is held out. With output-error evidence both records are evidence, and the choice is
        confirmed by cross-validation over the halves of both.
    effects : sequence of Effect
        The catalogue (default :data:`symsbl.CATALOGUE`; see
        :func:`symsbl.catalogue` to add or remove entries).
    displacement, velocity : str, optional
        One pair to search (equation-error evidence searches one pair: by default the first base
        equation ``x: v``).
    kinematics : mapping or str, optional
        The position-velocity pairs to search, ``{"x1": "x2", "x3": "x4"}`` or ``"x1:x2,x3:x4"``
        (default: every base equation ``x: v``); effects of the relative motion of two coupled pairs
        are candidates too. A velocity of a pair that ``data`` and ``heldout`` do not hold is unmeasured
        (displacement only): it is estimated from its position for the equation-error start
        (a smoothing derivative) and the output error fits the measured states alone.
        A third name, ``"x:v:a"``, is a column measuring ``v'`` (an accelerometer): the pair's states are then
        integrated from it for the start and the output error fits the measured acceleration.
    evidence : {"output-error", "equation-error"}, optional
        How effects are scored: the Laplace evidence of the output-error fit of every record
        (default with ``error="simulation"``), or the RVM evidence of the weak-form equation error of
        the training record (default with ``error="equation"``, for plants that cannot run open loop).
    search_library : bool
        Output error: also try library terms outside the catalogue (products of a pair's states up to
        degree three, absolute values, signs, an offset); one is added only when it beats every named
        effect.
    derivative : str or strategy
        Regression rows of the equation-error fits (default the weak form on non-overlapping windows).
    error : {"simulation", "equation"}
        Held-out error: mean NRMSE of the re-simulated states, or NRMSE of the velocity equation
        on the held-out rows (for closed-loop or drifting plants that cannot be run open-loop).
    rule : DecisionRule
        When an effect is added: evidence floor, bootstrap calibration, margin over the
        runner-up (and, for equation-error evidence, the held-out improvement).
    max_iterations : int
        Iterations at most (each adds, replaces or removes one effect, or ends the search).
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
    >>> grid = symsbl.time_grid(2.0, 4096)
    >>> train = symsbl.simulate(truth, grid, inputs=symsbl.Sine(100.0, 10.0)).with_noise(0.004, seed=0)
    >>> held = symsbl.simulate(truth, grid[:4097], inputs=symsbl.Sine(10.0, 10.0)).with_noise(0.004, seed=1)
    >>> report = symsbl.discrepancy(train, "x1: x2; x2: F, x1, x2", heldout=held,
    ...                             rule=symsbl.DecisionRule(n_bootstrap=0))
    >>> report.verdict
    'added coulomb_friction; then nothing missing'
    >>> (added,) = report.added
    >>> added.terms, round(added.coef, 2)
    (('sign(x2)',), -1.0)
    >>> step = report.steps[0]
    >>> step.error_heldout > 10 * step.error_after    # held-out error before and after
    True
    """
    check_record(data, "data", None)
    names = (tuple(data.state_names), tuple(data.input_names))
    chosen_by_default = evidence is None
    error, evidence, search_library, max_iterations, seed = _options(
        error, evidence, search_library, max_iterations, seed, rule
    )
    if heldout is None:
        data, heldout = split_record(data)
    check_record(heldout, "heldout", names)
    data, heldout, states, measured, accelerations = _complete_records(data, heldout, kinematics, evidence)
    if isinstance(base, str):
        base = parse_base(base, states, data.input_names)
    if not isinstance(base, dict) or set(base) != set(states):
        got = sorted(base) if isinstance(base, dict) else type(base).__name__
        raise LibraryError(expected("base", f"terms for exactly the states {list(states)}", got))
    pairs = parse_kinematics(kinematics, states)
    if displacement is not None and velocity is not None and not pairs:
        pairs = ((displacement, velocity),)
    x, v = displacement or (pairs[0][0] if pairs else None), velocity or (pairs[0][1] if pairs else None)
    run = Workflow(data, heldout, base, effects, x, v, derivative, error, measured, accelerations)
    start = run.design.model(run.structure, run.view)
    notes = []
    if evidence == "output-error":
        run.use_output_error(start, pairs, search_library)
        start = run.structure_model
        loop = _feedback(run, start) if chosen_by_default and states == measured else ""
        if loop:  # a closed loop biases output error; the inverse model's equation error is consistent
            notes.append(
                f"{loop}: the record looks closed-loop, where output error is biased; the equation-error "
                "(inverse-model) evidence and the equation error are used instead"
            )
            evidence, error = "equation-error", "equation"
            run = Workflow(data, heldout, base, effects, x, v, derivative, error, measured)
            start = run.design.model(run.structure, data)
    steps, names_added, note, model = _iterate(run, start, evidence, rule, max_iterations, seed)
    verdict = f"added {', '.join(names_added)}; then {note}" if names_added else note
    initial = steps[0].model if evidence == "output-error" else start
    final = model if evidence == "equation-error" or steps[-1].model_after is not None else steps[-1].model
    if evidence == "output-error":
        steps = as_in_final(run, steps, final)
    return DiscrepancyReport(initial, final, tuple(steps), verdict, error, run.noise, evidence, tuple(notes))


def _complete_records(data, heldout, kinematics, evidence):
    """The records with every state of the declared pairs (estimated when unmeasured) then their measured
    accelerations, the states, the measured channels and the accelerations ``{velocity: column}``."""
    measured = tuple(data.state_names)
    states, accelerations = sensor_states(measured, kinematics)
    if states != measured:  # displacement or acceleration only: the pairs' states estimated for the start
        if evidence != "output-error":
            raise DataError(
                expected(
                    "evidence",
                    "'output-error' when a velocity is not measured (only the output "
                    "error fits the measured positions alone)",
                    evidence,
                    raw=True,
                )
            )
        pairs = parse_kinematics(kinematics, states)
        keep = tuple(accelerations.values())
        (data, heldout), _ = complete_states([data, heldout], states, pairs, accelerations, keep=keep)
    return data, heldout, states, measured, accelerations


def _iterate(run, start, evidence, rule, max_iterations, seed):
    """The search's steps from ``start``, the names of the effects it added, how it ended and its last model."""
    steps, names_added, note, model = list[DiscrepancyStep](), list[str](), _ending(None), start
    for it in range(1, max_iterations + 1):
        step = (
            oe_step(run, it, model, rule, seed=seed + it, history=tuple(steps))
            if evidence == "output-error"
            else decide(run, it, model, rule, seed=seed + it)
        )
        steps.append(step)
        if step.model_after is None:
            note = _ending(step)
            break
        if step.replaces is not None:
            old, old_added = next((s, s.added) for s in steps if s.added is not None and s.added.label == step.replaces)
            if step.added is not None:  # replaced; an effect removed is not proposed again
                run.added_keys.discard((old_added.effect, old_added.where))
            names_added.remove(_added_name(old))
        if step.added is not None:  # else removed
            names_added.append(_added_name(step))
            run.added_keys.add((step.added.effect, step.added.where))
        model = step.model_after
    return steps, names_added, note, model


def _feedback(run, model) -> str:
    """The inputs that depend on past residuals of ``model``'s output-error fit on the records (a closed loop),
    as a phrase; empty when none does."""
    scorer = run.scorer(model, run.records)
    loops = sorted(
        {
            f"{name} depends on past residuals of {t.channel}"
            for t in residual_tests(scorer.engine, scorer.solution)
            for name, r in t.feedback_ratio.items()
            if r > 1
        }
    )
    return "; ".join(loops)


def _added_name(step) -> str:
    """How an added effect is named in the verdict."""
    label = step.added.label
    outside = step.added.family == OUTSIDE_CATALOGUE
    if step.decision is Decision.AMBIGUOUS:
        return (
            f"{label} ({OUTSIDE_CATALOGUE + '; ' if outside else ''}ambiguous with {step.runner_up}, "
            f"Bayes factor {step.bayes_factor:.3g})"
        )
    if outside:
        return f"{label} ({OUTSIDE_CATALOGUE})"
    if step.decision is Decision.REPLACED:
        return f"{label} (in place of {step.replaces})"
    return label


def _options(error, evidence, search_library, max_iterations, seed, rule):
    """:func:`discrepancy`'s scalar options checked against :data:`OPTIONS` (``evidence`` defaults by ``error``)."""
    error = check_params({"error": error}, OPTIONS, error=DataError)["error"]
    evidence = ("output-error" if error == "simulation" else "equation-error") if evidence is None else evidence
    checked = check_params(
        dict(evidence=evidence, search_library=search_library, max_iterations=max_iterations, seed=seed),
        OPTIONS,
        error=DataError,
    )
    if checked["evidence"] == "output-error" and error != "simulation":
        raise DataError(
            expected(
                "error",
                "'simulation' with evidence='output-error' (the output-error search scores "
                "terms the equation-error measure cannot evaluate)",
                error,
                "use evidence='equation-error' for a plant that cannot run open loop",
            )
        )
    if not isinstance(rule, DecisionRule):
        raise DataError(expected("rule", "a DecisionRule", type(rule).__name__, raw=True))
    return error, checked["evidence"], checked["search_library"], checked["max_iterations"], checked["seed"]


def _ending(step) -> str:
    """How a run ends, in words: the decision of its last step (or the iteration limit)."""
    if step is None:
        return "stopped after the last iteration"
    if step.decision is Decision.NOTHING_MISSING:
        return str(step.decision)
    if step.decision is Decision.UNEXPLAINED:
        return step.verdict
    ranked = [c for c in step.scores if c.admissible and np.isfinite(c.evidence_gain)]
    if step.decision is Decision.AMBIGUOUS:
        return f"ambiguous between {ranked[0].effect} and {ranked[1].effect}"
    return step.verdict


class Workflow:
    """The state of one discrepancy run: the records, the design and the current structure."""

    def __init__(
        self, data, heldout, base, effects, displacement, velocity, derivative, error, measured=None, accelerations=None
    ):
        self.data, self.heldout, self.error, self.effects = data, heldout, error, tuple(effects)
        #: The channels the records measure (an unmeasured state's column is estimated for the start).
        self.measured = tuple(data.state_names) if measured is None else tuple(measured)
        #: ``{velocity: column}``: the accelerometers among them, carried after the states in the records.
        self.accelerations = dict(accelerations or {})
        carried = set(self.accelerations.values())
        #: The training record's states, what the design regresses.
        self.view = data.with_states([n for n in data.state_names if n not in carried]) if carried else data
        view = self.view
        self.x, self.v = _pair(base, view.state_names, displacement, velocity)
        states = tuple(ca.SX.sym(n) for n in view.state_names)
        inputs = tuple(ca.SX.sym(n) for n in data.input_names)
        sym = dict(zip(view.state_names, states))
        x_amp = float(np.max(np.abs(data.column(self.x)))) if self.x else 1.0
        x_sym = sym[self.x] if self.x else ca.SX.sym("_unused")
        variants = [
            w
            for e in self.effects
            for w in e.variants(x_sym, sym[self.v], x_amp, float(np.max(np.abs(data.column(self.v)))))
        ]
        variants = [w for w in variants if self.x or not any(ca.depends_on(e, x_sym) for e in w.exprs)]
        n_terms = len(variants) + sum(map(len, base.values()))
        diff = get_differentiator(derivative).resolve(view.t, view.states, n_terms=n_terms)
        self.design = Design(base, variants, states, inputs, diff)
        self.structure = {s: [self.design.column(e) for e in terms] for s, terms in base.items()}
        for s, cols in self.structure.items():
            if None in cols or len(set(cols)) < len(cols):
                raise LibraryError(
                    expected(
                        f"base: state {s!r}",
                        "distinct terms (up to a constant factor)",
                        [str(e) for e in casadi_to_sympy(list(base[s]))],
                        "list each term once",
                    )
                )
        candidates = [(w, [self.design.column(e) for e in w.exprs]) for w in variants]
        self.candidates = [(w, cols) for w, cols in candidates if None not in cols]
        lib = self.design.library
        self.input_terms = [i for i, c in enumerate(self.structure[self.v]) if lib.terms[c].name in data.input_names]
        estimated = set(data.state_names) - set(self.measured)  # an unmeasured velocity's estimate has no noise level
        self.noise = {k: level for k, level in noise_levels(data).items() if k not in estimated}
        self.added_keys: set = set()  # (effect, where) of what the search has added

    def err(self, model, traj) -> float:
        """The held-out error measure of ``model`` on ``traj`` (over the measured channels)."""
        return heldout_error(model, self.observed(traj), self.error, self.design, self.v, self.measured)

    def observed(self, traj: Trajectory) -> Trajectory:
        """``traj`` as a model with accelerometers is validated on it: the measured channels alone (the states
        estimated from an accelerometer are not measurements); other records as they are."""
        if not self.accelerations:
            return traj
        return traj.with_states([n for n in traj.state_names if n in self.measured])

    def use_output_error(self, start, pairs, search_library: bool) -> None:
        """Prepare the output-error search from the equation-error fit ``start`` of the base structure: every
        record as evidence, the pairs, the candidates, kinematic base equations ``x' = v`` held exact."""
        data = self.data
        symbols = {s.name(): s for s in start.states}
        base_exprs = {eq.lhs: tuple(t.expr for t in eq.terms) for eq in start.equations}
        found = tuple(pairs) or tuple((p.x, p.v) for p in pairs_of(base_exprs, symbols) if p.x in symbols)
        velocity_of = dict(found)
        equations = tuple(
            Equation.kinematic(eq.lhs, symbols[velocity_of[eq.lhs]]) if eq.names == [velocity_of.get(eq.lhs)] else eq
            for eq in start.equations
        )
        self.structure_model = dataclasses.replace(start, equations=equations, kinematics=found)
        if self.accelerations:  # the accelerometers read the velocity equations' right-hand sides
            states = tuple(m for m in self.measured if m in symbols)
            sensors = tuple(AccelerationOutput(a, v) for v, a in self.accelerations.items())
            self.structure_model = dataclasses.replace(
                self.structure_model, measured=states, outputs=state_outputs(states) + sensors
            )
        self.pairs = pairs_of(base_exprs, symbols, found)
        if not self.pairs:
            raise DataError(
                expected(
                    "kinematics",
                    "a position-velocity pair to search (a base equation 'x: v' or kinematics={'x': 'v'})",
                    "none",
                    raw=True,
                )
            )
        every = {**symbols, **{s.name(): s for s in start.inputs}}
        named = catalogue_candidates(self.effects, self.pairs, every, [data, self.heldout])
        taken = {n for c in named for n in c.terms} | {n for eq in start.equations for n in eq.names}
        self.oe_candidates = named + (library_candidates(self.pairs, taken) if search_library else [])
        self.records = [data, self.heldout]
        self.input_names = tuple(data.input_names)
        self.settings = Settings()

    def scorer(self, model, records) -> Scorer:
        """``model``'s structure fitted by output error on ``records``."""
        return Scorer(model, records, self.measured, self.settings)

    def where(self, model):
        """Where ``model`` disagrees with the records (the first pair)."""
        self.design.weight = 1.0
        return locate(
            model, self.data, self.observed(self.heldout), self.design, self.x, self.v, self.error, self.measured
        )

    def residual_ratio(self, scorer: Scorer) -> float:
        """The largest residual standard deviation over the measured noise level, per record and state."""
        passes, R = scorer.engine.passes, scorer.residual
        out = 0.0
        for r, a, n in zip(scorer.records, passes.records.starts, passes.records.lengths):
            levels = noise_levels(r)
            for c, name in enumerate(scorer.measured):
                res = R[a : a + n, c]
                res = res[np.isfinite(res)]
                if res.size and levels.get(name, 0) > 0:
                    out = max(out, float(np.std(res)) / levels[name])
        return out

    def input_share(self, scorer: Scorer, segments: int = 16) -> float:
        """How far the residual follows the experiment, beyond chance (above 1: it does), the largest over records
        and states of two statistics, each over its critical value at a false-alarm rate of 1e-3:

        - the magnitude-squared coherence between each input and the residual (Welch, ``segments``
          segments; critical value ``1 - (1e-3 / (bins tests))^(1 / (segments - 1))``, Bonferroni over the
          frequency bins and the tests, one per record, state and input): dynamics the model misses, driven
          by the input;
        - the R^2 of the residual on simple functions of the simulated states (s, s^2, s^3, s|s|, sign s,
          products of two states; critical value ``max(0.2, 5 p / N_eff)`` for ``p`` regressors): a missing
          nonlinearity.

        Measurement noise of any colour, independent of the experiment, stays below 1."""
        from scipy.signal import coherence

        passes, X, R = scorer.engine.passes, scorer.simulated, scorer.residual
        tests = R.shape[1] * sum(
            r.inputs.shape[1] for r, n in zip(scorer.records, passes.records.lengths) if n >= 64 * segments
        )
        out = 0.0
        for r, a, n in zip(scorer.records, passes.records.starts, passes.records.lengths):
            if n < 64 * segments:
                continue
            A = _regressors(X[a : a + n])
            for c in range(R.shape[1]):
                y = R[a : a + n, c]
                if not (np.all(np.isfinite(y)) and np.all(np.isfinite(A))) or np.std(y) == 0:
                    continue
                fit = np.linalg.lstsq(A, y, rcond=None)[0]
                r2 = 1.0 - float(np.var(y - A @ fit)) / float(np.var(y))
                out = max(out, r2 / max(0.2, 5.0 * A.shape[1] / (n * effective_fraction(y))))
                for j in range(r.inputs.shape[1]):
                    _, coh = coherence(r.inputs[:, j], y, nperseg=n // segments, noverlap=0)
                    crit = 1.0 - (1e-3 / (coh.size * tests)) ** (1.0 / (segments - 1))
                    out = max(out, float(np.max(coh)) / crit)
        return out

    def noise_of(self, fit: dict) -> dict:
        """Noise standard deviation per measured state of a refit."""
        return {m: 1.0 / float(np.sqrt(w)) for m, w in zip(self.measured, fit["w"])}

    def with_terms(self, *scores) -> dict:
        """The current structure with the terms of ``scores`` added to the velocity equation."""
        trial = dict(self.structure)
        trial[self.v] = self.structure[self.v] + [self.design.library.index(n) for c in scores for n in c.terms]
        return trial
